//! Row stereo on rectified pairs: where the right image shows a left pixel's patch (a
//! sub-pixel disparity), and the 3-D point and its covariance that disparity gives.

use nalgebra::{Matrix3, Point3};

use doorslam_dataset::StereoCalibration;

use crate::config::FeatureConfig;
use crate::image::Gray;

/// Finds the left pixel's patch in the right image on the same row (rectified pair: the
/// match lies `d ≥ 0` pixels to the left) by the sum of absolute differences over a
/// `(2r+1)²` block, with sub-pixel refinement by a parabola through the three costs
/// around the minimum. Refuses ambiguous (repeated texture), poor and boundary matches.
pub fn match_along_row(
    left: &Gray<'_>,
    right: &Gray<'_>,
    pixel: [f32; 2],
    config: &FeatureConfig,
) -> Option<f32> {
    let r = config.stereo_window_radius;
    let (u, v) = (pixel[0].round() as isize, pixel[1].round() as isize);
    let (w, h) = (left.width as isize, left.height as isize);
    if u < r as isize || v < r as isize || u + r as isize >= w || v + r as isize >= h {
        return None;
    }
    let (u, v) = (u as usize, v as usize);
    // Candidates d = 0..=dmax keep the whole right block inside the image.
    let dmax = config.max_disparity_px.min(u - r);
    if dmax < 3 {
        return None;
    }
    let mut cost = [0u32; 513];
    let cost = &mut cost[..=dmax];
    // A block's cost fits 16 bits up to r = 7 ((2r+1)² × 255 ≤ 65535): twice the lanes
    // per SIMD add of 32-bit sums, where the matcher spends its time.
    if (2 * r + 1) * (2 * r + 1) * 255 <= u16::MAX as usize {
        let mut narrow = [0u16; 513];
        let narrow = &mut narrow[..=dmax];
        block_costs(left, right, (u, v), r, narrow);
        for (c, &n) in cost.iter_mut().zip(narrow.iter()) {
            *c = u32::from(n);
        }
    } else {
        block_costs(left, right, (u, v), r, cost);
    }
    let (kbest, &best) = cost.iter().enumerate().min_by_key(|(_, c)| **c)?;
    let d = dmax - kbest;
    if d == 0 || d == dmax {
        return None;
    }
    let pixels = ((2 * r + 1) * (2 * r + 1)) as f64;
    if best as f64 / pixels > config.stereo_max_mean_abs_diff {
        return None;
    }
    let second = cost
        .iter()
        .enumerate()
        .filter(|(k, _)| k.abs_diff(kbest) > 1)
        .map(|(_, c)| *c)
        .min()
        .unwrap_or(u32::MAX);
    if best as f64 >= config.stereo_uniqueness * second as f64 {
        return None;
    }
    // Costs at d-1 and d+1 (k grows as d shrinks).
    let (cm, c0, cp) = (cost[kbest + 1] as f64, best as f64, cost[kbest - 1] as f64);
    let curvature = cm - 2.0 * c0 + cp;
    let offset = if curvature > 0.0 {
        (0.5 * (cm - cp) / curvature).clamp(-0.5, 0.5)
    } else {
        0.0
    };
    // The block was matched at round(u); disparity varies smoothly over the block, so the
    // sub-pixel keypoint a fraction of a pixel away has the same one.
    let disparity = d as f64 + offset;
    (disparity >= config.min_disparity_px).then_some(disparity as f32)
}

/// Sums of absolute differences between the left block around `(u, v)` and the right
/// blocks of every disparity: `cost[k]` is disparity `d = dmax - k` (`cost.len() = dmax + 1`).
/// For a fixed left pixel the right pixels of all candidates are contiguous, so the inner
/// loop runs over memory in order and vectorizes.
fn block_costs<T: Copy + From<u8> + std::ops::AddAssign>(
    left: &Gray<'_>,
    right: &Gray<'_>,
    (u, v): (usize, usize),
    r: usize,
    cost: &mut [T],
) {
    let dmax = cost.len() - 1;
    for y in v - r..=v + r {
        let (lrow, rrow) = (left.row(y), right.row(y));
        for x in u - r..=u + r {
            let l = lrow[x];
            let candidates = &rrow[x - dmax..=x];
            for (c, &p) in cost.iter_mut().zip(candidates) {
                *c += T::from(l.abs_diff(p));
            }
        }
    }
}

/// The 3-D point (left camera frame) of pixel `(u, v)` seen with disparity `d`.
pub fn triangulate(calib: &StereoCalibration, u: f64, v: f64, d: f64) -> Point3<f64> {
    let z = calib.depth(d);
    Point3::new(
        (u - calib.cx) * z / calib.fx,
        (v - calib.cy) * z / calib.fy,
        z,
    )
}

/// `∂P/∂(u, v, d)` of [`triangulate`]: how pixel and disparity noise become the 3-D
/// point's covariance `G · diag(σu², σv², σd²) · Gᵀ`, which grows with depth squared.
pub fn triangulation_jacobian(calib: &StereoCalibration, u: f64, v: f64, d: f64) -> Matrix3<f64> {
    let z = calib.depth(d);
    let dz = -z / d;
    Matrix3::new(
        z / calib.fx,
        0.0,
        (u - calib.cx) / calib.fx * dz,
        0.0,
        z / calib.fy,
        (v - calib.cy) / calib.fy * dz,
        0.0,
        0.0,
        dz,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth random texture, and its copy shifted left by `disparity` px (bilinear), as a
    /// rectified right image of a fronto-parallel plane.
    fn pair(width: usize, height: usize, disparity: f64) -> (Vec<u8>, Vec<u8>) {
        let texture = |x: f64, y: f64| {
            128.0
                + 50.0 * (0.31 * x + 0.07 * y).sin()
                + 40.0 * (0.13 * x - 0.23 * y).cos()
                + 30.0 * (0.47 * x * 0.5 + 0.41 * y).sin()
        };
        let mut left = vec![0u8; width * height];
        let mut right = vec![0u8; width * height];
        for y in 0..height {
            for x in 0..width {
                let (xf, yf) = (x as f64, y as f64);
                left[y * width + x] = texture(xf, yf).round() as u8;
                right[y * width + x] = texture(xf + disparity, yf).round() as u8;
            }
        }
        (left, right)
    }

    #[test]
    fn row_matching_recovers_a_sub_pixel_disparity() {
        let (w, h) = (200, 60);
        let config = FeatureConfig::default();
        for truth in [5.0, 12.3, 30.7] {
            let (l, r) = pair(w, h, truth);
            let (left, right) = (Gray::new(w, h, &l).unwrap(), Gray::new(w, h, &r).unwrap());
            // Sub-pixel keypoints too: the disparity belongs to the place, not to the rounding.
            for x in [60.4f32, 100.0, 149.6] {
                let d = match_along_row(&left, &right, [x, 30.0], &config).unwrap();
                assert!(
                    (d as f64 - truth).abs() < 0.2,
                    "disparity {d} at x {x}, truth {truth}"
                );
            }
        }
    }

    #[test]
    fn flat_images_and_borders_give_no_disparity() {
        let (w, h) = (100, 40);
        let flat = vec![90u8; w * h];
        let img = Gray::new(w, h, &flat).unwrap();
        let config = FeatureConfig::default();
        // Every candidate costs the same: ambiguous, refused.
        assert_eq!(match_along_row(&img, &img, [50.0, 20.0], &config), None);
        let (l, r) = pair(w, h, 8.0);
        let (left, right) = (Gray::new(w, h, &l).unwrap(), Gray::new(w, h, &r).unwrap());
        assert_eq!(match_along_row(&left, &right, [1.0, 20.0], &config), None);
        assert_eq!(match_along_row(&left, &right, [50.0, 39.0], &config), None);
        assert!(Gray::new(w, h, &l[1..]).is_err());
    }

    #[test]
    fn depth_uncertainty_grows_with_depth_squared() {
        let calib = StereoCalibration {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            baseline_m: 0.1,
        };
        let p = triangulate(&calib, 320.0, 240.0, 10.0);
        assert!((p.z - 5.0).abs() < 1e-12);
        let near = triangulation_jacobian(&calib, 320.0, 240.0, 20.0)[(2, 2)].abs();
        let far = triangulation_jacobian(&calib, 320.0, 240.0, 10.0)[(2, 2)].abs();
        assert!((far / near - 4.0).abs() < 1e-9, "{far} / {near}");
    }
}
