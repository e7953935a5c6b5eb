//! KITTI `calib.txt` files of the real clips in `shared/data/stereo` (or `$DOORSLAM_DATA`).

use std::path::PathBuf;

use doorslam_dataset::{Dataset, StereoCalibration};

fn data(rel: &str) -> PathBuf {
    let root = std::env::var("DOORSLAM_DATA").unwrap_or_else(|_| "../../../shared/data".into());
    PathBuf::from(root).join(rel)
}

#[test]
fn kitti_odometry_and_raw_calibrations() {
    // Sequence 06 (odometry benchmark): fx 707.0912, P1[3] = -379.8145 → b = 0.5372 m.
    let c = StereoCalibration::from_kitti(&data("stereo/kitti06_0000-0050/calib.txt")).unwrap();
    assert_eq!(
        (c.fx, c.fy, c.cx, c.cy),
        (707.0912, 707.0912, 601.8873, 183.1104)
    );
    assert!((c.baseline_m - 379.8145 / 707.0912).abs() < 1e-12, "{c:?}");
    // A raw drive's rectified calibration in the same layout: the KITTI rig's 0.54 m.
    let raw =
        StereoCalibration::from_kitti(&data("stereo/kitti_raw_2011_09_26_drive_0001/calib.txt"))
            .unwrap();
    assert!((raw.baseline_m - 0.5372).abs() < 0.01, "{raw:?}");
    // Through the dataset reader.
    let d = Dataset::open(&data("stereo/kitti06_0000-0050")).unwrap();
    assert_eq!(d.calibration().unwrap(), c);
}

#[test]
fn a_missing_file_is_named() {
    let e = StereoCalibration::from_kitti(&data("stereo/no-such/calib.txt"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("no-such/calib.txt"), "{e}");
}
