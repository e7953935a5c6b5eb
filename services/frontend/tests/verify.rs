//! Geometric verification on rendered views: the same place seen from two poses is accepted
//! with the right relative pose; views of unrelated places and malformed packets are refused.

use doorslam_dataset::StereoCalibration;
use doorslam_frontend::{verify, Feature, Gray, Rejection, StereoVo, VerifyConfig, VoConfig};
use doorslam_geometry::{LieGroup, SE3};
use doorslam_hil::flights::{simulate_team, FlightConfig};
use doorslam_hil::{render_stereo, StereoCamera, World};
use nalgebra::{Translation3, UnitQuaternion, Vector3};

fn calib(camera: &StereoCamera) -> StereoCalibration {
    StereoCalibration {
        fx: camera.fx(),
        fy: camera.fy(),
        cx: camera.cx(),
        cy: camera.cy(),
        baseline_m: camera.baseline(),
    }
}

/// The keyframe features the odometry makes of the view from `pose` in `world`.
fn features_at(world: &World, camera: &StereoCamera, pose: &SE3) -> Vec<Feature> {
    let pair = render_stereo(world, camera, pose);
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    let mut vo = StereoVo::new(calib(camera), VoConfig::default()).unwrap();
    let left = Gray::new(w, h, pair.left.pixels()).unwrap();
    let right = Gray::new(w, h, pair.right.pixels()).unwrap();
    let result = vo.process(0, 0, &left, &right).unwrap();
    result
        .keyframe
        .expect("a textured view makes a keyframe")
        .features
}

fn poses(seed: u64) -> (World, Vec<SE3>) {
    let config = FlightConfig {
        robots: 1,
        frames: 40,
        seed,
        ..FlightConfig::default()
    };
    let world = World::town(seed);
    let team = simulate_team(&world, &StereoCamera::euroc_like(), &config).unwrap();
    (world, team.flights[0].poses.clone())
}

#[test]
fn the_same_place_from_another_pose_is_accepted_with_the_true_relative_pose() {
    let camera = StereoCamera::euroc_like();
    let (world, flight) = poses(3);
    let local_pose = flight[10];
    // Another robot half a metre to the side, 0.3 m back, turned by 8 degrees.
    let offset = SE3::from_parts(
        Translation3::new(0.5, 0.1, -0.3),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 8f64.to_radians()),
    );
    let remote_pose = local_pose * offset;
    let local = features_at(&world, &camera, &local_pose);
    let remote = features_at(&world, &camera, &remote_pose);
    let start = std::time::Instant::now();
    let c = calib(&camera);
    let v = verify(&c, &local, &c, &remote, &VerifyConfig::default()).unwrap();
    let ms = start.elapsed().as_secs_f64() * 1e3;
    let truth = remote_pose.inverse() * local_pose;
    let err = (truth.inverse() * v.relative).log();
    let (rot_deg, trans_m) = (
        err.fixed_rows::<3>(0).norm().to_degrees(),
        err.fixed_rows::<3>(3).norm(),
    );
    let nees = (err.transpose() * v.information * err)[0];
    eprintln!(
        "true pair: {} matches, {} inliers, error {rot_deg:.3} deg / {:.1} mm, NEES {nees:.1}, {ms:.1} ms",
        v.matches,
        v.inliers,
        trans_m * 1e3
    );
    assert!(v.inliers >= 50, "{} inliers", v.inliers);
    assert!(
        rot_deg < 0.5 && trans_m < 0.05,
        "error {rot_deg} deg, {trans_m} m"
    );
    doorslam_geometry::check_information(
        &v.information,
        6,
        doorslam_geometry::InformationCheck::PositiveDefinite,
    )
    .unwrap();
}

#[test]
fn unrelated_places_and_malformed_packets_are_refused() {
    let camera = StereoCamera::euroc_like();
    let (world_a, flight_a) = poses(3);
    let (world_b, flight_b) = poses(11);
    let c = calib(&camera);
    let config = VerifyConfig::default();
    let local = features_at(&world_a, &camera, &flight_a[10]);
    // Other towns, other streets: several unrelated views, all refused.
    for k in [0, 15, 30] {
        let remote = features_at(&world_b, &camera, &flight_b[k]);
        let outcome = verify(&c, &local, &c, &remote, &config);
        eprintln!("unrelated view {k}: {outcome:?}");
        match outcome {
            Err(
                Rejection::TooFewMatches { .. }
                | Rejection::TooFewInliers { .. }
                | Rejection::NoPose,
            ) => {}
            other => panic!("unrelated view {k} accepted or refused oddly: {other:?}"),
        }
    }
    assert!(matches!(
        verify(&c, &local, &c, &[], &config),
        Err(Rejection::TooFewFeatures { remote: 0, .. })
    ));
    let mut bad = local.clone();
    bad[3].point[2] = f32::NAN;
    assert!(matches!(
        verify(&c, &local, &c, &bad, &config),
        Err(Rejection::BadFeature { index: 3 })
    ));
}

#[test]
fn the_wire_packet_verifies_like_the_full_features_even_across_cameras() {
    use doorslam_frontend::packet::{packet_file_bytes, packet_from_file_bytes};
    use doorslam_frontend::{from_packet, to_packet, MAX_PACKET_FEATURES};
    use doorslam_ipc::wire::{Message, RobotId};

    let (world, flight) = poses(3);
    let local_camera = StereoCamera::euroc_like();
    // The remote robot flies another camera (larger sensor, other principal point, a
    // 25 cm baseline; a similar focal length, as single-level ORB descriptors do not match
    // across scales): the packet carries its calibration.
    let remote_camera = StereoCamera::new(900, 600, 470.0, 468.0, 452.5, 290.25, 0.25).unwrap();
    let local_pose = flight[10];
    let offset = SE3::from_parts(
        Translation3::new(-0.4, 0.05, 0.6),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -6f64.to_radians()),
    );
    let remote_pose = local_pose * offset;
    let local = features_at(&world, &local_camera, &local_pose);
    let remote = features_at(&world, &remote_camera, &remote_pose);
    let (lc, rc) = (calib(&local_camera), calib(&remote_camera));
    let truth = remote_pose.inverse() * local_pose;
    let error = |v: &doorslam_frontend::Verified| {
        let e = (truth.inverse() * v.relative).log();
        (
            e.fixed_rows::<3>(0).norm().to_degrees(),
            e.fixed_rows::<3>(3).norm(),
        )
    };
    let config = VerifyConfig::default();
    let full = verify(&lc, &local, &rc, &remote, &config).unwrap();

    let key = doorslam_geometry::key::symbol(1, 42).unwrap();
    let packet = to_packet(key, &rc, &remote, MAX_PACKET_FEATURES).unwrap();
    assert_eq!(packet.features.len(), remote.len().min(MAX_PACKET_FEATURES));
    let bytes = packet_file_bytes(&RobotId::new("bravo").unwrap(), 7, packet.clone()).unwrap();
    assert!(bytes.len() <= 20_000, "{} bytes", bytes.len());
    assert_eq!(Message::decode(&bytes).unwrap().encoded_len(), bytes.len());
    let back = packet_from_file_bytes(&bytes).unwrap();
    assert_eq!(back, packet);
    let (received_calib, received) = from_packet(&back, config.disparity_sigma_px);
    assert!((received_calib.fx - rc.fx).abs() < 1e-3 && received_calib.baseline_m > 0.0);
    // Rebuilt points agree with the sender's to the rounding of pixel and disparity.
    for (a, b) in received.iter().zip(&remote) {
        let z = b.point[2];
        assert!((a.point[2] - z).abs() <= z * z / (rc.fx * rc.baseline_m) as f32 * 0.01 + 1e-4);
        assert!((a.pixel[0] - b.pixel[0]).abs() <= 1.0 / 32.0);
    }
    let quantized = verify(&lc, &local, &received_calib, &received, &config).unwrap();
    let (fr, ft) = error(&full);
    let (qr, qt) = error(&quantized);
    eprintln!(
        "across cameras: full {} features: {} inliers, {fr:.3} deg / {:.1} mm; packet of {} ({} bytes): {} inliers, {qr:.3} deg / {:.1} mm",
        remote.len(),
        full.inliers,
        ft * 1e3,
        back.features.len(),
        bytes.len(),
        quantized.inliers,
        qt * 1e3
    );
    assert!(fr < 0.5 && ft < 0.05, "full: {fr} deg, {ft} m");
    assert!(qr < 0.5 && qt < 0.05, "packet: {qr} deg, {qt} m");
    // A file that is another kind of message, or garbage, is refused by name.
    assert!(packet_from_file_bytes(b"\x02\x01").is_err());
}
