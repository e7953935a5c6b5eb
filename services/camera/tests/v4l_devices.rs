//! v4l2 device enumeration agrees with /dev, and a missing camera is a clear error.

use std::path::PathBuf;

use doorslam_camera::{enumerate_devices, open_devices, CameraConfig, CameraError};

#[test]
fn enumeration_matches_dev_video_nodes() {
    let mut from_dev: Vec<PathBuf> = std::fs::read_dir("/dev")
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                n.strip_prefix("video")
                    .is_some_and(|d| !d.is_empty() && d.bytes().all(|c| c.is_ascii_digit()))
            })
        })
        .collect();
    from_dev.sort();
    assert_eq!(enumerate_devices(), from_dev);
}

#[test]
fn a_missing_device_names_the_path_and_points_at_replay() {
    let config = CameraConfig {
        left: "/dev/video97".into(),
        right: Some("/dev/video98".into()),
        ..Default::default()
    };
    let err = open_devices(&config)
        .err()
        .expect("no /dev/video97 on any test machine");
    assert!(matches!(err, CameraError::NoCamera { .. }));
    let msg = err.to_string();
    assert!(
        msg.contains("no camera found at /dev/video97") && msg.contains("replay"),
        "{msg}"
    );
}

#[test]
fn impossible_settings_are_rejected_by_field() {
    let config = CameraConfig {
        width: 4000,
        ..Default::default()
    };
    assert!(open_devices(&config)
        .err()
        .unwrap()
        .to_string()
        .contains("camera.width"));
    let config = CameraConfig {
        fps: 0,
        ..Default::default()
    };
    assert!(open_devices(&config)
        .err()
        .unwrap()
        .to_string()
        .contains("camera.fps"));
}
