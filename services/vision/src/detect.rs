//! Keypoints and 32-byte ORB descriptors: GFTT / FAST / ORB detection, descriptors of
//! given pixels, and whole stereo frames' features.

use opencv::core::{no_array, KeyPoint, Mat, Point2f, Ptr, Size, TermCriteria, Vector};
use opencv::features2d::{
    FastFeatureDetector, FastFeatureDetector_DetectorType, ORB_ScoreType, ORB,
};
use opencv::prelude::*;

use crate::config::{Detector, FeatureConfig};
use crate::error::{cv, VisionError};
use crate::image::Gray;
use crate::stereo::{match_along_row, refine_disparity};

/// One left-image feature of a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameFeature {
    /// Sub-pixel position (u, v) in the left image.
    pub pixel: [f32; 2],
    pub descriptor: [u8; 32],
    /// Sub-pixel disparity (px): where the right image shows the pixel's patch.
    pub disparity: f32,
    /// Detector response (higher is stronger): keyframes keep their features in this
    /// order, so a packet's first N are its best.
    pub response: f32,
}

/// A stereo frame's features: the left keypoints that matched along the row.
#[derive(Debug, Clone, Default)]
pub struct FrameFeatures {
    pub features: Vec<FrameFeature>,
}

/// A detected corner: sub-pixel position and detector response.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Corner {
    pub pixel: [f32; 2],
    pub response: f32,
}

/// Detector and descriptor objects, created once (OpenCV allocates on creation).
pub struct Extractor {
    config: FeatureConfig,
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
pub const ORB_EDGE: i32 = 31;

impl Extractor {
    pub fn new(config: &FeatureConfig) -> Result<Self, VisionError> {
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

    pub fn config(&self) -> &FeatureConfig {
        &self.config
    }

    /// The left keypoints that found a stereo match, each with its sub-pixel disparity and
    /// ORB descriptor, in detection order (strongest first for GFTT and FAST).
    ///
    /// Only matched keypoints are of use (a keyframe carries 3-D points), so the row
    /// stereo runs first, on the detector's integer corners, and the costly per-keypoint
    /// work (GFTT's sub-pixel refinement, ORB's descriptors) only on the matches: at KITTI
    /// size a third to a half of the corners find no match (sky, road, far field). The
    /// block matcher works on the rounded pixel anyway, and the refined corner is at most a
    /// pixel away: disparity belongs to the place, not to the rounding.
    pub fn extract(
        &mut self,
        left: &Gray<'_>,
        right: &Gray<'_>,
    ) -> Result<FrameFeatures, VisionError> {
        let image = left.mat()?;
        let config = self.config.clone();
        let config = &config;
        let (mut keypoints, disparities) = match config.detector {
            Detector::Orb => {
                // ORB's own oriented multi-scale keypoints: detected and described
                // together, then the matched ones kept.
                let mut keypoints = Vector::<KeyPoint>::new();
                let mut descriptors = Mat::default();
                self.orb
                    .detect_and_compute(
                        &image,
                        &no_array(),
                        &mut keypoints,
                        &mut descriptors,
                        false,
                    )
                    .map_err(cv("ORB detect and describe"))?;
                return stereo_features(left, right, config, &keypoints, &descriptors, None);
            }
            Detector::Gftt | Detector::Fast => {
                let corners = self.detect_integer(&image)?;
                let mut matched = Vector::<KeyPoint>::with_capacity(corners.len());
                let mut disparities = Vec::with_capacity(corners.len());
                for mut kp in corners.iter() {
                    if let Some(d) = match_along_row(left, right, [kp.pt().x, kp.pt().y], config) {
                        // The index rides in the class id, so the rows ORB returns (it
                        // drops keypoints it cannot describe) find their disparities.
                        kp.set_class_id(disparities.len() as i32);
                        matched.push(kp);
                        disparities.push(d);
                    }
                }
                (matched, disparities)
            }
        };
        if keypoints.is_empty() {
            return Ok(FrameFeatures::default());
        }
        if config.detector == Detector::Gftt {
            refine_sub_pixel(&image, &mut keypoints)?;
        }
        let mut descriptors = Mat::default();
        self.orb
            .compute(&image, &mut keypoints, &mut descriptors)
            .map_err(cv("ORB descriptors"))?;
        stereo_features(
            left,
            right,
            config,
            &keypoints,
            &descriptors,
            Some(&disparities),
        )
    }

    /// Corners of the configured detector in the left image, strongest first (at most
    /// `max_features`, none within ORB's border).
    pub fn corners(&mut self, left: &Gray<'_>) -> Result<Vec<Corner>, VisionError> {
        let image = left.mat()?;
        if self.config.detector == Detector::Orb {
            let mut keypoints = Vector::<KeyPoint>::new();
            self.orb
                .detect(&image, &mut keypoints, &no_array())
                .map_err(cv("ORB detect"))?;
            let mut out: Vec<Corner> = keypoints
                .iter()
                .map(|k| Corner {
                    pixel: [k.pt().x, k.pt().y],
                    response: k.response(),
                })
                .collect();
            out.sort_by(|a, b| b.response.total_cmp(&a.response));
            return Ok(out);
        }
        let mut keypoints = self.detect_integer(&image)?;
        if self.config.detector == Detector::Gftt {
            refine_sub_pixel(&image, &mut keypoints)?;
        }
        Ok(keypoints
            .iter()
            .map(|k| Corner {
                pixel: [k.pt().x, k.pt().y],
                response: k.response(),
            })
            .collect())
    }

    /// Upright single-level ORB descriptors of the given left-image pixels (`None` for a
    /// pixel too close to the border to be described).
    pub fn describe(
        &mut self,
        left: &Gray<'_>,
        pixels: &[[f32; 2]],
    ) -> Result<Vec<Option<[u8; 32]>>, VisionError> {
        let image = left.mat()?;
        let mut keypoints = Vector::<KeyPoint>::with_capacity(pixels.len());
        for (i, p) in pixels.iter().enumerate() {
            keypoints.push(
                KeyPoint::new_coords(p[0], p[1], 31.0, 0.0, 0.0, 0, i as i32)
                    .map_err(cv("KeyPoint"))?,
            );
        }
        let mut descriptors = Mat::default();
        self.orb
            .compute(&image, &mut keypoints, &mut descriptors)
            .map_err(cv("ORB compute"))?;
        let mut out = vec![None; pixels.len()];
        if keypoints.is_empty() {
            return Ok(out);
        }
        if descriptors.cols() != 32 || descriptors.rows() != keypoints.len() as i32 {
            return Err(VisionError::DescriptorWidth {
                cols: descriptors.cols(),
            });
        }
        // ORB drops keypoints near the border; the class id says which pixel each row is.
        for (row, kp) in keypoints.iter().enumerate() {
            if let Some(slot) = usize::try_from(kp.class_id())
                .ok()
                .and_then(|i| out.get_mut(i))
            {
                *slot = Some(descriptor_row(&descriptors, row)?);
            }
        }
        Ok(out)
    }

    /// The GFTT or FAST corners at their integer pixels, strongest first, at most
    /// `max_features` (none for ORB, which detects as it describes).
    fn detect_integer(
        &mut self,
        image: &impl opencv::core::ToInputArray,
    ) -> Result<Vector<KeyPoint>, VisionError> {
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
                    .detect(image, &mut keypoints, &no_array())
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

    /// "Good features to track" (Shi-Tomasi: the smaller eigenvalue of the gradient's
    /// structure tensor) with OpenCV's score image, but selected on a grid: the strongest
    /// pixel of each `min_feature_distance_px` cell above `gftt_quality` × the best score,
    /// strongest first. The same corners as cv::goodFeaturesToTrack's spread-out set at a
    /// fraction of its cost (it sorts every candidate pixel), at integer pixels
    /// ([`refine_sub_pixel`] refines the ones kept). Returns (u, v, score).
    fn shi_tomasi(
        &mut self,
        image: &impl opencv::core::ToInputArray,
    ) -> Result<Vec<[f32; 3]>, VisionError> {
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
        Ok(cells)
    }
}

/// Moves each keypoint to its sub-pixel corner (the gradient-orthogonality iteration of
/// cv::cornerSubPix): integer positions alone would add up to ±0.5 px to every residual.
/// A corner that wanders more than a pixel was not a corner, and keeps its pixel.
fn refine_sub_pixel(
    image: &impl opencv::core::ToInputArray,
    keypoints: &mut Vector<KeyPoint>,
) -> Result<(), VisionError> {
    if keypoints.is_empty() {
        return Ok(());
    }
    let mut corners: Vector<Point2f> = keypoints.iter().map(|k| k.pt()).collect();
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
    for (i, p) in corners.iter().enumerate() {
        let mut kp = keypoints.get(i).map_err(cv("keypoint"))?;
        let q = kp.pt();
        if (p.x - q.x).abs() <= 1.0 && (p.y - q.y).abs() <= 1.0 {
            kp.set_pt(p);
            keypoints.set(i, kp).map_err(cv("keypoint"))?;
        }
    }
    Ok(())
}

/// The features of described keypoints with a stereo match: row `i` of `descriptors` is
/// keypoint `i`; its disparity is `disparities[class id]` when the row stereo already ran
/// on the detector's corners, else matched here.
fn stereo_features(
    left: &Gray<'_>,
    right: &Gray<'_>,
    config: &FeatureConfig,
    keypoints: &Vector<KeyPoint>,
    descriptors: &Mat,
    disparities: Option<&[f32]>,
) -> Result<FrameFeatures, VisionError> {
    if keypoints.is_empty() {
        return Ok(FrameFeatures::default());
    }
    if descriptors.cols() != 32 || descriptors.rows() != keypoints.len() as i32 {
        return Err(VisionError::DescriptorWidth {
            cols: descriptors.cols(),
        });
    }
    let mut features = Vec::with_capacity(keypoints.len());
    for (row, kp) in keypoints.iter().enumerate() {
        let pixel = [kp.pt().x, kp.pt().y];
        let disparity = match disparities {
            // Matched at the integer corner; refined again where the corner is now.
            Some(d) => usize::try_from(kp.class_id())
                .ok()
                .and_then(|i| d.get(i).copied())
                .map(|d| {
                    if config.stereo_gradient_refine {
                        refine_disparity(left, right, pixel, d as f64, config.stereo_window_radius)
                            .map_or(d, |refined| refined as f32)
                    } else {
                        d
                    }
                })
                .filter(|&d| d as f64 >= config.min_disparity_px),
            None => match_along_row(left, right, pixel, config),
        };
        if let Some(disparity) = disparity {
            features.push(FrameFeature {
                pixel,
                descriptor: descriptor_row(descriptors, row)?,
                disparity,
                response: kp.response(),
            });
        }
    }
    Ok(FrameFeatures { features })
}

fn descriptor_row(descriptors: &Mat, row: usize) -> Result<[u8; 32], VisionError> {
    let bytes = descriptors
        .at_row::<u8>(row as i32)
        .map_err(cv("descriptor row"))?;
    let mut descriptor = [0u8; 32];
    descriptor.copy_from_slice(bytes);
    Ok(descriptor)
}

/// Hamming distance of two 256-bit descriptors.
pub fn hamming(a: &[u8; 32], b: &[u8; 32]) -> u32 {
    let mut d = 0;
    for k in 0..4 {
        let x = u64::from_le_bytes(a[8 * k..8 * k + 8].try_into().expect("8 bytes"));
        let y = u64::from_le_bytes(b[8 * k..8 * k + 8].try_into().expect("8 bytes"));
        d += (x ^ y).count_ones();
    }
    d
}

/// ORB keypoints with their 32-byte binary descriptors, index-aligned.
#[derive(Debug, Clone, Default)]
pub struct OrbFeatures {
    /// Pixel coordinates (x, y) of each keypoint.
    pub points: Vec<[f32; 2]>,
    /// Detector response of each keypoint (higher is stronger).
    pub responses: Vec<f32>,
    /// One 256-bit descriptor per keypoint.
    pub descriptors: Vec<[u8; 32]>,
}

/// Detects up to `max_features` ORB features (FAST corners on an 8-level pyramid, Harris
/// ranking) and computes their descriptors.
pub fn detect_orb(image: &Mat, max_features: i32) -> Result<OrbFeatures, VisionError> {
    let mut orb = ORB::create(
        max_features,
        1.2,
        8,
        31,
        0,
        2,
        ORB_ScoreType::HARRIS_SCORE,
        31,
        20,
    )
    .map_err(cv("ORB::create"))?;
    let mut keypoints = Vector::<KeyPoint>::new();
    let mut descriptors = Mat::default();
    orb.detect_and_compute(image, &no_array(), &mut keypoints, &mut descriptors, false)
        .map_err(cv("ORB::detect_and_compute"))?;
    let mut out = OrbFeatures::default();
    if keypoints.is_empty() {
        return Ok(out);
    }
    if descriptors.cols() != 32 {
        return Err(VisionError::DescriptorWidth {
            cols: descriptors.cols(),
        });
    }
    for (i, kp) in keypoints.iter().enumerate() {
        out.points.push([kp.pt().x, kp.pt().y]);
        out.responses.push(kp.response());
        out.descriptors.push(descriptor_row(&descriptors, i)?);
    }
    Ok(out)
}

/// [`detect_orb`] on a borrowed image.
pub fn detect_orb_gray(image: &Gray<'_>, max_features: i32) -> Result<OrbFeatures, VisionError> {
    let mat = image.mat()?;
    // An owned Mat (one image copy, small next to ORB's cost) for detect_orb's &Mat.
    let mat = mat.try_clone().map_err(cv("Mat clone"))?;
    detect_orb(&mat, max_features)
}

/// Shi-Tomasi corners ("good features to track"), strongest first, at least
/// `min_distance` pixels apart.
pub fn detect_gftt(
    image: &Mat,
    max_corners: i32,
    quality: f64,
    min_distance: f64,
) -> Result<Vec<[f32; 2]>, VisionError> {
    let mut corners = Vector::<Point2f>::new();
    opencv::imgproc::good_features_to_track(
        image,
        &mut corners,
        max_corners,
        quality,
        min_distance,
        &no_array(),
        3,
        false,
        0.04,
    )
    .map_err(cv("goodFeaturesToTrack"))?;
    Ok(corners.iter().map(|p| [p.x, p.y]).collect())
}
