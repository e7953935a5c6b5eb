//! The systemd units in deploy/systemd pass `systemd-analyze verify`, with ExecStart
//! pointed at the binary under test (verify checks that the executable exists).

use std::process::Command;

#[test]
fn units_pass_systemd_analyze_verify() {
    let src = concat!(".", "/deploy/systemd");
    let tmp = tempfile::tempdir().unwrap();
    let mut units = Vec::new();
    for entry in std::fs::read_dir(src).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_owned();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.contains("Description="),
            "{} has no Description",
            path.display()
        );
        if text.contains("[Service]") {
            for key in [
                "Type=notify",
                "WatchdogSec=",
                "Restart=on-failure",
                "PartOf=doorslam.target",
            ] {
                assert!(text.contains(key), "{} lacks {key}", path.display());
            }
        }
        let text = text.replace("/usr/local/bin/doorslam", env!("CARGO_BIN_EXE_doorslam"));
        let out = tmp.path().join(&name);
        std::fs::write(&out, text).unwrap();
        units.push(out);
    }
    assert!(units.len() >= 5, "expected the target and four services");
    assert_start_order(src);
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg("--man=no")
        .args(&units)
        .env("SYSTEMD_LOG_LEVEL", "warning")
        .output()
        .expect(
            "systemd-analyze (Debian package systemd) must be installed: deploy/setup installs it",
        );
    let stderr = String::from_utf8_lossy(&out.stderr);
    // Only our units matter: ignore complaints about units of the host system.
    let ours: Vec<&str> = stderr.lines().filter(|l| l.contains("doorslam")).collect();
    assert!(
        out.status.success() && ours.is_empty(),
        "systemd-analyze verify:\n{stderr}"
    );
}

/// The robot's pipeline starts consumers first: backend, then frontend (it feeds the
/// back-end), then the camera (frames are lossy: nobody should miss the first ones); the
/// target starts all three, and the test stand-in never runs beside the real front-end.
fn assert_start_order(dir: &str) {
    let unit = |name: &str| std::fs::read_to_string(format!("{dir}/{name}")).unwrap();
    let key = |text: &str, key: &str| -> Vec<String> {
        text.lines()
            .filter_map(|l| l.strip_prefix(key)?.strip_prefix('='))
            .flat_map(|v| v.split_whitespace().map(String::from))
            .collect()
    };
    let frontend = unit("doorslam-frontend.service");
    assert!(frontend.contains("ExecStart=/usr/local/bin/doorslam service frontend "));
    assert!(key(&frontend, "After").contains(&"doorslam-backend.service".into()));
    assert!(key(&frontend, "Conflicts").contains(&"doorslam-sim-keyframes.service".into()));
    let camera = unit("doorslam-camera.service");
    for first in ["doorslam-backend.service", "doorslam-frontend.service"] {
        assert!(
            key(&camera, "After").contains(&first.into()),
            "camera after {first}"
        );
    }
    let target = unit("doorslam.target");
    for service in ["backend", "frontend", "camera"] {
        assert!(
            key(&target, "Wants").contains(&format!("doorslam-{service}.service")),
            "doorslam.target wants {service}"
        );
    }
    assert!(
        !key(&target, "Wants").contains(&"doorslam-sim-keyframes.service".into()),
        "the stand-in is not part of the robot"
    );
}
