//! The place-recognition service end to end over iceoryx2, in-process: the test publishes
//! frames and keyframes as the camera and the front-end would, the service (on a thread)
//! publishes one descriptor per keyframe. With a small ONNX model written by
//! `doorslam_place_recognition::onnx` (no big model needed), and with the files
//! deploy/setup builds (the NetVLAD model and the bag-of-words vocabulary).

use std::mem::MaybeUninit;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::time::{Duration, Instant};

use doorslam_ipc::{
    create_node, Feature, FrameHeader, Keyframe, KeyframeSource, PlaceDescriptor, Receiver, Sender,
    StereoFrame, Topic, MAX_KEYFRAME_FEATURES,
};
use doorslam_place_recognition::bow::default_vocabulary_path;
use doorslam_place_recognition::netvlad::default_model_path;
use doorslam_place_recognition::service::{
    describe_jobs, open_describer, run, BowFeatures, Job, PlaceConfig, PlaceReport,
};
use doorslam_place_recognition::{onnx, GrayImage, Method, PlaceRecognitionError};

/// A robot id of its own per test (iceoryx2 service names are machine-wide).
fn robot_id() -> String {
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "prtest{}x{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}

fn config(method: Method, model: &Path, robot: &str) -> PlaceConfig {
    PlaceConfig {
        robot: robot.to_string(),
        robot_index: 0,
        method,
        model: model.to_path_buf(),
        vocabulary: default_vocabulary_path(),
        match_threshold: method.default_threshold(),
        threads: 1,
        batch_size: 4,
        frame_cache: 8,
        temporal_exclusion: 10,
        bow_features: BowFeatures::default(),
    }
}

/// A textured test image (seeded noise blurred into blobs): every seed another place.
fn texture(seed: u64, width: usize, height: usize) -> GrayImage {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let coarse: Vec<f32> = (0..(width / 8 + 2) * (height / 8 + 2))
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 56) as f32
        })
        .collect();
    let cw = width / 8 + 2;
    let pixels = (0..height)
        .flat_map(|r| (0..width).map(move |c| (r, c)))
        .map(|(r, c)| {
            // Bilinear upsampling of the coarse grid: smooth blobs a small model can see.
            let (fy, fx) = (r as f32 / 8.0, c as f32 / 8.0);
            let (y0, x0) = (fy as usize, fx as usize);
            let (ty, tx) = (fy - y0 as f32, fx - x0 as f32);
            let at = |y: usize, x: usize| coarse[y * cw + x];
            let v = at(y0, x0) * (1.0 - ty) * (1.0 - tx)
                + at(y0, x0 + 1) * (1.0 - ty) * tx
                + at(y0 + 1, x0) * ty * (1.0 - tx)
                + at(y0 + 1, x0 + 1) * ty * tx;
            v as u8
        })
        .collect();
    GrayImage::new(width, height, pixels).unwrap()
}

/// `img` shifted right by `dx` pixels (edge repeated): the same place, camera moved.
fn shifted(img: &GrayImage, dx: usize) -> GrayImage {
    let pixels = (0..img.height)
        .flat_map(|r| (0..img.width).map(move |c| (r, c)))
        .map(|(r, c)| img.pixels[r * img.width + c.saturating_sub(dx)])
        .collect();
    GrayImage::new(img.width, img.height, pixels).unwrap()
}

/// A small model with the contract: [batch, 1, 24, 32] -> 128, a seeded random projection.
fn small_model(dir: &Path) -> PathBuf {
    let (h, w, d) = (24, 32, 128);
    let mut x = 12345u64;
    let weights: Vec<f32> = (0..h * w * d)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        })
        .collect();
    let bytes = onnx::image_head(1, h, w, d, &weights, &vec![0.0; d]).unwrap();
    let path = dir.join("small.onnx");
    std::fs::write(&path, bytes).unwrap();
    path
}

fn keyframe(robot: u32, id: u64, frame_seq: u64, features: &[[u8; 32]]) -> Box<Keyframe> {
    let mut all = [Feature::default(); MAX_KEYFRAME_FEATURES];
    for (f, d) in all.iter_mut().zip(features) {
        f.descriptor = *d;
    }
    Box::new(Keyframe {
        robot,
        source: KeyframeSource::VisualOdometry as u32,
        id,
        frame_seq,
        stamp_ns: frame_seq * 50_000_000,
        pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        n_features: features.len() as u32,
        reserved: 0,
        features: all,
    })
}

/// What the test plays, in order: frames (as the camera), keyframes (as the front-end,
/// after the frame they were made from).
enum Event {
    Frame(u64, GrayImage),
    Keyframe(Box<Keyframe>),
}

/// Checks one received descriptor and keeps its values.
fn take(d: &PlaceDescriptor, robot: u32, out: &mut Vec<(u64, Vec<f32>)>) {
    assert_eq!(d.robot, robot);
    assert!(d.values[d.dim as usize..].iter().all(|v| *v == 0.0));
    out.push((d.keyframe, d.values[..d.dim as usize].to_vec()));
}

/// Descriptors by keyframe id, the service's report, and (lockstep) the time from each
/// keyframe's publication to its descriptor's arrival.
type Played = (Vec<(u64, Vec<f32>)>, PlaceReport, Vec<Duration>);

/// Starts the service, waits until it listens, plays the script, waits for `expect`
/// descriptors (bounded), stops it. `lockstep`: after each keyframe, wait for its
/// descriptor before going on (and time it).
fn play(config: PlaceConfig, script: Vec<Event>, expect: usize, lockstep: bool) -> Played {
    let stop = AtomicBool::new(false);
    std::thread::scope(|scope| {
        let service = scope.spawn(|| run(&config, &stop));
        let (node, _) = create_node("place-service-test").unwrap();
        let frames = Sender::<StereoFrame>::new(&node, &config.robot, Topic::Frames).unwrap();
        let keyframes = Sender::<Keyframe>::new(&node, &config.robot, Topic::Keyframes).unwrap();
        let descriptors =
            Receiver::<PlaceDescriptor>::new(&node, &config.robot, Topic::Descriptors).unwrap();
        // Frames are lossy: publish only once the service subscribed.
        let start = Instant::now();
        while frames.receivers() == 0 || keyframes.receivers() == 0 {
            assert!(
                !service.is_finished() && start.elapsed() < Duration::from_secs(30),
                "the service did not subscribe (finished: {})",
                service.is_finished()
            );
            std::thread::sleep(Duration::from_millis(10));
        }
        let mut out: Vec<(u64, Vec<f32>)> = Vec::new();
        let mut latencies = Vec::new();
        for event in &script {
            match event {
                Event::Frame(seq, img) => {
                    let header = FrameHeader {
                        seq: *seq,
                        width: img.width as u32,
                        height: img.height as u32,
                        ..Default::default()
                    };
                    frames
                        .send_with(|slot: &mut MaybeUninit<StereoFrame>| {
                            StereoFrame::write(slot, header, &img.pixels, &img.pixels)
                        })
                        .unwrap();
                    // The camera's pace: the 2-deep frame queue is drained between frames.
                    std::thread::sleep(Duration::from_millis(25));
                }
                Event::Keyframe(kf) => {
                    let sent = Instant::now();
                    keyframes.send_copy(kf.as_ref()).unwrap();
                    if lockstep {
                        let s = descriptors
                            .recv_timeout(Duration::from_secs(20))
                            .unwrap()
                            .expect("a descriptor within 20 s");
                        latencies.push(sent.elapsed());
                        take(s.payload(), config.robot_index, &mut out);
                    }
                }
            }
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        while out.len() < expect && Instant::now() < deadline {
            if let Some(s) = descriptors
                .recv_timeout(Duration::from_millis(100))
                .unwrap()
            {
                take(s.payload(), config.robot_index, &mut out);
            }
        }
        // Nothing more than expected arrives.
        std::thread::sleep(Duration::from_millis(200));
        while let Some(s) = descriptors.try_recv().unwrap() {
            out.push((s.payload().keyframe, vec![]));
        }
        stop.store(true, Ordering::Relaxed);
        let report = service.join().unwrap().unwrap();
        out.sort_by_key(|d| d.0);
        (out, report, latencies)
    })
}

fn distance(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f32>()
        .sqrt()
}

#[test]
fn keyframes_in_descriptors_out_with_a_small_generated_model() {
    let dir = tempfile::tempdir().unwrap();
    let model = small_model(dir.path());
    let robot = robot_id();
    let mut cfg = config(Method::NetVlad, &model, &robot);
    cfg.frame_cache = 10;
    // Places 1..=3, place 1 seen again shifted (frame 13, keyframe 0); frames 20..=29 push
    // the early frames out of the 10-frame cache, so keyframe 9 (frame 2) finds no image.
    let place = |seed| texture(seed, 160, 120);
    let frame = |seq, img| Event::Frame(seq, img);
    let kf = |id, seq| Event::Keyframe(keyframe(0, id, seq, &[]));
    let mut script = vec![
        frame(0, place(1)),
        frame(1, place(2)),
        frame(2, place(3)),
        frame(13, shifted(&place(1), 6)),
        kf(0, 13),
        frame(20, place(120)),
        kf(1, 20),
    ];
    script.extend((21..30).map(|s| frame(s, place(100 + s))));
    script.push(kf(9, 2));
    // A burst (the inference thread batches what queued up), one of them twice, and
    // another robot's keyframe (refused).
    script.extend((21..30).map(|s| kf(s, s)));
    script.push(kf(21, 21));
    script.push(Event::Keyframe(keyframe(3, 40, 22, &[])));
    let (described, report, _) = play(cfg.clone(), script, 11, false);

    let ids: Vec<u64> = described.iter().map(|d| d.0).collect();
    assert_eq!(
        ids,
        [0, 1, 21, 22, 23, 24, 25, 26, 27, 28, 29],
        "{report:?}"
    );
    assert_eq!(report.described, 11);
    assert_eq!(report.frame_not_cached, 1, "{report:?}");
    assert_eq!(
        (report.duplicates, report.wrong_robot),
        (1, 1),
        "{report:?}"
    );
    assert!(
        report.largest_batch > 1 && report.largest_batch <= 4,
        "the burst was batched, at most batch_size at once: {report:?}"
    );

    // The descriptors are exactly what the describer gives offline (same preprocessing),
    // unit vectors of the wire length.
    let mut describer = open_describer(&cfg).unwrap();
    let jobs: Vec<Job> = [(0, shifted(&place(1), 6)), (1, place(120))]
        .into_iter()
        .map(|(k, img)| Job {
            keyframe: k,
            image: Some(img.into()),
            features: vec![],
        })
        .collect();
    let offline = describe_jobs(&mut describer, &jobs).unwrap();
    for (d, o) in described.iter().zip(&offline) {
        assert_eq!(d.1.len(), 128);
        assert!(distance(&d.1, &o.values) < 1e-5, "keyframe {}", d.0);
        assert!((d.1.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-4);
    }
}

#[test]
fn a_missing_corrupt_or_wrong_shape_model_stops_the_service_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let stop = AtomicBool::new(false);
    let missing = dir.path().join("missing.onnx");
    let err = run(&config(Method::NetVlad, &missing, &robot_id()), &stop).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("missing.onnx") && msg.contains("[batch, 1 or 3, H, W]"),
        "{msg}"
    );

    let corrupt = dir.path().join("corrupt.onnx");
    std::fs::write(&corrupt, b"\x08\x07 not a protobuf model").unwrap();
    let err = run(&config(Method::NetVlad, &corrupt, &robot_id()), &stop).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("corrupt.onnx") && msg.contains("expected an ONNX model"),
        "{msg}"
    );

    // Valid ONNX, wrong contract: [batch, 3] -> [batch, 2].
    let wrong = dir.path().join("wrong.onnx");
    std::fs::write(
        &wrong,
        onnx::projection_head(3, 2, &[0.5; 6], &[0.0; 2]).unwrap(),
    )
    .unwrap();
    let err = run(&config(Method::NetVlad, &wrong, &robot_id()), &stop).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("wrong.onnx") && msg.contains("expected input"),
        "{msg}"
    );

    // A vocabulary without its wire projection (the first file format).
    let mut cfg = config(Method::BagOfWords, &missing, &robot_id());
    cfg.vocabulary = dir.path().join("old.voc");
    let mut old = b"DSBOWV01".to_vec();
    old.extend(1u32.to_le_bytes());
    old.extend([0u8; 32]);
    old.extend(1.0f32.to_le_bytes());
    std::fs::write(&cfg.vocabulary, old).unwrap();
    let err = run(&cfg, &stop).unwrap_err();
    assert!(
        matches!(
            &err,
            doorslam_place_recognition::service::ServiceError::Model(
                PlaceRecognitionError::Vocabulary { .. }
            )
        ),
        "{err}"
    );
    assert!(err.to_string().contains("old.voc") && err.to_string().contains("projection"));
}

/// Frames of the KITTI 06 clip (real images, 1241 x 376).
fn kitti(frame: usize) -> GrayImage {
    let path = std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
        .join(format!("stereo/kitti06_0000-0050/image_0/{frame:06}.png"));
    let (w, h, pixels) = doorslam_dataset::read_gray_png(&path)
        .unwrap_or_else(|e| panic!("test data {}: {e}", path.display()));
    GrayImage::new(w as usize, h as usize, pixels).unwrap()
}

/// The real files (deploy/setup): the shifted view of a place is described nearer to it
/// than another place, through the service, for both methods.
fn real_files(method: Method) {
    let robot = robot_id();
    let cfg = config(method, &default_model_path(), &robot);
    if let Err(e) = open_describer(&cfg) {
        panic!("{e}\n(source the env file of deploy/setup, which builds the model and vocabulary)");
    }
    // Keyframes without features: the bag of words runs ORB on the cached image.
    let script = [kitti(0), shifted(&kitti(0), 12), kitti(50)]
        .into_iter()
        .enumerate()
        .flat_map(|(i, img)| {
            let i = i as u64;
            [
                Event::Frame(i, img),
                Event::Keyframe(keyframe(0, i, i, &[])),
            ]
        })
        .collect();
    let (d, report, latencies) = play(cfg, script, 3, true);
    assert_eq!(report.described, 3, "{report:?}");
    // For BENCHMARKS.md (--nocapture): keyframe published -> descriptor received.
    eprintln!(
        "{}: keyframe -> descriptor at 1241x376: {:?}",
        method.name(),
        latencies
    );
    let (same, other) = (distance(&d[0].1, &d[1].1), distance(&d[0].1, &d[2].1));
    assert!(
        same < other,
        "{}: shifted view at {same:.3}, another place at {other:.3}",
        method.name()
    );
}

#[test]
fn the_real_netvlad_model_through_the_service() {
    real_files(Method::NetVlad);
}

#[test]
fn the_real_vocabulary_through_the_service() {
    real_files(Method::BagOfWords);
}
