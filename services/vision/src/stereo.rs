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
    let mut disparity = d as f64 + offset;
    if config.stereo_gradient_refine {
        disparity = refine_disparity(left, right, pixel, disparity, r).unwrap_or(disparity);
    }
    (disparity >= config.min_disparity_px).then_some(disparity as f32)
}

/// Largest move (px) of the gradient refinement away from the block match it starts from:
/// beyond it the iteration has left the block match's basin (repeated texture, an edge
/// along the row), and the block match is kept.
const MAX_REFINE_MOVE_PX: f64 = 1.0;

/// The disparity `d` of the left pixel `pixel` (sub-pixel) refined from `d0` by
/// Gauss-Newton on `Σ (R(x − d, y) − L(x, y) − β)²` over the `(2r+1)²` window around it,
/// `β` absorbing a brightness offset between the two cameras. Both images are sampled
/// bilinearly at the window's sub-pixel positions, so the estimate is continuous in the
/// shift; the parabola through three SAD costs ([`match_along_row`]'s own sub-pixel step)
/// is biased towards whole pixels ("pixel locking"), an error every point of a frame
/// shares in the same direction for the same fractional disparity. `None` when the window
/// leaves an image, the rows carry no horizontal gradient, or the iteration moves more
/// than a pixel from `d0` (then `d0` stands).
pub fn refine_disparity(
    left: &Gray<'_>,
    right: &Gray<'_>,
    pixel: [f32; 2],
    d0: f64,
    r: usize,
) -> Option<f64> {
    let (x0, y0) = (pixel[0] as f64, pixel[1] as f64);
    let (w, h) = (left.width as f64, left.height as f64);
    let rf = r as f64;
    // The window, its right-image copy up to a pixel either way and the gradient's ±1 px
    // (d0 ≥ 0.5 from the block match, so the copy never reaches past x0 + r + 2.5).
    if y0 - rf < 0.0
        || y0 + rf + 1.0 >= h
        || x0 + rf + 3.0 >= w
        || x0 - rf - d0 - MAX_REFINE_MOVE_PX - 2.0 < 0.0
    {
        return None;
    }
    let n = 2 * r + 1;
    if n > MAX_REFINE_WINDOW {
        return None;
    }
    // Every sample of a window shares one fractional offset, so each image row is
    // interpolated once per window row: the window's n samples plus one on each side for
    // the central-difference gradient.
    let mut template = [0.0f64; MAX_REFINE_WINDOW * MAX_REFINE_WINDOW];
    let mut samples = [0.0f64; MAX_REFINE_WINDOW + 2];
    let (ly, fy) = split(y0 - rf);
    let (lx, fx) = split(x0 - rf);
    for j in 0..n {
        interpolate_row(left, lx, ly + j, fx, fy, &mut template[j * n..(j + 1) * n]);
    }
    let (mut d, mut beta) = (d0, 0.0);
    for _ in 0..8 {
        // Normal equations of (Δd, Δβ), residual e = R(x − d, y) − L(x, y) − β, Jacobian
        // (−∂R/∂x, −1).
        let (rx, rfx) = split(x0 - rf - d - 1.0);
        let (mut h_dd, mut h_db, mut b_d, mut b_b) = (0.0, 0.0, 0.0, 0.0);
        for j in 0..n {
            interpolate_row(right, rx, ly + j, rfx, fy, &mut samples[..n + 2]);
            for i in 0..n {
                let gx = 0.5 * (samples[i + 2] - samples[i]);
                let e = samples[i + 1] - template[j * n + i] - beta;
                h_dd += gx * gx;
                h_db += gx;
                b_d += gx * e;
                b_b += e;
            }
        }
        let h_bb = (n * n) as f64;
        // J = (−gx, −1): JᵀJ = [[Σgx², Σgx], [Σgx, N]], −Jᵀe = (Σgx·e, Σe).
        let det = h_dd * h_bb - h_db * h_db;
        if det <= 1e-6 * h_bb * h_bb {
            return None;
        }
        let step_d = (h_bb * b_d - h_db * b_b) / det;
        let step_b = (h_dd * b_b - h_db * b_d) / det;
        d += step_d;
        beta += step_b;
        if (d - d0).abs() > MAX_REFINE_MOVE_PX {
            return None;
        }
        if step_d.abs() < 1e-2 {
            break;
        }
    }
    Some(d)
}

/// Widest refinement window (`2r + 1`, r ≤ 7 as the block matcher's 16-bit costs).
const MAX_REFINE_WINDOW: usize = 15;

/// Whole and fractional part of a non-negative coordinate.
fn split(x: f64) -> (usize, f64) {
    let whole = x.floor();
    (whole as usize, x - whole)
}

/// `out[k]` = the image bilinearly interpolated at `(x + k + fx, y + fy)`.
fn interpolate_row(image: &Gray<'_>, x: usize, y: usize, fx: f64, fy: f64, out: &mut [f64]) {
    let (top, bottom) = (image.row(y), image.row(y + 1));
    let (w00, w01) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy));
    let (w10, w11) = ((1.0 - fx) * fy, fx * fy);
    for (k, o) in out.iter_mut().enumerate() {
        let c = x + k;
        *o = w00 * top[c] as f64
            + w01 * top[c + 1] as f64
            + w10 * bottom[c] as f64
            + w11 * bottom[c + 1] as f64;
    }
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

    /// The parabola through three SAD costs locks towards whole pixels; the gradient
    /// refinement does not, and a brightness offset between the cameras does not move it.
    #[test]
    fn gradient_refinement_removes_the_parabolas_pixel_locking() {
        let (w, h) = (200, 60);
        let parabola = FeatureConfig {
            stereo_gradient_refine: false,
            ..FeatureConfig::default()
        };
        let gradient = FeatureConfig::default();
        let (mut worst_parabola, mut worst_gradient) = (0.0f64, 0.0f64);
        for truth in [8.1, 8.25, 8.4, 8.6, 8.75, 8.9, 21.3, 21.7] {
            let (l, mut r) = pair(w, h, truth);
            for p in &mut r {
                *p = p.saturating_add(6);
            }
            let (left, right) = (Gray::new(w, h, &l).unwrap(), Gray::new(w, h, &r).unwrap());
            for x in [60.0f32, 100.3, 140.7] {
                let a = match_along_row(&left, &right, [x, 30.0], &parabola).unwrap() as f64;
                let b = match_along_row(&left, &right, [x, 30.0], &gradient).unwrap() as f64;
                worst_parabola = worst_parabola.max((a - truth).abs());
                worst_gradient = worst_gradient.max((b - truth).abs());
            }
        }
        assert!(
            worst_gradient < 0.05 && worst_gradient < 0.5 * worst_parabola,
            "worst error: gradient {worst_gradient:.3} px, parabola {worst_parabola:.3} px"
        );
    }

    #[test]
    fn gradient_refinement_refuses_a_flat_window_and_the_border() {
        let (w, h) = (80, 40);
        let flat = vec![90u8; w * h];
        let image = Gray::new(w, h, &flat).unwrap();
        assert_eq!(refine_disparity(&image, &image, [40.0, 20.0], 5.0, 3), None);
        let (l, r) = pair(w, h, 5.0);
        let (left, right) = (Gray::new(w, h, &l).unwrap(), Gray::new(w, h, &r).unwrap());
        assert_eq!(refine_disparity(&left, &right, [6.0, 20.0], 5.0, 3), None);
        assert_eq!(refine_disparity(&left, &right, [40.0, 38.5], 5.0, 3), None);
        assert!(refine_disparity(&left, &right, [40.0, 20.0], 5.0, 3).is_some());
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
