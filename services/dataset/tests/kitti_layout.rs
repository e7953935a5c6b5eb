//! `Dataset::write_kitti_layout` (`doorslam vo --export-rectified`): EuRoC pairs written as
//! the odometry sees them (rectified) into a KITTI-layout folder, which then opens as a
//! rectified dataset with the same calibration and the same pixels.

use std::path::PathBuf;

use doorslam_dataset::Dataset;

fn data(rel: &str) -> PathBuf {
    let root = std::env::var("DOORSLAM_DATA").unwrap_or_else(|_| "../../../shared/data".into());
    PathBuf::from(root).join(rel)
}

#[test]
fn euroc_pairs_written_in_kitti_layout_reopen_rectified_and_identical() {
    let euroc = Dataset::open(&data("stereo/euroc_v101_micro")).unwrap();
    let out = std::env::temp_dir().join(format!("doorslam-kitti-layout-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let n = euroc.write_kitti_layout(&out).unwrap();
    assert_eq!(n, euroc.len());

    let copy = Dataset::open(&out).unwrap();
    assert_eq!(copy.len(), n);
    // Rectified on disk: no rectifier, and the EuRoC rectification's calibration
    // (written with `{:e}`, read back to the last digit).
    assert!(copy.rectifier().unwrap().is_none());
    let (a, b) = (euroc.stereo().unwrap(), copy.calibration().unwrap());
    for (x, y) in [
        (a.calibration.fx, b.fx),
        (a.calibration.fy, b.fy),
        (a.calibration.cx, b.cx),
        (a.calibration.cy, b.cy),
        (a.calibration.baseline_m, b.baseline_m),
    ] {
        assert!((x - y).abs() <= 1e-9 * x.abs().max(1.0), "{x} vs {y}");
    }
    for k in [0, n - 1] {
        let want = a.prepare(euroc.load(k).unwrap()).unwrap();
        let got = copy.load(k).unwrap();
        assert_eq!((got.width, got.height), (want.width, want.height));
        assert!(got.left == want.left && got.right == want.right, "pair {k}");
    }
    // Writing over an unwritable place is an error naming it, not a panic.
    let blocked = out.join("image_0").join("000000.png").join("sub");
    let err = euroc.write_kitti_layout(&blocked).unwrap_err().to_string();
    assert!(err.contains("000000.png"), "{err}");
    std::fs::remove_dir_all(&out).unwrap();
}
