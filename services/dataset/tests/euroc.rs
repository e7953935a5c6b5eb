//! EuRoC calibration (`sensor.yaml`) and rectification on the real pairs in
//! shared/data/stereo (or `$DOORSLAM_DATA`).

use std::path::{Path, PathBuf};

use doorslam_dataset::{read_gray_png, Dataset, EurocCamera, Pair, Rectifier};
use opencv::core::{no_array, KeyPoint, Mat, Point2f, Size, TermCriteria, Vector};
use opencv::features2d::{BFMatcher, ORB_ScoreType, ORB};
use opencv::prelude::*;

fn data(rel: &str) -> PathBuf {
    let root = std::env::var("DOORSLAM_DATA").unwrap_or_else(|_| "../../../shared/data".into());
    PathBuf::from(root).join(rel)
}

#[test]
fn sensor_yaml_is_read_into_the_camera_type() {
    let cam0 =
        EurocCamera::from_yaml(&data("stereo/euroc_v101_micro/mav0/cam0/sensor.yaml")).unwrap();
    assert_eq!(cam0.resolution, [752, 480]);
    assert_eq!(cam0.intrinsics, [458.654, 457.296, 367.215, 248.375]);
    assert_eq!(
        cam0.distortion,
        [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    );
    let t = cam0.body_from_camera.translation.vector;
    assert!((t.x + 0.0216401454975).abs() < 1e-12 && (t.z - 0.00981073058949).abs() < 1e-12);
    let cam1 =
        EurocCamera::from_yaml(&data("stereo/euroc_v101_micro/mav0/cam1/sensor.yaml")).unwrap();
    // The README's baseline: |T_cam1_cam0| = 0.1101 m.
    let right_from_left = cam1.body_from_camera.inverse() * cam0.body_from_camera;
    let b = right_from_left.translation.vector.norm();
    assert!((b - 0.1101).abs() < 1e-3, "baseline {b}");
    // The loop-closure folder's copies are the same calibration.
    let left =
        EurocCamera::from_yaml(&data("stereo/euroc_loop_closure_pairs/sensorLeft.yaml")).unwrap();
    assert_eq!(left, cam0);
}

#[test]
fn bad_sensor_yaml_names_file_and_field() {
    let good =
        std::fs::read_to_string(data("stereo/euroc_v101_micro/mav0/cam0/sensor.yaml")).unwrap();
    let bad = |text: &str| {
        EurocCamera::parse_yaml(text, Path::new("cam0/sensor.yaml"))
            .unwrap_err()
            .to_string()
    };
    let e = bad(&good.replace("intrinsics: [458.654, ", "intrinsics: ["));
    assert!(
        e.contains("cam0/sensor.yaml") && e.contains("field intrinsics") && e.contains("3 values"),
        "{e}"
    );
    let e = bad(&good.replace("458.654", "-458.654"));
    assert!(e.contains("field intrinsics") && e.contains("> 0"), "{e}");
    let e = bad(&good.replace("radial-tangential", "equidistant"));
    assert!(
        e.contains("field distortion_model") && e.contains("equidistant"),
        "{e}"
    );
    let e = bad(&good.replace("distortion_coefficients", "coefficients"));
    assert!(
        e.contains("field distortion_coefficients") && e.contains("missing"),
        "{e}"
    );
    let e = bad(&good.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0, 2.0]"));
    assert!(
        e.contains("field T_BS.data") && e.contains("0 0 0 1"),
        "{e}"
    );
    let e = bad(&good.replace("0.0148655429818", "0.5"));
    assert!(
        e.contains("field T_BS.data") && e.contains("not a rotation"),
        "{e}"
    );
    let e = bad(&good.replace("resolution: [752, 480]", "resolution: [752.5, 480]"));
    assert!(e.contains("field resolution"), "{e}");
    let e = EurocCamera::from_yaml(Path::new("/no/such/sensor.yaml"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("/no/such/sensor.yaml"), "{e}");
}

/// Sub-pixel Shi-Tomasi corners with upright ORB descriptors.
fn corners(img: &Mat) -> (Vec<[f32; 2]>, Mat) {
    let mut pts = Vector::<Point2f>::new();
    opencv::imgproc::good_features_to_track(
        img,
        &mut pts,
        800,
        0.01,
        8.0,
        &no_array(),
        3,
        false,
        0.04,
    )
    .unwrap();
    opencv::imgproc::corner_sub_pix(
        img,
        &mut pts,
        Size::new(3, 3),
        Size::new(-1, -1),
        TermCriteria::new(
            opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
            20,
            0.01,
        )
        .unwrap(),
    )
    .unwrap();
    let mut kps: Vector<KeyPoint> = pts
        .iter()
        .map(|p| KeyPoint::new_coords(p.x, p.y, 31.0, 0.0, 1.0, 0, -1).unwrap())
        .collect();
    let mut orb = ORB::create(1000, 1.2, 1, 31, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
    let mut desc = Mat::default();
    orb.detect_and_compute(img, &no_array(), &mut kps, &mut desc, true)
        .unwrap();
    (kps.iter().map(|k| [k.pt().x, k.pt().y]).collect(), desc)
}

/// Row differences |v_left − v_right| of cross-checked corner matches between the two
/// images of a pair (only matches with a plausible disparity, 0.5-120 px).
fn row_differences(pair: &Pair) -> Vec<f64> {
    let mat = |p: &[u8]| {
        Mat::new_rows_cols_with_data(pair.height as i32, pair.width as i32, p)
            .unwrap()
            .try_clone()
            .unwrap()
    };
    let (l, r) = (mat(&pair.left), mat(&pair.right));
    let ((pl, dl), (pr, dr)) = (corners(&l), corners(&r));
    let matcher = BFMatcher::create(opencv::core::NORM_HAMMING, true).unwrap();
    let mut matches = Vector::new();
    matcher
        .train_match(&dl, &dr, &mut matches, &no_array())
        .unwrap();
    matches
        .iter()
        .filter(|m| m.distance < 40.0)
        .filter_map(|m| {
            let (a, b) = (pl[m.query_idx as usize], pr[m.train_idx as usize]);
            let d = a[0] - b[0];
            (0.5..120.0)
                .contains(&d)
                .then(|| (a[1] - b[1]).abs() as f64)
        })
        .collect()
}

fn quantile(v: &[f64], q: f64) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[((q * v.len() as f64) as usize).min(v.len() - 1)]
}

#[test]
fn rectified_rows_agree_to_a_fraction_of_a_pixel() {
    let dataset = Dataset::open(&data("stereo/euroc_v101_micro")).unwrap();
    let stereo = dataset.stereo().unwrap();
    let rectifier = stereo.rectifier.as_ref().expect("EuRoC needs rectifying");
    let c = stereo.calibration;
    eprintln!("rectified EuRoC calibration: {c:?}");
    assert!((c.baseline_m - 0.1101).abs() < 1e-3, "{c:?}");
    assert!((400.0..470.0).contains(&c.fx) && c.fx == c.fy, "{c:?}");
    assert_eq!(dataset.calibration().unwrap(), c);
    let (mut raw_rows, mut rect_rows) = (Vec::new(), Vec::new());
    for k in [0, 15, 29] {
        let raw = dataset.load(k).unwrap();
        raw_rows.extend(row_differences(&raw));
        rect_rows.extend(row_differences(&stereo.prepare(raw).unwrap()));
    }
    let (raw_med, raw_p90) = (quantile(&raw_rows, 0.5), quantile(&raw_rows, 0.9));
    let (med, p75) = (quantile(&rect_rows, 0.5), quantile(&rect_rows, 0.75));
    // A few cross-checked descriptor matches are wrong (repeated texture): the bulk is
    // what rectification is judged by.
    let within = rect_rows.iter().filter(|&&d| d < 0.5).count() as f64 / rect_rows.len() as f64;
    eprintln!(
        "row difference of {} raw matches: median {raw_med:.2} px, p90 {raw_p90:.2}; \
         of {} rectified matches: median {med:.3} px, p75 {p75:.3}, {:.0} % under 0.5 px",
        raw_rows.len(),
        rect_rows.len(),
        100.0 * within
    );
    assert!(rect_rows.len() > 300, "{} matches", rect_rows.len());
    assert!(
        med < 0.25 && within > 0.7,
        "median {med} px, {within} under 0.5 px"
    );
    assert!(raw_med > 2.0 * med, "raw {raw_med} vs rectified {med}");
    // The same maps through the slice interface, and a wrong size is refused.
    let raw = dataset.load(3).unwrap();
    let n = raw.left.len();
    let (mut l, mut r) = (vec![0; n], vec![0; n]);
    rectifier
        .rectify_into(&raw.left, &raw.right, &mut l, &mut r)
        .unwrap();
    assert_eq!(stereo.prepare(raw.clone()).unwrap().left, l);
    let e = rectifier
        .rectify_into(&raw.left[1..], &raw.right, &mut l, &mut r)
        .unwrap_err();
    assert!(e.to_string().contains("752x480"), "{e}");
}

#[test]
fn loop_closure_pairs_rectify_with_their_own_yaml() {
    let dir = data("stereo/euroc_loop_closure_pairs");
    let left = EurocCamera::from_yaml(&dir.join("sensorLeft.yaml")).unwrap();
    let right = EurocCamera::from_yaml(&dir.join("sensorRight.yaml")).unwrap();
    let rectifier = Rectifier::new(&left, &right, &dir).unwrap();
    let (w, h, l) = read_gray_png(&dir.join("left_img_0.png")).unwrap();
    let (_, _, r) = read_gray_png(&dir.join("right_img_0.png")).unwrap();
    let pair = Pair {
        width: w,
        height: h,
        left: l,
        right: r,
    };
    let rows = row_differences(&rectifier.rectify(&pair).unwrap());
    assert!(
        rows.len() > 100 && quantile(&rows, 0.5) < 0.25,
        "{}",
        rows.len()
    );
}
