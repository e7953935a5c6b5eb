//! What the odometry hands downstream (place recognition, verification, the back-end): the
//! contract of the front-end.

use doorslam_geometry::{TangentMatrix, SE3};

/// A keyframe feature: everything geometric verification needs about it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Feature {
    /// Sub-pixel position (u, v) in the left image.
    pub pixel: [f32; 2],
    /// 256-bit ORB descriptor.
    pub descriptor: [u8; 32],
    /// Triangulated point in the keyframe's left-camera frame (x right, y down, z forward), m.
    pub point: [f32; 3],
    /// Standard deviation of the point's depth (m): `z² σd / (fx b)`, the stereo uncertainty.
    pub depth_sigma_m: f32,
}

/// A keyframe of the odometry.
#[derive(Debug, Clone, PartialEq)]
pub struct Keyframe {
    /// Keyframe index, increasing over the whole run (across segments).
    pub id: u64,
    /// Tracking segment: starts at 0 and grows by one each time the odometry re-initializes
    /// after being lost. Keyframes of different segments are not linked by odometry edges.
    pub segment: u32,
    /// Index of the frame it was made from, and that frame's stamp.
    pub frame: u64,
    pub stamp_ns: u64,
    /// Left-camera pose (camera-to-world) in the odometry's world frame; a new segment starts
    /// where the previous one was last seen, moved by its last motion (see [`SegmentLink`]).
    pub pose: SE3,
    /// Its stereo features, strongest detector response first: the first N are the best N
    /// (what [`crate::packet::to_packet`] sends).
    pub features: Vec<Feature>,
}

/// A relative-pose measurement between consecutive keyframes of one segment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometryEdge {
    /// Keyframe ids.
    pub from: u64,
    pub to: u64,
    /// Pose of `to` in the frame of `from`: `X_from⁻¹ · X_to`.
    pub relative: SE3,
    /// Information (inverse covariance) of `relative` under the right perturbation
    /// `relative · Exp(δ)`, rotation first (doorslam-geometry's order): `Σ Jᵀ Σr⁻¹ J` of the
    /// reprojection refinement at its optimum.
    pub information: TangentMatrix,
}

/// The weak prior joining a new segment to the previous one: the last good motion carried
/// over the time lost, with a covariance that grows with that time, so the back-end keeps
/// one connected graph and loop closures can correct the guess.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentLink {
    /// Last keyframe of the previous segment and first keyframe of the new one.
    pub from: u64,
    pub to: u64,
    pub relative: SE3,
    pub information: TangentMatrix,
}
