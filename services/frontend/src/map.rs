//! The local map of the odometry: the last few keyframes (the window) and the landmarks
//! they saw, each a world point with its keyframe measurements; the tracked ones also
//! carry where they were in the last frame. At every keyframe the window is adjusted
//! ([`crate::bundle`]) and the odometry edge takes its information from the adjustment.

use std::collections::VecDeque;

use nalgebra::{Matrix3, Vector3};

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{TangentMatrix, SE3};
use doorslam_vision::triangulate;

use crate::bundle::{adjust, relative_covariance, Bundle, BundleObservation};
use crate::refine::{stereo_point_covariance, Noise};

/// One measurement of a landmark in a keyframe: `(u, v, d)`, `d` only when `stereo`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct KeyframeObservation {
    pub keyframe: u64,
    pub uvd: [f64; 3],
    pub stereo: bool,
}

/// A 3-D point of the local map.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Landmark {
    /// World position.
    pub point: Vector3<f64>,
    /// Covariance of `point` (m², world axes).
    pub covariance: Matrix3<f64>,
    /// Its measurements in the window's keyframes, oldest first.
    pub observations: Vec<KeyframeObservation>,
    /// Followed from frame to frame (else only kept for the window's adjustment).
    pub tracked: bool,
    /// Where it was in the last tracked frame (left image), and its disparity there.
    pub pixel: [f32; 2],
    pub disparity: Option<f32>,
    /// Where it was in the current reference keyframe (for the parallax), if seen there.
    pub keyframe_pixel: Option<[f32; 2]>,
}

/// The point, in the world, that a stereo measurement in a keyframe at `pose`
/// triangulates, and its covariance.
fn stereo_point(
    calib: &StereoCalibration,
    noise: &Noise,
    pose: &SE3,
    pixel: [f32; 2],
    disparity: f64,
) -> (Vector3<f64>, Matrix3<f64>) {
    let (u, v) = (pixel[0] as f64, pixel[1] as f64);
    let local = triangulate(calib, u, v, disparity);
    let r = pose.rotation.to_rotation_matrix().into_inner();
    (
        (pose * local).coords,
        r * stereo_point_covariance(calib, noise, u, v, disparity) * r.transpose(),
    )
}

impl Landmark {
    /// Adds a keyframe's stereo measurement and fuses the point it triangulates with the
    /// current estimate (information-weighted: a first guess, which the window's
    /// adjustment then replaces). False, and nothing changed, when degenerate.
    fn observe_stereo(
        &mut self,
        calib: &StereoCalibration,
        noise: &Noise,
        keyframe: u64,
        pose: &SE3,
        disparity: f64,
    ) -> bool {
        let (x, c) = stereo_point(calib, noise, pose, self.pixel, disparity);
        let (Some(wa), Some(wb)) = (self.covariance.try_inverse(), c.try_inverse()) else {
            return false;
        };
        let Some(fused) = (wa + wb).try_inverse() else {
            return false;
        };
        self.point = fused * (wa * self.point + wb * x);
        self.covariance = fused;
        self.observations.push(KeyframeObservation {
            keyframe,
            uvd: [self.pixel[0] as f64, self.pixel[1] as f64, disparity],
            stereo: true,
        });
        true
    }
}

/// A keyframe of the window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct WindowKeyframe {
    pub id: u64,
    pub pose: SE3,
}

/// The adjusted edge from the previous keyframe of the window to the newest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct WindowEdge {
    pub relative: SE3,
    pub covariance: TangentMatrix,
    /// The a-posteriori variance factor of the adjustment (χ² per degree of freedom).
    pub variance_factor: f64,
}

/// Landmarks and the keyframe window.
#[derive(Debug, Default)]
pub(crate) struct LocalMap {
    pub landmarks: Vec<Landmark>,
    pub window: VecDeque<WindowKeyframe>,
}

impl LocalMap {
    pub fn clear(&mut self) {
        self.landmarks.clear();
        self.window.clear();
    }

    pub fn tracked(&self) -> usize {
        self.landmarks.iter().filter(|l| l.tracked).count()
    }

    /// A new keyframe at `pose` (the window keeps the last `capacity`): the tracked
    /// landmarks' measurements in it, at their current pixels.
    pub fn add_keyframe(
        &mut self,
        calib: &StereoCalibration,
        noise: &Noise,
        id: u64,
        pose: SE3,
        capacity: usize,
    ) {
        self.window.push_back(WindowKeyframe { id, pose });
        while self.window.len() > capacity.max(2) {
            self.window.pop_front();
        }
        let oldest = self.window.front().map_or(id, |k| k.id);
        for l in &mut self.landmarks {
            l.observations.retain(|o| o.keyframe >= oldest);
            if !l.tracked {
                continue;
            }
            let stereo = l
                .disparity
                .is_some_and(|d| l.observe_stereo(calib, noise, id, &pose, d as f64));
            if !stereo {
                l.observations.push(KeyframeObservation {
                    keyframe: id,
                    uvd: [l.pixel[0] as f64, l.pixel[1] as f64, 0.0],
                    stereo: false,
                });
            }
            l.keyframe_pixel = Some(l.pixel);
        }
        // What no longer helps: untracked landmarks seen by fewer than two keyframes of
        // the window.
        self.landmarks
            .retain(|l| l.tracked || l.observations.len() >= 2);
    }

    /// A landmark from a stereo measurement in the newest keyframe (`id` at `pose`).
    pub fn add_landmark(
        &mut self,
        calib: &StereoCalibration,
        noise: &Noise,
        id: u64,
        pose: &SE3,
        pixel: [f32; 2],
        disparity: f64,
    ) {
        let (point, covariance) = stereo_point(calib, noise, pose, pixel, disparity);
        if !covariance.iter().all(|x| x.is_finite()) {
            return;
        }
        self.landmarks.push(Landmark {
            point,
            covariance,
            observations: vec![KeyframeObservation {
                keyframe: id,
                uvd: [pixel[0] as f64, pixel[1] as f64, disparity],
                stereo: true,
            }],
            tracked: true,
            pixel,
            disparity: Some(disparity as f32),
            keyframe_pixel: Some(pixel),
        });
    }

    /// Adjusts the window's poses and the points two or more of its keyframes saw; returns
    /// the edge from the second-newest keyframe to the newest. Observations that stay
    /// outliers are dropped (and a tracked landmark whose newest observation is one stops
    /// being tracked). `None` (nothing changed) when the window cannot be adjusted.
    pub fn adjust(
        &mut self,
        calib: &StereoCalibration,
        noise: &Noise,
        outlier_chi2: f64,
        iterations: usize,
    ) -> Option<WindowEdge> {
        let n = self.window.len();
        if n < 2 {
            return None;
        }
        let slot = |id: u64| self.window.iter().position(|k| k.id == id);
        let mut bundle = Bundle {
            poses: self.window.iter().map(|k| k.pose).collect(),
            ..Bundle::default()
        };
        let mut members = Vec::new();
        for (index, l) in self.landmarks.iter().enumerate() {
            if l.observations.len() < 2 {
                continue;
            }
            let point = bundle.points.len();
            bundle.points.push(l.point);
            members.push(index);
            for o in &l.observations {
                if let Some(pose) = slot(o.keyframe) {
                    bundle.observations.push(BundleObservation {
                        point,
                        pose,
                        uvd: o.uvd,
                        stereo: o.stereo,
                    });
                }
            }
        }
        let adjusted = adjust(&mut bundle, calib, noise, outlier_chi2, iterations)?;
        let covariance = relative_covariance(&bundle, &adjusted, n - 2, n - 1);
        // Degrees of freedom: residual dimensions minus the parameters.
        let dof = adjusted.dimensions as f64 - 6.0 * (n - 1) as f64 - 3.0 * members.len() as f64;
        let variance_factor = if dof > 0.0 { adjusted.chi2 / dof } else { 1.0 };
        for (k, w) in self.window.iter_mut().enumerate() {
            w.pose = bundle.poses[k];
        }
        let newest = self.window[n - 1].id;
        let mut observation = 0;
        for (point, &index) in members.iter().enumerate() {
            let l = &mut self.landmarks[index];
            l.point = bundle.points[point];
            l.covariance = adjusted.point_covariances[point];
            let mut k = 0;
            let outliers = &adjusted.outliers[observation..];
            let window = &self.window;
            let mut lost_newest = false;
            l.observations.retain(|o| {
                if slot_of(window, o.keyframe).is_none() {
                    return true;
                }
                let outlier = outliers[k];
                k += 1;
                lost_newest |= outlier && o.keyframe == newest;
                !outlier
            });
            if lost_newest {
                l.tracked = false;
            }
            observation += k;
        }
        let relative = bundle.poses[n - 2].inverse() * bundle.poses[n - 1];
        Some(WindowEdge {
            relative,
            covariance,
            variance_factor,
        })
    }

    /// The newest keyframe's pose (adjusted).
    pub fn newest_pose(&self) -> Option<SE3> {
        self.window.back().map(|k| k.pose)
    }
}

fn slot_of(window: &VecDeque<WindowKeyframe>, id: u64) -> Option<usize> {
    window.iter().position(|k| k.id == id)
}
