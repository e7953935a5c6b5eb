//! OpenCV feature detection on real stereo images from ../shared/data/stereo.

// Paths are relative to the package root, the working directory cargo runs tests in (a
// compile-time CARGO_MANIFEST_DIR goes stale when one target dir serves several clones).
use std::path::PathBuf;

use doorslam_vision::{detect_gftt, detect_orb, load_gray};
use opencv::prelude::*;

fn data(rel: &str) -> PathBuf {
    let root = std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(".").join("../../../shared/data"));
    let p = root.join(rel);
    assert!(
        p.is_file(),
        "test data missing: {} (set DOORSLAM_DATA)",
        p.display()
    );
    p
}

#[test]
fn orb_and_gftt_find_plenty_of_features_on_euroc() {
    let img = load_gray(&data("stereo/euroc_loop_closure_pairs/left_img_0.png")).unwrap();
    assert_eq!((img.cols(), img.rows()), (752, 480));

    let orb = detect_orb(&img, 1000).unwrap();
    let n = orb.points.len();
    assert!(
        (500..=1000).contains(&n),
        "ORB found {n} features on a textured EuRoC frame"
    );
    assert_eq!(orb.descriptors.len(), n);
    assert!(orb
        .points
        .iter()
        .all(|p| (0.0..752.0).contains(&p[0]) && (0.0..480.0).contains(&p[1])));
    // Descriptors are not all identical (a broken binding would give zeros).
    let distinct: std::collections::BTreeSet<_> = orb.descriptors.iter().collect();
    assert!(
        distinct.len() > n * 9 / 10,
        "only {} distinct descriptors of {n}",
        distinct.len()
    );

    let corners = detect_gftt(&img, 500, 0.01, 10.0).unwrap();
    assert!(
        (200..=500).contains(&corners.len()),
        "GFTT found {} corners",
        corners.len()
    );
}

#[test]
fn a_flat_image_has_no_features_and_missing_files_are_named() {
    let flat =
        Mat::new_rows_cols_with_default(480, 752, opencv::core::CV_8UC1, 128.into()).unwrap();
    assert!(detect_orb(&flat, 1000).unwrap().points.is_empty());
    assert!(detect_gftt(&flat, 500, 0.01, 10.0).unwrap().is_empty());

    let err = load_gray(std::path::Path::new("/nonexistent/left.png")).unwrap_err();
    assert!(err.to_string().contains("/nonexistent/left.png"), "{err}");
}
