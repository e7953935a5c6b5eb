//! Feature detection on grayscale images.

use std::path::Path;

use opencv::core::{no_array, KeyPoint, Mat, Point2f, Vector};
use opencv::features2d::{ORB_ScoreType, ORB};
use opencv::prelude::*;

/// Failures of the front-end's image processing.
#[derive(Debug, thiserror::Error)]
pub enum FrontendError {
    #[error("cannot read image {path}: {reason}")]
    Image { path: String, reason: String },
    #[error("OpenCV {op}: {source}")]
    OpenCv {
        op: &'static str,
        #[source]
        source: opencv::Error,
    },
    #[error("ORB descriptors are {cols} bytes wide, expected 32")]
    DescriptorWidth { cols: i32 },
    #[error("image of {width}x{height} pixels has {bytes} bytes (8-bit grayscale expected, both images of a pair the same size)")]
    ImageSize {
        width: usize,
        height: usize,
        bytes: usize,
    },
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
}

fn cv(op: &'static str) -> impl FnOnce(opencv::Error) -> FrontendError {
    move |source| FrontendError::OpenCv { op, source }
}

/// Reads an image file as 8-bit grayscale.
pub fn load_gray(path: &Path) -> Result<Mat, FrontendError> {
    let name = path.display().to_string();
    if !path.is_file() {
        return Err(FrontendError::Image {
            path: name,
            reason: "no such file".into(),
        });
    }
    let img = opencv::imgcodecs::imread(&name, opencv::imgcodecs::IMREAD_GRAYSCALE)
        .map_err(cv("imread"))?;
    if img.empty() {
        return Err(FrontendError::Image {
            path: name,
            reason: "not a decodable image".into(),
        });
    }
    Ok(img)
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
pub fn detect_orb(image: &Mat, max_features: i32) -> Result<OrbFeatures, FrontendError> {
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
        return Err(FrontendError::DescriptorWidth {
            cols: descriptors.cols(),
        });
    }
    for (i, kp) in keypoints.iter().enumerate() {
        let row = descriptors
            .at_row::<u8>(i as i32)
            .map_err(cv("descriptor row"))?;
        let mut d = [0u8; 32];
        d.copy_from_slice(row);
        out.points.push([kp.pt().x, kp.pt().y]);
        out.responses.push(kp.response());
        out.descriptors.push(d);
    }
    Ok(out)
}

/// Shi-Tomasi corners ("good features to track"), strongest first, at least
/// `min_distance` pixels apart.
pub fn detect_gftt(
    image: &Mat,
    max_corners: i32,
    quality: f64,
    min_distance: f64,
) -> Result<Vec<[f32; 2]>, FrontendError> {
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
