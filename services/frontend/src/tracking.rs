//! Frame-to-frame tracking of the landmarks: each is looked for where the motion
//! prediction projects it, found by pyramidal KLT from where it was in the previous frame,
//! kept only when tracking it back lands where it started (forward-backward consistency),
//! and measured in the right image along its row (its disparity now).

use nalgebra::Point3;

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::SE3;
use doorslam_vision::klt::track_point;
use doorslam_vision::{match_along_row, FeatureConfig, Gray, KltConfig, KltScratch, Pyramid};

use crate::map::Landmark;

/// A landmark found in the current frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct TrackedPoint {
    /// Index into the landmarks.
    pub landmark: usize,
    pub pixel: [f32; 2],
    pub disparity: Option<f32>,
}

/// Why tracks were dropped in a frame (for the logs and the loss reasons).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct TrackingCounts {
    pub attempted: usize,
    /// Predicted outside the image or behind the camera.
    pub left_view: usize,
    pub klt_failed: usize,
    /// Of `klt_failed`: (outside, flat, no convergence, residual).
    pub klt_failures: [usize; 4],
    pub inconsistent: usize,
    pub tracked: usize,
}

/// Where `predicted` (the current camera in the world) sees the world point `x`; `None`
/// behind the camera or more than `margin` px outside the image.
pub(crate) fn project(
    calib: &StereoCalibration,
    predicted_inverse: &SE3,
    x: &nalgebra::Vector3<f64>,
    size: (usize, usize),
    margin: f64,
) -> Option<[f32; 2]> {
    let q = predicted_inverse * Point3::from(*x);
    if q.z < 0.1 {
        return None;
    }
    let u = calib.fx * q.x / q.z + calib.cx;
    let v = calib.fy * q.y / q.z + calib.cy;
    let inside =
        u > -margin && v > -margin && u < size.0 as f64 + margin && v < size.1 as f64 + margin;
    inside.then_some([u as f32, v as f32])
}

/// Settings of one frame's tracking.
pub(crate) struct TrackSettings<'a> {
    pub klt: &'a KltConfig,
    pub features: &'a FeatureConfig,
    /// Largest distance (px) between a point and where tracking it back lands.
    pub max_back_error_px: f32,
}

/// Tracks every landmark from the previous frame (`prev`) into the current one (`next`,
/// with its right image `right`), seeded by the projection through `predicted`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn track_landmarks(
    calib: &StereoCalibration,
    landmarks: &[Landmark],
    predicted: &SE3,
    prev: &Pyramid,
    next: &Pyramid,
    right: &Gray<'_>,
    settings: &TrackSettings<'_>,
    scratch: &mut KltScratch,
    out: &mut Vec<TrackedPoint>,
) -> TrackingCounts {
    out.clear();
    let Some(left) = next.image() else {
        return TrackingCounts::default();
    };
    let size = (left.width, left.height);
    let inverse = predicted.inverse();
    let mut counts = TrackingCounts::default();
    for (index, l) in landmarks.iter().enumerate() {
        if !l.tracked {
            continue;
        }
        counts.attempted += 1;
        let Some(guess) = project(calib, &inverse, &l.point, size, 0.0) else {
            counts.left_view += 1;
            continue;
        };
        let forward = match track_point(
            prev,
            next,
            l.pixel,
            guess,
            settings.klt.levels,
            settings.klt,
            scratch,
        ) {
            Ok(f) => f,
            Err(e) => {
                counts.klt_failed += 1;
                counts.klt_failures[e as usize] += 1;
                continue;
            }
        };
        // Back from where it was found, at full resolution only: a point tracked to the
        // right place returns to where it started.
        let back = track_point(next, prev, forward.pixel, l.pixel, 1, settings.klt, scratch);
        let consistent = back.is_ok_and(|b| {
            let (dx, dy) = (b.pixel[0] - l.pixel[0], b.pixel[1] - l.pixel[1]);
            dx * dx + dy * dy <= settings.max_back_error_px * settings.max_back_error_px
        });
        if !consistent {
            counts.inconsistent += 1;
            continue;
        }
        out.push(TrackedPoint {
            landmark: index,
            pixel: forward.pixel,
            disparity: match_along_row(&left, right, forward.pixel, settings.features),
        });
    }
    counts.tracked = out.len();
    counts
}
