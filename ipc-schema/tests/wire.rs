//! The inter-robot wire format: pinned bytes per kind, round trips, exact lengths, sizes
//! against the paper's Table II, and property tests over random and mutated encodings.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use doorslam_geometry::information::upper_from_diagonal;
use doorslam_geometry::key::symbol;
use doorslam_ipc::wire::*;
use proptest::prelude::*;

// ---- allocation accounting: bytes allocated by this thread ----

struct Counting;

thread_local! {
    static ALLOCATED: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = ALLOCATED.try_with(|a| a.set(a.get() + layout.size()));
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = ALLOCATED.try_with(|a| a.set(a.get() + new_size));
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Decodes, checking that the decoder allocated no more than a small multiple of the input
/// (the in-memory form of the largest item per wire byte is an ack range: 16 bytes for 2)
/// plus a constant: nothing is sized by an untrusted length.
fn decode_bounded(bytes: &[u8]) -> Result<Message, WireError> {
    let before = ALLOCATED.with(Cell::get);
    let result = Message::decode(bytes);
    let allocated = ALLOCATED.with(Cell::get) - before;
    assert!(
        allocated <= 8 * bytes.len() + 1024,
        "decoding {} bytes allocated {allocated} bytes",
        bytes.len()
    );
    result
}

// ---- samples ----

fn header(sender: &str, sequence: u64) -> Header {
    Header {
        sender: RobotId::new(sender).unwrap(),
        epoch: 3,
        sequence,
    }
}

fn key(robot: u8, index: u64) -> u64 {
    symbol(robot, index).unwrap()
}

fn pose(t: [f32; 3]) -> Pose {
    // 90° about z.
    let h = std::f32::consts::FRAC_1_SQRT_2;
    Pose::from_array([t[0], t[1], t[2], 0.0, 0.0, h, h]).unwrap()
}

fn compact(t: [f64; 3]) -> Estimate {
    let p = pose([t[0] as f32, t[1] as f32, t[2] as f32]);
    Estimate::Pose(CompactPose::quantize(p.se3()).unwrap())
}

fn information() -> Information {
    // σ = 0.01 rad for rotations, 0.05 m for translations.
    Information::from_upper(&upper_from_diagonal([1e4, 1e4, 1e4, 400.0, 400.0, 400.0])).unwrap()
}

fn descriptor(index: u64) -> Descriptor {
    let v: Vec<f32> = (0..DESCRIPTOR_DIM)
        .map(|i| ((i as f32 + index as f32) * 0.37).sin() / 8.0)
        .collect();
    Descriptor::quantize(key(0, index), &v).unwrap()
}

fn feature(i: usize) -> VerificationFeature {
    VerificationFeature::quantize(
        [100.5 + i as f32, 200.25],
        12.5 + i as f32 / 64.0,
        std::array::from_fn(|b| (b + i) as u8),
    )
    .unwrap()
}

fn camera() -> VerificationCamera {
    VerificationCamera::new(458.5, 457.25, 367.0, 248.5, 0.11).unwrap()
}

fn closure(i: u64) -> LoopClosure {
    LoopClosure {
        key_a: key(0, 120 + i),
        key_b: key(1, 45 + i),
        relative: pose([1.5, -0.25, 0.125]),
        information: information(),
        inliers: 37,
    }
}

/// One message of each kind, small enough to pin.
fn samples() -> Vec<Message> {
    vec![
        Message::new(
            header("alpha", 0),
            Hello {
                robot: 0,
                heard: Some(4),
                base: 130,
            },
        ),
        Message::new(
            header("alpha", 1),
            Descriptors {
                robot: 0,
                keyframes: 5..9,
                descriptors: vec![descriptor(7)],
            },
        ),
        Message::new(
            header("bravo", 2),
            Matches {
                matches: vec![Match {
                    query: key(0, 7),
                    candidate: key(1, 300),
                    distance: 0.125,
                }],
            },
        ),
        Message::new(
            header("bravo", 3),
            VerificationFeatures {
                key: key(1, 300),
                camera: camera(),
                features: vec![feature(0)],
            },
        ),
        Message::new(
            header("alpha", 4),
            LoopClosures {
                closures: vec![closure(0)],
            },
        ),
        Message::new(
            header("alpha", 5),
            PoseEstimates {
                optimization: 2,
                round: 9,
                stage: Stage::Pose,
                flags: ESTIMATES_CONVERGED,
                anchor: 0,
                estimates: vec![
                    PoseEstimate {
                        key: key(0, 120),
                        value: compact([10.0, 20.0, -1.5]),
                    },
                    PoseEstimate {
                        key: key(0, 121),
                        value: compact([10.5, 20.0, -1.5]),
                    },
                ],
            },
        ),
        Message::new(
            header("bravo", 6),
            Ack {
                epoch: 3,
                kind: Kind::Descriptors,
                next: 5,
                received: vec![std::ops::Range { start: 7, end: 9 }],
            },
        ),
        Message::new(
            header("alpha", 7),
            Body::SeparatorGraph(SeparatorGraph {
                origin: 1,
                version: 4,
                base: 3,
                removed: vec![(key(1, 40), key(1, 52))],
                edges: vec![graph_edge(40, key(1, 46)), graph_edge(46, key(2, 7))],
            }),
        ),
        Message::new(
            header("bravo", 8),
            Route {
                path: vec![0, 3, 1],
                subtree: 0b1_0010,
                session: 2,
            },
        ),
        Message::new(
            header("bravo", 9),
            TeamMap::Trajectory(Trajectory {
                anchor: 0,
                version: 5,
                total: 2,
                poses: [(0, [10.0, 20.0, -1.5]), (3, [10.5, 20.0, -1.5])]
                    .map(|(i, t)| {
                        let Estimate::Pose(p) = compact(t) else {
                            unreachable!()
                        };
                        (key(1, 300 + i), p)
                    })
                    .to_vec(),
            }),
        ),
    ]
}

/// An edge of robot b's condensed graph from its pose `a` (the information shared).
fn graph_edge(a: u64, b: u64) -> GraphEdge {
    let Estimate::Pose(relative) = compact([1.5, -0.25, 0.125]) else {
        unreachable!()
    };
    thread_local! {
        static INFORMATION: std::sync::Arc<Information> = std::sync::Arc::new(information());
    }
    GraphEdge {
        key_a: key(1, a),
        key_b: b,
        relative,
        information: INFORMATION.with(std::sync::Arc::clone),
    }
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

// The hello, in full: version 3, kind 1, sender "alpha" (5 bytes), epoch 3, sequence 0,
// robot 0, heard epoch 4 (as 5), base 130 (a two-byte varint). The descriptor and feature payloads are long, so those pins cover everything.
const PINNED: [&str; 10] = [
    // hello (14 bytes)
    "030105616c706861030000058201",
    // descriptors (147 bytes)
    concat!(
        "030205616c706861030100050401025ce3803a4317e8bd9a86818fabd3012f56727f7a654216e7bc",
        "9a85828facd4023057737f7a644115e6bb9985828facd4033058737f79644014e6ba99858290add5",
        "033158737f79634014e5ba98858290aed6043259747f79633f13e4b998848291aed7053359747f79",
        "623e12e3b897848291afd806345a747f78613d11e2b897848291b0",
    ),
    // matches (20 bytes)
    "030305627261766f030201000701ac020000003e",
    // verification features (72 bytes: the camera's five f32, then one feature: pixel
    // (1608, 3204) sixteenths, disparity 800 sixty-fourths, descriptor 0..31)
    concat!(
        "030405627261766f030301ac020040e54300a0e4430080b74300807843ae47e13d014806840c2003",
        "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f",
    ),
    // loop closures (90 bytes)
    concat!(
        "030505616c7068610304010078012d0000c03f000080be0000003e0000000000000000f304353ff3",
        "04353f0000c842003c0000003c00000000003c000000000000663200000000000000006632000000",
        "00000000000000663225",
    ),
    // pose estimates (57 bytes: two compact poses, the second key as a gap of 1; a
    // compact pose: translation (10, 20, -1.5) m in 0.1 mm as zigzag varints c09a0c
    // 80b518 afea01, then w the largest (03) and x, y, z in 24 bits: 0, 0, 0x7fffff (a
    // quarter turn about z))
    concat!(
        "030605616c706861030502090101000002",
        "78c09a0c80b518afea0103000000000000ffff7f",
        "01d0e80c80b518afea0103000000000000ffff7f",
    ),
    // ack (16 bytes)
    "030705627261766f0306030205010202",
    // separator graph (106 bytes): origin 1, version 4, base 3; removed b40-b52 (key a
    // zigzag 40, key b robot 1 and zigzag +12); two edges: b40 -> b46 with its information,
    // then b46 -> c7 with tag 0 (the same information).
    concat!(
        "030805616c70686103070104030150011802",
        "5001",
        "0cb0ea018727c41303000000000000ffff7f",
        "01",
        "0000c842003c0000003c00000000003c0000000000006632000000000000000066320000000000000000000066320c",
        "0207b0ea018727c41303000000000000ffff7f00",
    ),
    // route (16 bytes): path a -> d -> b (3 robots), subtree {b, e} = 0b10010, session 2
    "030905627261766f0308030003011202",
    // team map reply (57 bytes): tag 1, anchor 0, version 5, total 2, robot 1, two poses
    // (b300, then b303 as a gap of 3), compact as the pose estimates above
    concat!(
        "030a05627261766f03090100050201",
        "02ac02c09a0c80b518afea0103000000000000ffff7f",
        "03d0e80c80b518afea0103000000000000ffff7f",
    ),
];

#[test]
fn pinned_bytes_of_each_kind() {
    let samples = samples();
    assert_eq!(samples.len(), Kind::ALL.len());
    assert_eq!(
        PINNED.len(),
        samples.len(),
        "pin every kind; the last sample encodes as {}",
        samples
            .last()
            .map(|m| hex(&m.encode().unwrap()))
            .unwrap_or_default()
    );
    for (m, pin) in samples.iter().zip(PINNED) {
        let b = m.encode().unwrap();
        assert_eq!(hex(&b), pin, "{:?}", m.kind());
    }
    assert_eq!(
        samples[0].encode().unwrap(),
        [3, 1, 5, b'a', b'l', b'p', b'h', b'a', 3, 0, 0, 5, 0x82, 1]
    );
}

#[test]
fn round_trip_and_exact_length() {
    for m in samples() {
        let b = m.encode().unwrap();
        assert_eq!(m.encoded_len(), b.len(), "{:?}", m.kind());
        assert_eq!(decode_bounded(&b).unwrap(), m);
    }
}

#[test]
fn quantized_values_stay_close() {
    let d = descriptor(7);
    let v: Vec<f32> = (0..DESCRIPTOR_DIM)
        .map(|i| ((i as f32 + 7.0) * 0.37).sin() / 8.0)
        .collect();
    let err = d
        .to_f32()
        .iter()
        .zip(&v)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(err <= d.scale / 2.0 + 1e-7, "descriptor error {err}");
    let f = feature(3);
    assert_eq!(f.pixel_px(), [103.5, 200.25]);
    assert_eq!(f.disparity_px(), 12.5 + 3.0 / 64.0);
    let g = VerificationFeature::quantize([10.01, 20.02], 7.003, [0; 32]).unwrap();
    assert!((g.pixel_px()[0] - 10.01).abs() <= 1.0 / 32.0);
    assert!((g.pixel_px()[1] - 20.02).abs() <= 1.0 / 32.0);
    assert!((g.disparity_px() - 7.003).abs() <= 1.0 / 128.0);
    // Out of range or not finite: refused, naming the field.
    for (pixel, d) in [
        ([-1.0, 5.0], 3.0),
        ([5.0, 4096.0], 3.0),
        ([5.0, 5.0], 0.001),
        ([5.0, 5.0], 1024.0),
        ([f32::NAN, 5.0], 3.0),
    ] {
        let e = VerificationFeature::quantize(pixel, d, [0; 32]).unwrap_err();
        assert!(e.to_string().contains("feature"), "{e}");
    }
    for bad in [
        VerificationCamera::new(0.0, 1.0, 1.0, 1.0, 0.1),
        VerificationCamera::new(1.0, 1.0, f32::NAN, 1.0, 0.1),
        VerificationCamera::new(1.0, 1.0, 1.0, 1.0, -0.1),
    ] {
        assert!(bad.is_err(), "{bad:?}");
    }
    let info = information();
    let want = doorslam_geometry::information::matrix_from_upper(&upper_from_diagonal([
        1e4, 1e4, 1e4, 400.0, 400.0, 400.0,
    ]));
    assert!(((info.matrix() - want).amax() / want.amax()) < 1e-3);
    // A correlated information matrix survives its Cholesky factor's rounding.
    let mut m = want;
    m[(0, 3)] = 150.0;
    m[(3, 0)] = 150.0;
    m[(4, 5)] = -90.0;
    m[(5, 4)] = -90.0;
    let q = Information::from_matrix(&m).unwrap();
    assert!(((q.matrix() - m).amax() / m.amax()) < 1e-3);
    // Indefinite information is refused on the way out.
    m[(5, 5)] = -1.0;
    assert!(Information::from_matrix(&m).is_err());
    // Dynamic range: entries of L far below its largest become subnormal halves and lose
    // relative precision (0.3 % on Ω at a condition number of 1e10); beyond ~1e15 the
    // smallest direction would round to zero, and the matrix is refused.
    let diagonal = |d: f64| {
        doorslam_geometry::information::matrix_from_upper(&upper_from_diagonal([
            d, 1.0, 1.0, 1.0, 1.0, 1.0,
        ]))
    };
    let wide = Information::from_matrix(&diagonal(1e10)).unwrap();
    assert!((wide.matrix()[(1, 1)] - 1.0).abs() < 5e-3);
    assert!(Information::from_matrix(&diagonal(1e16)).is_err());
}

fn print_size(what: &str, bytes: usize, target: usize) {
    println!("{what}: {bytes} bytes (target <= {target})");
    assert!(bytes <= target, "{what}: {bytes} bytes > {target}");
}

#[test]
fn sizes_against_the_targets() {
    // Place descriptors: per keyframe in a batch of 10, header share included.
    let batch = Message::new(
        header("alpha", 1),
        Descriptors {
            robot: 0,
            keyframes: 100..110,
            descriptors: (100..110).map(descriptor).collect(),
        },
    );
    let n = batch.encoded_len();
    print_size("descriptor per keyframe (batch of 10)", n.div_ceil(10), 140);
    // One pose estimate, with a 7-character sender and a realistic key.
    let estimate = |sender: &str, n: u64| {
        Message::new(
            header(sender, 1000),
            PoseEstimates {
                optimization: 12,
                round: 40,
                stage: Stage::Pose,
                flags: 0,
                anchor: 0,
                estimates: (0..n)
                    .map(|i| PoseEstimate {
                        key: key(1, 4000 + i),
                        value: compact([120.0, -35.5, 12.0]),
                    })
                    .collect(),
            },
        )
        .encoded_len()
    };
    print_size(
        "pose estimate (one per message)",
        estimate("drone-b", 1),
        100,
    );
    print_size(
        "pose estimate (one per message, 32-char sender)",
        estimate(&"x".repeat(32), 1),
        100,
    );
    print_size(
        "pose estimate per pose (round of 20)",
        estimate("drone-b", 20).div_ceil(20),
        100,
    );
    // Loop closures.
    let closures = |sender: &str, n: u64| {
        Message::new(
            header(sender, 1000),
            LoopClosures {
                closures: (0..n)
                    .map(|i| LoopClosure {
                        key_a: key(0, 4000 + i),
                        key_b: key(1, 3000 + i),
                        inliers: 150,
                        ..closure(0)
                    })
                    .collect(),
            },
        )
        .encoded_len()
    };
    print_size(
        "loop closure (one per message)",
        closures("drone-a", 1),
        100,
    );
    print_size(
        "loop closure per closure (batch of 5, 32-char sender)",
        closures(&"x".repeat(32), 5).div_ceil(5),
        100,
    );
    // Verification packets: 38 bytes per feature after a 20-byte camera. The 32-byte ORB
    // descriptors alone of 1000 features are 32 kB, so 1000 features cannot fit 20 kB;
    // the front-end sends its best 500: 19.1 kB at most, with the longest sender id, the
    // largest key and the longest varints (the paper's packet was 59.5 kB).
    let packet = |sender: &str, sequence: u64, index: u64, n: usize| {
        let mut h = header(sender, sequence);
        h.epoch = u64::MAX;
        Message::new(
            h,
            VerificationFeatures {
                key: key(25, index),
                camera: camera(),
                features: (0..n).map(feature).collect(),
            },
        )
        .encoded_len()
    };
    let longest = |n| packet(&"x".repeat(32), u64::MAX, (1 << 56) - 1, n);
    print_size(
        "verification packet, 500 features, worst header",
        longest(500),
        19_100,
    );
    print_size(
        "verification packet, 500 features",
        packet("drone-b", 1000, 3000, 500),
        19_050,
    );
    print_size(
        "verification packet, 1000 features",
        packet("drone-b", 1000, 3000, 1000),
        38_050,
    );
    assert_eq!(longest(1000) - longest(999), FEATURE_BYTES);
    assert_eq!(FEATURE_BYTES, 38);
    assert_eq!(VERIFICATION_CAMERA_BYTES, 20);
}

#[test]
fn truncation_trailing_version_and_kind() {
    for m in samples() {
        let b = m.encode().unwrap();
        for len in 0..b.len() {
            let e = decode_bounded(&b[..len]).unwrap_err();
            assert!(
                matches!(e, WireError::Truncated { .. }),
                "{:?} cut at {len}: {e}",
                m.kind()
            );
        }
        let mut long = b.clone();
        long.push(0);
        assert_eq!(
            decode_bounded(&long),
            Err(WireError::TrailingBytes { count: 1 })
        );
        let mut v2 = b.clone();
        v2[0] = 4;
        let e = decode_bounded(&v2).unwrap_err();
        assert_eq!(
            e,
            WireError::UnknownVersion {
                found: 4,
                supported: 3
            }
        );
        assert_eq!(
            e.to_string(),
            "wire version 4 is not supported (this build speaks version 3)"
        );
        let mut k = b;
        k[1] = 0;
        assert_eq!(decode_bounded(&k), Err(WireError::UnknownKind { found: 0 }));
        k[1] = 200;
        assert_eq!(
            decode_bounded(&k),
            Err(WireError::UnknownKind { found: 200 })
        );
    }
}

#[test]
fn limits_are_checked_before_allocation() {
    // A feature count of 1000 with no features after it: refused as truncated, and the
    // decoder allocated nothing for them.
    let mut b = samples()[3].encode().unwrap();
    let count_at = b.len() - FEATURE_BYTES - 1;
    b.truncate(count_at);
    b.extend_from_slice(&[0xe8, 0x07]); // 1000
    assert!(matches!(
        decode_bounded(&b),
        Err(WireError::Truncated {
            field: "feature count",
            ..
        })
    ));
    // 1001 features: too long, whatever follows.
    b.truncate(count_at);
    b.extend_from_slice(&[0xe9, 0x07]);
    b.extend(std::iter::repeat_n(0, 1001 * FEATURE_BYTES));
    assert!(matches!(
        decode_bounded(&b),
        Err(WireError::TooLong {
            field: "feature count",
            len: 1001,
            max: 1000,
            ..
        })
    ));
    // The encoder refuses what the decoder would.
    let too_many = Message::new(
        header("bravo", 0),
        VerificationFeatures {
            key: key(1, 0),
            camera: camera(),
            features: vec![feature(0); MAX_FEATURES + 1],
        },
    );
    assert!(matches!(too_many.encode(), Err(WireError::TooLong { .. })));
    let plain_key = Message::new(
        header("bravo", 0),
        VerificationFeatures {
            key: 5,
            camera: camera(),
            features: vec![],
        },
    );
    assert!(matches!(plain_key.encode(), Err(WireError::Invalid { .. })));
    // Orders and ranges the decoder would refuse are refused on the way out too.
    let refused = |body: Body| {
        let m = Message::new(header("alpha", 0), body);
        assert!(
            matches!(m.encode(), Err(WireError::Invalid { .. })),
            "{m:?}"
        );
    };
    refused(Body::Hello(Hello {
        robot: 52,
        heard: None,
        base: 0,
    }));
    refused(Body::Hello(Hello {
        robot: 1,
        heard: Some(u64::MAX),
        base: 0,
    }));
    let (d1, d0) = (descriptor(1), descriptor(0));
    let batch = |descriptors| {
        Body::Descriptors(Descriptors {
            robot: 0,
            keyframes: 0..10,
            descriptors,
        })
    };
    refused(batch(vec![d1.clone(), d0]));
    refused(batch(vec![d1.clone(), d1.clone()]));
    refused(batch(vec![descriptor(10)]));
    let other_robot = Descriptor {
        key: key(1, 5),
        ..d1.clone()
    };
    refused(batch(vec![d1, other_robot]));
    refused(Body::Matches(Matches {
        matches: vec![Match {
            query: key(0, 1),
            candidate: key(1, 1),
            distance: f32::NAN,
        }],
    }));
    let r = |start, end| std::ops::Range { start, end };
    for received in [
        vec![r(5, 6)],
        vec![r(8, 8)],
        vec![r(7, 9), r(9, 10)],
        vec![r(9, 10), r(7, 8)],
    ] {
        refused(Body::Ack(Ack {
            epoch: 0,
            kind: Kind::Matches,
            next: 5,
            received,
        }));
    }
    // Oversized input is refused before anything is read.
    assert!(matches!(
        Message::decode(&vec![1; MAX_MESSAGE_BYTES + 1]),
        Err(WireError::TooLong {
            field: "message",
            ..
        })
    ));
}

#[test]
fn invalid_values_are_named() {
    // A quaternion vector part longer than 1 (no real w) in the pose estimate.
    let m = &samples()[5];
    let mut b = m.encode().unwrap();
    let q_at = b.len() - 9;
    b[q_at..].copy_from_slice(&[0xff, 0xff, 0x7f, 0xff, 0xff, 0x7f, 0xff, 0xff, 0x7f]);
    b[q_at - 1] = 3;
    let e = decode_bounded(&b).unwrap_err();
    assert!(
        matches!(
            e,
            WireError::Invalid {
                field: "estimate pose",
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("exceed 3/4"), "{e}");
    // A zero information factor in the closure.
    let mut b = samples()[4].encode().unwrap();
    let info_at = b.len() - 1 - INFORMATION_BYTES;
    b[info_at + 4..info_at + INFORMATION_BYTES].fill(0);
    let e = decode_bounded(&b).unwrap_err();
    assert!(
        matches!(
            e,
            WireError::Invalid {
                field: "closure information",
                ..
            }
        ),
        "{e}"
    );
    // A sender id with an upper-case letter.
    let mut b = samples()[0].encode().unwrap();
    b[3] = b'A';
    assert!(matches!(
        decode_bounded(&b),
        Err(WireError::Invalid {
            field: "sender",
            offset: 2,
            ..
        })
    ));
    assert!(RobotId::new("").is_err() && RobotId::new(&"a".repeat(33)).is_err());
}

#[test]
fn the_solve_stop_rides_in_the_estimate_flags_at_no_byte() {
    let with = |flags: u8| {
        let mut m = samples()[5].clone();
        if let Body::PoseEstimates(p) = &mut m.body {
            p.flags = flags;
        }
        m
    };
    let plain = with(0).encode().unwrap();
    let cut = with(SolveStop::flags(Some(SolveStop::MaxIterations)));
    let bytes = cut.encode().unwrap();
    assert_eq!(bytes.len(), plain.len());
    let back = decode_bounded(&bytes).unwrap();
    assert_eq!(back, cut);
    let Body::PoseEstimates(p) = &back.body else {
        panic!("{back:?}")
    };
    assert_eq!(
        SolveStop::from_flags(p.flags),
        Ok(Some(SolveStop::MaxIterations))
    );
    // The flags byte: version, kind, sender (length + 5), epoch, sequence, then
    // optimization, round and stage (one byte each here).
    let at = (0..plain.len())
        .find(|&i| {
            let mut b = plain.clone();
            b[i] = 0b1_0010;
            decode_bounded(&b).is_ok_and(|m| m == with(0b1_0010))
        })
        .expect("the flags byte");
    for (flags, why) in [
        (10u8 << 1, "names no stop"),
        (15 << 1, "names no stop"),
        (1 << 5, "unknown bits"),
        (1 << 7, "unknown bits"),
    ] {
        let mut b = plain.clone();
        b[at] = flags;
        let e = decode_bounded(&b).unwrap_err();
        assert!(
            matches!(
                e,
                WireError::Invalid {
                    field: "estimate flags",
                    ..
                }
            ),
            "{flags:#b}: {e}"
        );
        assert!(e.to_string().contains(why), "{flags:#b}: {e}");
        assert!(with(flags).encode().is_err(), "{flags:#b} encoded");
    }
}

#[test]
fn condensed_graph_edges_are_compact_and_informations_canonical() {
    // An edge that repeats the previous edge's information costs its keys, a compact pose
    // and one tag byte; one with its own information 46 bytes more (a LoopClosures entry
    // is 82 bytes).
    let graph = |n: u64, shared: bool| {
        Message::new(
            header("drone-b", 1000),
            Body::SeparatorGraph(SeparatorGraph {
                origin: 1,
                version: 7,
                base: 0,
                removed: vec![],
                edges: (0..n)
                    .map(|i| {
                        let mut e = graph_edge(4000 + 3 * i, key(1, 4003 + 3 * i));
                        if !shared {
                            let mut m = *information().matrix();
                            m[(0, 0)] += i as f64;
                            e.information =
                                std::sync::Arc::new(Information::from_matrix(&m).unwrap());
                        }
                        e
                    })
                    .collect(),
            }),
        )
        .encoded_len()
    };
    let repeated = graph(21, true) - graph(20, true);
    let own = graph(21, false) - graph(20, false);
    println!("condensed graph edge: {repeated} bytes, {own} with its own information");
    assert!(
        repeated <= 24 && own <= repeated + INFORMATION_BYTES,
        "{repeated} {own}"
    );
    // The tag is canonical: a repeated information sent in full, or tag 0 on the first
    // edge, is refused.
    let sample = &samples()[7];
    let b = sample.encode().unwrap();
    // The last edge: key a (1), key b (2), pose (17), tag (1); the first edge's information
    // just before it.
    let first_info = b.len() - 21 - INFORMATION_BYTES;
    let mut full = b[..b.len() - 1].to_vec();
    full.push(1);
    full.extend_from_slice(&b[first_info..first_info + INFORMATION_BYTES]);
    let e = decode_bounded(&full).unwrap_err();
    assert!(e.to_string().contains("repeats the previous"), "{e}");
    let mut zero = b.clone();
    zero[first_info - 1] = 0;
    let e = decode_bounded(&zero).unwrap_err();
    assert!(
        matches!(
            e,
            WireError::Invalid {
                field: "graph information tag",
                ..
            }
        ),
        "{e}"
    );
}

// ---- property tests ----

fn arb_key() -> impl Strategy<Value = u64> {
    (
        0u8..52,
        prop_oneof![0u64..5000, 0..=doorslam_geometry::key::MAX_INDEX],
    )
        .prop_map(|(r, i)| key(r, i))
}

fn arb_pose() -> impl Strategy<Value = Pose> {
    (
        prop::array::uniform3(-1e4f32..1e4),
        prop::array::uniform4(-1f32..1.0),
    )
        .prop_filter_map("degenerate quaternion", |(t, q)| {
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            (n > 0.1).then(|| {
                Pose::from_array([t[0], t[1], t[2], q[0] / n, q[1] / n, q[2] / n, q[3] / n])
                    .unwrap()
            })
        })
}

fn arb_information() -> impl Strategy<Value = Information> {
    (
        prop::array::uniform6(0.1f64..1000.0),
        prop::collection::vec(-10f64..10.0, 15),
    )
        .prop_filter_map("ill-conditioned", |(d, off)| {
            let mut l = doorslam_geometry::TangentMatrix::zeros();
            let mut k = 0;
            for r in 0..6 {
                l[(r, r)] = d[r];
                for c in 0..r {
                    l[(r, c)] = off[k];
                    k += 1;
                }
            }
            Information::from_matrix(&(l * l.transpose())).ok()
        })
}

fn arb_descriptors() -> impl Strategy<Value = Descriptors> {
    (
        0u8..52,
        0u64..100_000,
        0u64..3,
        prop::collection::vec(
            (1u64..300, 0f32..1.0, prop::array::uniform32(any::<i8>())),
            0..12,
        ),
    )
        .prop_map(|(robot, start, after, entries)| {
            let mut index = start;
            let descriptors: Vec<_> = entries
                .into_iter()
                .enumerate()
                .map(|(i, (step, scale, v))| {
                    // The first descriptor may be the range's first keyframe.
                    index += if i == 0 { step - 1 } else { step };
                    Descriptor {
                        key: key(robot, index),
                        scale,
                        values: std::array::from_fn(|i| v[i % 32].wrapping_add(i as i8)),
                    }
                })
                .collect();
            let end = if descriptors.is_empty() {
                start
            } else {
                index + 1
            } + after;
            Descriptors {
                robot,
                keyframes: start..end,
                descriptors,
            }
        })
}

fn arb_feature() -> impl Strategy<Value = VerificationFeature> {
    (
        prop::array::uniform2(any::<u16>()),
        1..=u16::MAX,
        prop::array::uniform32(any::<u8>()),
    )
        .prop_map(|(pixel, disparity, descriptor)| VerificationFeature {
            pixel,
            disparity,
            descriptor,
        })
}

fn arb_camera() -> impl Strategy<Value = VerificationCamera> {
    (
        1f32..3000.0,
        1f32..3000.0,
        -100f32..3000.0,
        -100f32..3000.0,
        0.01f32..2.0,
    )
        .prop_map(|(fx, fy, cx, cy, b)| VerificationCamera::new(fx, fy, cx, cy, b).unwrap())
}

fn arb_body() -> impl Strategy<Value = Body> {
    prop_oneof![
        (0u8..52, prop::option::of(0u64..u64::MAX), any::<u64>())
            .prop_map(|(robot, heard, base)| Body::Hello(Hello { robot, heard, base })),
        arb_descriptors().prop_map(Body::Descriptors),
        prop::collection::vec((arb_key(), arb_key(), 0f32..2.0), 0..20).prop_map(|m| {
            Body::Matches(Matches {
                matches: m
                    .into_iter()
                    .map(|(query, candidate, distance)| Match {
                        query,
                        candidate,
                        distance,
                    })
                    .collect(),
            })
        }),
        (
            arb_key(),
            arb_camera(),
            prop::collection::vec(arb_feature(), 0..40)
        )
            .prop_map(|(key, camera, features)| {
                Body::VerificationFeatures(VerificationFeatures {
                    key,
                    camera,
                    features,
                })
            }),
        prop::collection::vec(
            (
                arb_key(),
                arb_key(),
                arb_pose(),
                arb_information(),
                any::<u32>()
            ),
            0..5
        )
        .prop_map(|c| {
            Body::LoopClosures(LoopClosures {
                closures: c
                    .into_iter()
                    .map(
                        |(key_a, key_b, relative, information, inliers)| LoopClosure {
                            key_a,
                            key_b,
                            relative,
                            information,
                            inliers,
                        },
                    )
                    .collect(),
            })
        }),
        (
            0u8..52,
            1u64..u64::MAX,
            prop::collection::vec((0u64..100_000, arb_key()), 0..4),
            prop::collection::vec(
                (
                    0u64..100_000,
                    arb_key(),
                    arb_pose(),
                    arb_information(),
                    any::<bool>()
                ),
                0..6
            )
        )
            .prop_map(|(origin, version, removed, edges)| {
                // An update (base below version) when the draw removes something.
                let base = if removed.is_empty() { 0 } else { version / 2 };
                let removed = if base == 0 {
                    vec![]
                } else {
                    removed
                        .into_iter()
                        .map(|(a, b)| (key(origin, a), b))
                        .collect()
                };
                let mut out: Vec<GraphEdge> = Vec::new();
                for (a, key_b, pose, information, repeat) in edges {
                    let information = match out.last() {
                        Some(l) if repeat || l.information.parts() == information.parts() => {
                            std::sync::Arc::clone(&l.information)
                        }
                        _ => std::sync::Arc::new(information),
                    };
                    out.push(GraphEdge {
                        key_a: key(origin, a),
                        key_b,
                        relative: CompactPose::quantize(pose.se3()).unwrap(),
                        information,
                    });
                }
                Body::SeparatorGraph(SeparatorGraph {
                    origin,
                    version,
                    base,
                    removed,
                    edges: out,
                })
            }),
        (
            prop::collection::btree_set(0u8..52, 1..8),
            0u64..(1 << 52),
            any::<u64>()
        )
            .prop_map(|(robots, subtree, session)| Body::Route(Route {
                path: robots.into_iter().rev().collect(),
                subtree,
                session,
            })),
        (
            any::<bool>(),
            any::<u64>(),
            0u8..52,
            prop::collection::btree_set(0u64..100_000, 0..10),
            prop::collection::vec(arb_pose(), 10)
        )
            .prop_map(|(request, version, robot, indices, poses)| {
                if request {
                    return Body::TeamMap(TeamMap::Request { known: version });
                }
                let poses: Vec<(u64, CompactPose)> = indices
                    .into_iter()
                    .zip(poses)
                    .map(|(i, p)| (key(robot, i), CompactPose::quantize(p.se3()).unwrap()))
                    .collect();
                Body::TeamMap(TeamMap::Trajectory(Trajectory {
                    anchor: robot,
                    version,
                    total: poses.len() as u64 + version % 3,
                    poses,
                }))
            }),
        (
            any::<u64>(),
            any::<u64>(),
            0u8..3,
            (any::<bool>(), 0u8..52, 0u8..52, 0u8..10),
            prop::collection::btree_set(0u64..100_000, 0..10),
            prop::collection::vec((arb_pose(), prop::array::uniform9(-2.0f64..2.0)), 10)
        )
            .prop_map(
                |(
                    optimization,
                    round,
                    stage,
                    (converged, anchor, robot, stop),
                    indices,
                    values,
                )| {
                    let stage = [Stage::Rotation, Stage::Pose, Stage::Refine][stage as usize];
                    let stop = SolveStop::from_flags(stop << 1).unwrap();
                    Body::PoseEstimates(PoseEstimates {
                        optimization,
                        round,
                        stage,
                        flags: SolveStop::flags(stop)
                            | if converged { ESTIMATES_CONVERGED } else { 0 },
                        anchor,
                        estimates: indices
                            .into_iter()
                            .zip(values)
                            .map(|(i, (pose, m))| PoseEstimate {
                                key: key(robot, i),
                                value: match stage {
                                    Stage::Rotation => Estimate::Rotation(
                                        RelaxedRotation::quantize(&std::array::from_fn(|r| {
                                            std::array::from_fn(|c| m[3 * r + c])
                                        }))
                                        .unwrap(),
                                    ),
                                    _ => Estimate::Pose(CompactPose::quantize(pose.se3()).unwrap()),
                                },
                            })
                            .collect(),
                    })
                }
            ),
        (
            any::<u64>(),
            0usize..Kind::ALL.len(),
            0u64..1_000_000,
            prop::collection::vec((1u64..100, 1u64..100), 0..MAX_ACK_RANGES)
        )
            .prop_map(|(epoch, kind, next, gaps)| {
                let mut end = next;
                let received = gaps
                    .into_iter()
                    .map(|(gap, len)| {
                        let r = end + gap..end + gap + len;
                        end = r.end;
                        r
                    })
                    .collect();
                Body::Ack(Ack {
                    epoch,
                    kind: Kind::ALL[kind],
                    next,
                    received,
                })
            }),
    ]
}

fn arb_message() -> impl Strategy<Value = Message> {
    ("[a-z0-9_-]{1,32}", any::<u64>(), any::<u64>(), arb_body()).prop_map(
        |(sender, epoch, sequence, body)| Message {
            header: Header {
                sender: RobotId::new(&sender).unwrap(),
                epoch,
                sequence,
            },
            body,
        },
    )
}

/// A decoded message re-encodes to the bytes it came from (the encoding is canonical).
fn check_decode(bytes: &[u8]) {
    if let Ok(m) = decode_bounded(bytes) {
        assert_eq!(m.encode().unwrap(), bytes);
        assert_eq!(m.encoded_len(), bytes.len());
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn random_messages_round_trip(m in arb_message()) {
        let b = m.encode().unwrap();
        prop_assert_eq!(m.encoded_len(), b.len());
        prop_assert_eq!(decode_bounded(&b).unwrap(), m);
    }

    #[test]
    fn truncated_and_extended_encodings_are_refused(
        m in arb_message(),
        extra in prop::collection::vec(any::<u8>(), 1..16),
    ) {
        let b = m.encode().unwrap();
        for len in 0..b.len() {
            prop_assert!(decode_bounded(&b[..len]).is_err());
        }
        let mut long = b.clone();
        long.extend_from_slice(&extra);
        prop_assert_eq!(
            decode_bounded(&long),
            Err(WireError::TrailingBytes { count: extra.len() })
        );
    }

    #[test]
    fn mutated_encodings_never_panic(
        m in arb_message(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..6),
    ) {
        let mut b = m.encode().unwrap();
        for (at, x) in flips {
            let i = at.index(b.len());
            b[i] ^= x;
        }
        check_decode(&b);
    }

    #[test]
    fn garbage_never_panics(
        kind in 0u8..12,
        tail in prop::collection::vec(any::<u8>(), 0..600),
    ) {
        let mut b = vec![WIRE_VERSION, kind];
        b.extend_from_slice(&tail);
        check_decode(&b);
        check_decode(&tail);
    }
}

proptest! {
    /// The stated bounds of the back-end's compact estimates: ≤ 0.05 mm per axis,
    /// ≤ 1e-6 rad of rotation, ≤ 3.1e-5 per relaxed-rotation entry.
    #[test]
    fn compact_estimates_stay_within_their_stated_error(p in arb_pose(), m in prop::array::uniform9(-1.9f64..1.9)) {
        let c = CompactPose::quantize(p.se3()).unwrap();
        let dt = (c.se3().translation.vector - p.se3().translation.vector).amax();
        prop_assert!(dt <= 0.5e-4 + 1e-9, "translation error {dt}");
        let da = c.se3().rotation.angle_to(&p.se3().rotation);
        prop_assert!(da <= COMPACT_ROTATION_ERROR_RAD, "rotation error {da}");
        let mat: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|k| m[3 * r + k]));
        let q = RelaxedRotation::quantize(&mat).unwrap().matrix();
        for r in 0..3 {
            for k in 0..3 {
                prop_assert!((q[r][k] - mat[r][k]).abs() <= RELAXED_ROTATION_STEP / 2.0 + 1e-12);
            }
        }
    }
}
