//! PnP-RANSAC: a camera's pose from 3-D points and the pixels where it sees them.

use nalgebra::{Isometry3, Translation3, Vector3};
use opencv::core::{Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{SE3, SO3};

use crate::error::{cv, VisionError};

/// solvePnPRansac of 3-D points (in a reference camera frame) against the pixels where a
/// second camera sees them: that camera's pose in the reference frame, and the inliers.
pub fn pnp_ransac(
    points: &[Vector3<f64>],
    pixels: &[[f32; 2]],
    calib: &StereoCalibration,
    iterations: i32,
    threshold_px: f64,
) -> Result<Option<(SE3, Vec<usize>)>, VisionError> {
    let object: Vector<Point3f> = points
        .iter()
        .map(|p| Point3f::new(p.x as f32, p.y as f32, p.z as f32))
        .collect();
    let image: Vector<Point2f> = pixels.iter().map(|p| Point2f::new(p[0], p[1])).collect();
    let k = Mat::from_slice_2d(&[
        [calib.fx, 0.0, calib.cx],
        [0.0, calib.fy, calib.cy],
        [0.0, 0.0, 1.0],
    ])
    .map_err(cv("camera matrix"))?;
    let mut rvec = Mat::default();
    let mut tvec = Mat::default();
    let mut inliers = Vector::<i32>::new();
    let ok = opencv::calib3d::solve_pnp_ransac(
        &object,
        &image,
        &k,
        &opencv::core::no_array(),
        &mut rvec,
        &mut tvec,
        false,
        iterations,
        threshold_px as f32,
        0.999,
        &mut inliers,
        opencv::calib3d::SOLVEPNP_AP3P,
    )
    .map_err(cv("solvePnPRansac"))?;
    if !ok || rvec.total() != 3 || tvec.total() != 3 {
        return Ok(None);
    }
    let r = Vector3::new(
        *rvec.at::<f64>(0).map_err(cv("rvec"))?,
        *rvec.at::<f64>(1).map_err(cv("rvec"))?,
        *rvec.at::<f64>(2).map_err(cv("rvec"))?,
    );
    let t = Vector3::new(
        *tvec.at::<f64>(0).map_err(cv("tvec"))?,
        *tvec.at::<f64>(1).map_err(cv("tvec"))?,
        *tvec.at::<f64>(2).map_err(cv("tvec"))?,
    );
    if !(r.iter().chain(t.iter()).all(|x| x.is_finite())) {
        return Ok(None);
    }
    // OpenCV's (rvec, tvec) maps keyframe points into the camera: X_ck.
    let camera_from_keyframe =
        Isometry3::from_parts(Translation3::from(t), SO3::exp(&r).quaternion());
    let inliers = inliers
        .iter()
        .filter_map(|i| usize::try_from(i).ok())
        .filter(|&i| i < points.len())
        .collect();
    Ok(Some((camera_from_keyframe.inverse(), inliers)))
}
