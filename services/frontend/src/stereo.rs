//! What one rectified stereo pair gives the odometry: left-image keypoints with 32-byte ORB
//! descriptors and, where the right image shows the same patch on the same row, a
//! sub-pixel disparity and hence a 3-D point with a depth-dependent covariance.

use nalgebra::{Matrix3, Point3};
use opencv::core::{KeyPoint, Mat, Point2f, Ptr, Size, TermCriteria, Vector};
use opencv::features2d::{
    FastFeatureDetector, FastFeatureDetector_DetectorType, ORB_ScoreType, ORB,
};
use opencv::prelude::*;

use crate::config::{Detector, VoConfig};
use crate::features::FrontendError;
use doorslam_dataset::StereoCalibration;

fn cv(op: &'static str) -> impl FnOnce(opencv::Error) -> FrontendError {
    move |source| FrontendError::OpenCv { op, source }
}

/// A borrowed 8-bit grayscale image, row-major without padding.
#[derive(Debug, Clone, Copy)]
pub struct Gray<'a> {
    pub width: usize,
    pub height: usize,
    pub pixels: &'a [u8],
}

impl<'a> Gray<'a> {
    /// Checks that `pixels` holds `width × height` bytes.
    pub fn new(width: usize, height: usize, pixels: &'a [u8]) -> Result<Self, FrontendError> {
        if width == 0 || height == 0 || pixels.len() != width * height {
            return Err(FrontendError::ImageSize {
                width,
                height,
                bytes: pixels.len(),
            });
        }
        Ok(Self {
            width,
            height,
            pixels,
        })
    }

    fn row(&self, y: usize) -> &'a [u8] {
        &self.pixels[y * self.width..(y + 1) * self.width]
    }

    /// Mean and standard deviation of the intensity on a sparse grid (every 4th pixel of
    /// every 4th row: enough to recognise a blank, saturated or flat frame cheaply).
    pub fn mean_std(&self) -> (f64, f64) {
        let (mut n, mut s, mut s2) = (0.0f64, 0.0f64, 0.0f64);
        for y in (0..self.height).step_by(4) {
            for &p in self.row(y).iter().step_by(4) {
                let p = p as f64;
                n += 1.0;
                s += p;
                s2 += p * p;
            }
        }
        let mean = s / n;
        (mean, (s2 / n - mean * mean).max(0.0).sqrt())
    }

    /// The image as an OpenCV matrix sharing the bytes (no copy).
    fn mat(&self) -> Result<opencv::boxed_ref::BoxedRef<'a, Mat>, FrontendError> {
        Mat::new_rows_cols_with_data(self.height as i32, self.width as i32, self.pixels)
            .map_err(cv("Mat over image bytes"))
    }
}

/// One left-image feature of a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameFeature {
    /// Sub-pixel position (u, v) in the left image.
    pub pixel: [f32; 2],
    pub descriptor: [u8; 32],
    /// Sub-pixel disparity (px) when the right image matched along the row.
    pub disparity: Option<f32>,
    /// Detector response (higher is stronger): keyframes keep their features in this
    /// order, so a packet's first N are its best.
    pub response: f32,
}

/// A stereo frame's features.
#[derive(Debug, Clone, Default)]
pub struct FrameFeatures {
    pub features: Vec<FrameFeature>,
}

/// Detector and descriptor objects, created once (OpenCV allocates on creation).
pub struct Extractor {
    config: VoConfig,
    /// Describes given keypoints on one pyramid level (GFTT / FAST), or detects and
    /// describes on eight (ORB).
    orb: Ptr<ORB>,
    fast: Ptr<FastFeatureDetector>,
    /// Shi-Tomasi score image, reused between frames.
    score: Mat,
}

impl std::fmt::Debug for Extractor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Extractor")
            .field("detector", &self.config.detector)
            .finish()
    }
}

/// ORB's border (px, OpenCV's default): keypoints closer to the edge get no descriptor, so
/// the detectors skip that band.
const ORB_EDGE: i32 = 31;

impl Extractor {
    pub fn new(config: &VoConfig) -> Result<Self, FrontendError> {
        let levels = if config.detector == Detector::Orb {
            8
        } else {
            1
        };
        let orb = ORB::create(
            config.max_features as i32,
            1.2,
            levels,
            ORB_EDGE,
            0,
            2,
            ORB_ScoreType::HARRIS_SCORE,
            31,
            config.fast_threshold,
        )
        .map_err(cv("ORB::create"))?;
        let fast = FastFeatureDetector::create(
            config.fast_threshold,
            true,
            FastFeatureDetector_DetectorType::TYPE_9_16,
        )
        .map_err(cv("FastFeatureDetector::create"))?;
        Ok(Self {
            config: config.clone(),
            orb,
            fast,
            score: Mat::default(),
        })
    }

    /// Left keypoints with descriptors, then their stereo disparities.
    pub fn extract(
        &mut self,
        left: &Gray<'_>,
        right: &Gray<'_>,
    ) -> Result<FrameFeatures, FrontendError> {
        let image = left.mat()?;
        let mut keypoints = self.detect(&image)?;
        let mut descriptors = Mat::default();
        let provided = self.config.detector != Detector::Orb;
        self.orb
            .detect_and_compute(
                &image,
                &opencv::core::no_array(),
                &mut keypoints,
                &mut descriptors,
                provided,
            )
            .map_err(cv("ORB descriptors"))?;
        if keypoints.is_empty() {
            return Ok(FrameFeatures::default());
        }
        if descriptors.cols() != 32 || descriptors.rows() != keypoints.len() as i32 {
            return Err(FrontendError::DescriptorWidth {
                cols: descriptors.cols(),
            });
        }
        let mut features = Vec::with_capacity(keypoints.len());
        for (i, kp) in keypoints.iter().enumerate() {
            let row = descriptors
                .at_row::<u8>(i as i32)
                .map_err(cv("descriptor row"))?;
            let mut descriptor = [0u8; 32];
            descriptor.copy_from_slice(row);
            let pixel = [kp.pt().x, kp.pt().y];
            let disparity = match_along_row(left, right, pixel, &self.config);
            features.push(FrameFeature {
                pixel,
                descriptor,
                disparity,
                response: kp.response(),
            });
        }
        Ok(FrameFeatures { features })
    }

    fn detect(
        &mut self,
        image: &impl opencv::core::ToInputArray,
    ) -> Result<Vector<KeyPoint>, FrontendError> {
        let mut keypoints = Vector::<KeyPoint>::new();
        match self.config.detector {
            Detector::Orb => {}
            Detector::Gftt => {
                for c in self.shi_tomasi(image)? {
                    keypoints.push(
                        KeyPoint::new_coords(c[0], c[1], 31.0, 0.0, c[2], 0, -1)
                            .map_err(cv("KeyPoint"))?,
                    );
                }
            }
            Detector::Fast => {
                self.fast
                    .detect(image, &mut keypoints, &opencv::core::no_array())
                    .map_err(cv("FAST"))?;
                opencv::features2d::KeyPointsFilter::retain_best(
                    &mut keypoints,
                    self.config.max_features as i32,
                )
                .map_err(cv("KeyPointsFilter::retainBest"))?;
                let mut upright = Vector::<KeyPoint>::with_capacity(keypoints.len());
                for kp in keypoints.iter() {
                    upright.push(
                        KeyPoint::new_coords(kp.pt().x, kp.pt().y, 31.0, 0.0, kp.response(), 0, -1)
                            .map_err(cv("KeyPoint"))?,
                    );
                }
                keypoints = upright;
            }
        }
        Ok(keypoints)
    }
}

impl Extractor {
    /// "Good features to track" (Shi-Tomasi: the smaller eigenvalue of the gradient's
    /// structure tensor) with OpenCV's score image, but selected on a grid: the strongest
    /// pixel of each `min_feature_distance_px` cell above `gftt_quality` × the best score,
    /// strongest first. The same corners as cv::goodFeaturesToTrack's spread-out set at a
    /// fraction of its cost (it sorts every candidate pixel), and a sub-pixel position from
    /// a parabola through the score around the peak. Returns (u, v, score).
    fn shi_tomasi(
        &mut self,
        image: &impl opencv::core::ToInputArray,
    ) -> Result<Vec<[f32; 3]>, FrontendError> {
        opencv::imgproc::corner_min_eigen_val(
            image,
            &mut self.score,
            3,
            3,
            opencv::core::BORDER_DEFAULT,
        )
        .map_err(cv("cornerMinEigenVal"))?;
        let (w, h) = (self.score.cols() as usize, self.score.rows() as usize);
        let score = self.score.data_typed::<f32>().map_err(cv("score image"))?;
        let border = ORB_EDGE as usize + 1;
        if w <= 2 * border || h <= 2 * border {
            return Ok(Vec::new());
        }
        let cell = (self.config.min_feature_distance_px.round() as usize).max(2);
        let mut best = 0.0f32;
        let mut cells: Vec<[f32; 3]> = Vec::new();
        for cy in (border..h - border).step_by(cell) {
            for cx in (border..w - border).step_by(cell) {
                let (mut m, mut mx, mut my) = (0.0f32, 0usize, 0usize);
                for y in cy..(cy + cell).min(h - border) {
                    let row = &score[y * w..(y + 1) * w];
                    for (x, &s) in row
                        .iter()
                        .enumerate()
                        .take((cx + cell).min(w - border))
                        .skip(cx)
                    {
                        if s > m {
                            (m, mx, my) = (s, x, y);
                        }
                    }
                }
                // Only a true peak: a cell's maximum on its edge may be the slope of a
                // stronger corner in the next cell, a poorly localised point.
                let peak = m > 0.0
                    && (my - 1..=my + 1).all(|y| {
                        (mx - 1..=mx + 1).all(|x| (x, y) == (mx, my) || score[y * w + x] < m)
                    });
                if peak {
                    best = best.max(m);
                    cells.push([mx as f32, my as f32, m]);
                }
            }
        }
        let threshold = self.config.gftt_quality as f32 * best;
        cells.retain(|c| c[2] > threshold);
        cells.sort_by(|a, b| b[2].total_cmp(&a[2]));
        cells.truncate(self.config.max_features);
        if cells.is_empty() {
            return Ok(cells);
        }
        // Sub-pixel corners (the gradient-orthogonality iteration of cv::cornerSubPix):
        // integer positions alone would add up to ±0.5 px to every residual.
        let mut corners: Vector<Point2f> = cells.iter().map(|c| Point2f::new(c[0], c[1])).collect();
        opencv::imgproc::corner_sub_pix(
            image,
            &mut corners,
            Size::new(3, 3),
            Size::new(-1, -1),
            TermCriteria::new(
                opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
                10,
                0.01,
            )
            .map_err(cv("TermCriteria"))?,
        )
        .map_err(cv("cornerSubPix"))?;
        for (c, p) in cells.iter_mut().zip(corners.iter()) {
            // A corner that wandered more than a pixel was not a corner.
            if (p.x - c[0]).abs() <= 1.0 && (p.y - c[1]).abs() <= 1.0 {
                (c[0], c[1]) = (p.x, p.y);
            }
        }
        Ok(cells)
    }
}

/// Finds the left pixel's patch in the right image on the same row (rectified pair: the
/// match lies `d ≥ 0` pixels to the left) by the sum of absolute differences over a
/// `(2r+1)²` block, with sub-pixel refinement by a parabola through the three costs
/// around the minimum. Refuses ambiguous (repeated texture), poor and boundary matches.
pub fn match_along_row(
    left: &Gray<'_>,
    right: &Gray<'_>,
    pixel: [f32; 2],
    config: &VoConfig,
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
    // cost[k] is the cost of disparity d = dmax - k: for a fixed left pixel the right pixels
    // of all candidates are contiguous, so the inner loop runs over memory in order and
    // vectorizes.
    let mut cost = [0u32; 513];
    let cost = &mut cost[..=dmax];
    for y in v - r..=v + r {
        let (lrow, rrow) = (left.row(y), right.row(y));
        for x in u - r..=u + r {
            let l = lrow[x] as i32;
            let candidates = &rrow[x - dmax..=x];
            for (c, &p) in cost.iter_mut().zip(candidates) {
                *c += (l - p as i32).unsigned_abs();
            }
        }
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
        let config = VoConfig::default();
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
        let config = VoConfig::default();
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
