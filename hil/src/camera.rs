//! A rectified pinhole stereo camera.
//!
//! Camera frame: x right, y down, z forward. A pose is camera-to-world
//! (`p_world = pose * p_camera`) and always refers to the LEFT camera; the right camera
//! is the left one translated by `+baseline` along its own x axis (a rectified pair, so
//! a point at depth z has disparity `fx * baseline / z` pixels, seen further left in the
//! right image). Pixel (col, row) has its centre at (u, v) = (col, row), as in OpenCV.

use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::error::HilError;

/// Intrinsics shared by both cameras of a rectified pair, plus the baseline.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoCamera {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    baseline: f64,
}

fn positive(field: &'static str, value: f64) -> Result<(), HilError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(HilError::InvalidCamera {
            field,
            value,
            reason: "must be finite and > 0",
        })
    }
}

impl StereoCamera {
    /// Checks every parameter; the principal point may lie anywhere finite.
    pub fn new(
        width: u32,
        height: u32,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        baseline: f64,
    ) -> Result<Self, HilError> {
        positive("width", width as f64)?;
        positive("height", height as f64)?;
        positive("fx", fx)?;
        positive("fy", fy)?;
        positive("baseline", baseline)?;
        for (field, value) in [("cx", cx), ("cy", cy)] {
            if !value.is_finite() {
                return Err(HilError::InvalidCamera {
                    field,
                    value,
                    reason: "must be finite",
                });
            }
        }
        Ok(Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            baseline,
        })
    }

    /// EuRoC MAV cam0 (MT9V034, 752×480) intrinsics and its 11 cm stereo baseline.
    pub fn euroc_like() -> Self {
        Self {
            width: 752,
            height: 480,
            fx: 458.654,
            fy: 457.296,
            cx: 367.215,
            cy: 248.375,
            baseline: 0.110,
        }
    }

    /// KITTI odometry sequences 00–02 rectified camera 0/1 (1241×376, 53.7 cm baseline).
    pub fn kitti_like() -> Self {
        Self {
            width: 1241,
            height: 376,
            fx: 718.856,
            fy: 718.856,
            cx: 607.1928,
            cy: 185.2157,
            baseline: 0.537,
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn fx(&self) -> f64 {
        self.fx
    }
    pub fn fy(&self) -> f64 {
        self.fy
    }
    pub fn cx(&self) -> f64 {
        self.cx
    }
    pub fn cy(&self) -> f64 {
        self.cy
    }
    pub fn baseline(&self) -> f64 {
        self.baseline
    }

    /// The rectified stereo calibration the front-end takes (what `calib.txt` holds).
    pub fn stereo_calibration(&self) -> doorslam_dataset::StereoCalibration {
        doorslam_dataset::StereoCalibration {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            baseline_m: self.baseline,
        }
    }

    /// Pose of the right camera given the left camera's pose (both camera-to-world).
    pub fn right_pose(&self, left: &Isometry3<f64>) -> Isometry3<f64> {
        left * Translation3::new(self.baseline, 0.0, 0.0)
    }

    /// Disparity in pixels of a point at camera depth `depth`.
    pub fn disparity(&self, depth: f64) -> f64 {
        self.fx * self.baseline / depth
    }

    /// Pinhole projection of a camera-frame point; `None` behind the camera.
    pub fn project_camera(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        (p.z > 0.0).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// Whether (u, v) falls on a pixel of the image.
    pub fn in_image(&self, u: f64, v: f64) -> bool {
        u >= -0.5 && v >= -0.5 && u < self.width as f64 - 0.5 && v < self.height as f64 - 0.5
    }

    /// Pixel coordinates of a world point in the camera at `pose`, if in front of it and
    /// inside the image.
    pub fn project(&self, pose: &Isometry3<f64>, p_world: &Point3<f64>) -> Option<(f64, f64)> {
        let (u, v) = self.project_camera(&pose.inverse_transform_point(p_world))?;
        self.in_image(u, v).then_some((u, v))
    }

    /// [`StereoCamera::project`] into the right camera of the pair whose left camera is at `pose`.
    pub fn project_right(
        &self,
        pose: &Isometry3<f64>,
        p_world: &Point3<f64>,
    ) -> Option<(f64, f64)> {
        self.project(&self.right_pose(pose), p_world)
    }

    /// Camera-frame ray direction through (u, v), scaled so its z component is 1: the
    /// ray parameter of a hit is then its depth.
    pub fn ray_camera(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// World point seen at pixel (u, v) at camera depth `depth` by the camera at `pose`.
    pub fn back_project(&self, pose: &Isometry3<f64>, u: f64, v: f64, depth: f64) -> Point3<f64> {
        pose * Point3::from(self.ray_camera(u, v) * depth)
    }
}

/// Camera-to-world pose of a camera at `eye` looking at `target`, with image "up" (−y)
/// as close to `up` as possible.
pub fn look_at(
    eye: Point3<f64>,
    target: Point3<f64>,
    up: Vector3<f64>,
) -> Result<Isometry3<f64>, HilError> {
    let forward = target - eye;
    let z = forward
        .try_normalize(1e-12)
        .ok_or(HilError::DegeneratePose("eye equals target"))?;
    let x = z
        .cross(&up)
        .try_normalize(1e-9)
        .ok_or(HilError::DegeneratePose("looking along up"))?;
    let y = z.cross(&x);
    let rotation = Rotation3::from_basis_unchecked(&[x, y, z]);
    Ok(Isometry3::from_parts(
        eye.into(),
        UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_points_z_forward_and_y_down() {
        let pose = look_at(
            Point3::new(1.0, 2.0, 3.0),
            Point3::new(1.0, 12.0, 3.0),
            Vector3::z(),
        )
        .unwrap();
        let fwd = pose.rotation * Vector3::z();
        let down = pose.rotation * Vector3::y();
        let right = pose.rotation * Vector3::x();
        assert!((fwd - Vector3::y()).norm() < 1e-12);
        assert!((down + Vector3::z()).norm() < 1e-12);
        assert!((right - Vector3::x()).norm() < 1e-12);
    }

    #[test]
    fn project_inverts_back_project() {
        let cam = StereoCamera::euroc_like();
        let pose = look_at(
            Point3::new(0.0, 0.0, 5.0),
            Point3::new(3.0, 10.0, 4.0),
            Vector3::z(),
        )
        .unwrap();
        let p = cam.back_project(&pose, 100.25, 300.75, 12.5);
        let (u, v) = cam.project(&pose, &p).unwrap();
        assert!((u - 100.25).abs() < 1e-9 && (v - 300.75).abs() < 1e-9);
    }

    #[test]
    fn right_camera_sees_points_shifted_left_by_disparity() {
        let cam = StereoCamera::kitti_like();
        let pose = Isometry3::identity();
        let p = Point3::new(0.3, -0.2, 8.0);
        let (ul, vl) = cam.project(&pose, &p).unwrap();
        let (ur, vr) = cam.project_right(&pose, &p).unwrap();
        assert!((ul - ur - cam.disparity(8.0)).abs() < 1e-9);
        assert!((vl - vr).abs() < 1e-12);
    }

    #[test]
    fn invalid_parameters_name_the_field() {
        let err = StereoCamera::new(640, 480, 500.0, 500.0, 320.0, 240.0, 0.0).unwrap_err();
        assert!(err.to_string().contains("baseline"));
        assert!(StereoCamera::new(0, 480, 500.0, 500.0, 320.0, 240.0, 0.1).is_err());
    }
}
