//! Byte-exact checks against encodings that are not ours: `fixtures/wire.json`, written by
//! `fixtures/make_fixtures.py` from rosbags' CDR serializer, RIHS01 hashes and ros2msg
//! definitions (Jazzy) and xxhash's XXH3-128. The messages below are the script's, field
//! for field. A second test re-runs the script in `--check` mode when the set-up's venv
//! has rosbags, so the committed fixture cannot drift from its reference.

use std::path::PathBuf;

use doorslam_ros2_wire::msgs::*;
use doorslam_ros2_wire::rmw::gid;
use doorslam_ros2_wire::types;
use doorslam_ros2_wire::RosMessage;

fn fixture() -> serde_json::Value {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/wire.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap()
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

fn time(sec: i32, nanosec: u32) -> Time {
    Time { sec, nanosec }
}

fn header(sec: i32, nanosec: u32, frame: &str) -> Header {
    Header {
        stamp: time(sec, nanosec),
        frame_id: frame.into(),
    }
}

fn pose(x: f64, y: f64, z: f64, qx: f64, qy: f64, qz: f64, qw: f64) -> Pose {
    Pose {
        position: Point { x, y, z },
        orientation: Quaternion {
            x: qx,
            y: qy,
            z: qz,
            w: qw,
        },
    }
}

#[allow(clippy::too_many_arguments)]
fn pose_stamped(
    sec: i32,
    frame: &str,
    x: f64,
    y: f64,
    z: f64,
    qx: f64,
    qy: f64,
    qz: f64,
    qw: f64,
) -> PoseStamped {
    PoseStamped {
        header: header(sec, 250_000_000, frame),
        pose: pose(x, y, z, qx, qy, qz, qw),
    }
}

fn color(r: f32, g: f32, b: f32, a: f32) -> ColorRgba {
    ColorRgba { r, g, b, a }
}

fn point(x: f64, y: f64, z: f64) -> Point {
    Point { x, y, z }
}

fn marker(id: i32, ns: &str, col: ColorRgba, points: Vec<Point>, colors: Vec<ColorRgba>) -> Marker {
    Marker {
        header: header(12, 5, "team"),
        ns: ns.into(),
        id,
        kind: Marker::LINE_LIST,
        action: Marker::ADD,
        pose: pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        scale: Vector3 {
            x: 0.125,
            y: 0.0,
            z: 0.0,
        },
        color: col,
        points,
        colors,
        ..Marker::default()
    }
}

fn transform(child: &str, t: [f64; 3], q: [f64; 4]) -> TransformStamped {
    TransformStamped {
        header: header(42, 9, "team"),
        child_frame_id: child.into(),
        transform: Transform {
            translation: Vector3 {
                x: t[0],
                y: t[1],
                z: t[2],
            },
            rotation: Quaternion {
                x: q[0],
                y: q[1],
                z: q[2],
                w: q[3],
            },
        },
    }
}

/// The script's cases: (name, type name, our encoding).
fn ours() -> Vec<(&'static str, &'static str, Vec<u8>)> {
    vec![
        (
            "time",
            Time::TYPE.name,
            time(1_700_000_000, 123_456_789).to_cdr().unwrap(),
        ),
        (
            "header",
            Header::TYPE.name,
            header(-3, 7, "team").to_cdr().unwrap(),
        ),
        (
            "pose_stamped",
            PoseStamped::TYPE.name,
            pose_stamped(42, "team", 1.5, -2.25, 0.125, 0.0, 0.0, 0.6, 0.8)
                .to_cdr()
                .unwrap(),
        ),
        (
            "path",
            Path::TYPE.name,
            Path {
                header: header(44, 0, "team"),
                poses: vec![
                    pose_stamped(42, "team", 1.5, -2.25, 0.125, 0.0, 0.0, 0.6, 0.8),
                    pose_stamped(43, "team", 2.5, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
                    pose_stamped(44, "team", 3.0, 0.5, -0.5, 0.5, 0.5, 0.5, 0.5),
                ],
            }
            .to_cdr()
            .unwrap(),
        ),
        (
            "path_empty",
            Path::TYPE.name,
            Path {
                header: header(1, 2, "ab"),
                poses: vec![],
            }
            .to_cdr()
            .unwrap(),
        ),
        (
            "tf",
            TfMessage::TYPE.name,
            TfMessage {
                transforms: vec![
                    transform("a/odom", [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]),
                    transform("bc/odom", [-1.0, 0.25, 0.0], [0.0, 0.6, 0.0, 0.8]),
                ],
            }
            .to_cdr()
            .unwrap(),
        ),
        (
            "marker_array",
            MarkerArray::TYPE.name,
            MarkerArray {
                markers: vec![
                    marker(
                        0,
                        "kept",
                        color(0.0, 0.75, 0.0, 1.0),
                        vec![point(0.0, 1.0, 2.0), point(3.0, 4.0, 5.0)],
                        vec![],
                    ),
                    marker(
                        1,
                        "rejected",
                        color(1.0, 0.0, 0.0, 0.5),
                        vec![point(-1.0, 0.5, 0.0), point(1.0, -0.5, 0.0)],
                        vec![color(1.0, 0.0, 0.0, 0.5), color(0.5, 0.0, 0.0, 0.5)],
                    ),
                ],
            }
            .to_cdr()
            .unwrap(),
        ),
        (
            "diagnostic_array",
            DiagnosticArray::TYPE.name,
            DiagnosticArray {
                header: header(50, 0, ""),
                status: vec![DiagnosticStatus {
                    level: DiagnosticStatus::OK,
                    name: "a/team_link".into(),
                    message: "sent".into(),
                    hardware_id: "a".into(),
                    values: vec![
                        KeyValue {
                            key: "b/pose/wire_bytes".into(),
                            value: "1234".into(),
                        },
                        KeyValue {
                            key: "b/pose/messages".into(),
                            value: "7".into(),
                        },
                    ],
                }],
            }
            .to_cdr()
            .unwrap(),
        ),
    ]
}

#[test]
fn cdr_encodings_match_rosbags_byte_for_byte() {
    let f = fixture();
    let cases = f["cdr"].as_array().unwrap();
    let ours = ours();
    assert_eq!(cases.len(), ours.len(), "every fixture case is built here");
    for (name, ty, bytes) in ours {
        let case = cases
            .iter()
            .find(|c| c["name"] == name)
            .unwrap_or_else(|| panic!("no fixture {name}"));
        assert_eq!(case["type"], ty, "{name}");
        assert_eq!(case["hex"].as_str().unwrap(), hex(&bytes), "{name}");
    }
}

#[test]
fn type_hashes_match_rosbags_for_every_type() {
    let f = fixture();
    let hashes = f["hashes"].as_object().unwrap();
    assert_eq!(hashes.len(), types::ALL.len());
    for t in types::ALL {
        assert_eq!(
            hashes[t.name].as_str().unwrap(),
            t.type_hash(),
            "{}",
            t.name
        );
    }
}

#[test]
fn schema_texts_match_rosbags_definitions() {
    let f = fixture();
    let schemas = f["schemas"].as_object().unwrap();
    for t in types::ALL {
        assert_eq!(
            schemas[t.name].as_str().unwrap(),
            t.schema_text(),
            "{}",
            t.name
        );
    }
}

#[test]
fn gids_match_xxhash() {
    let f = fixture();
    for case in f["gids"].as_array().unwrap() {
        let token = case["token"].as_str().unwrap();
        assert_eq!(case["gid"].as_str().unwrap(), hex(&gid(token)), "{token}");
    }
}

/// The committed fixture is what the reference encoders give now (needs the set-up's
/// venv with rosbags and xxhash; skipped with the reason printed otherwise).
#[test]
fn fixture_is_regenerated_by_its_script() {
    let home = std::env::var_os("DOORSLAM_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/doorslam")));
    let Some(python) = home
        .map(|h| h.join("venv/bin/python"))
        .filter(|p| p.is_file())
    else {
        println!("skipped: no set-up venv (run deploy/setup)");
        return;
    };
    let has = std::process::Command::new(&python)
        .args(["-c", "import rosbags, xxhash"])
        .status()
        .is_ok_and(|s| s.success());
    if !has {
        println!(
            "skipped: {} has no rosbags/xxhash (run deploy/setup)",
            python.display()
        );
        return;
    }
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/make_fixtures.py");
    let out = std::process::Command::new(&python)
        .arg(&script)
        .arg("--check")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
