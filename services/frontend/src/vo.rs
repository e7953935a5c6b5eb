//! Stereo visual odometry (paper §III-A): frame-to-keyframe tracking of stereo points by
//! descriptor matching around a constant-velocity prediction, PnP-RANSAC, refinement of
//! the stereo reprojection error ([`crate::refine`]), keyframe selection, and the lost /
//! re-initialize / new-segment cycle.

use nalgebra::{Isometry3, Matrix3, Translation3, Vector3};
use opencv::core::{Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{LieGroup, Tangent, SE3, SO3};

use crate::config::VoConfig;
use crate::features::FrontendError;
use crate::keyframe::{Feature, Keyframe, OdometryEdge, SegmentLink};
use crate::refine::{refine, Correspondence, Noise};
use crate::stereo::{
    triangulate, triangulation_jacobian, Extractor, FrameFeature, FrameFeatures, Gray,
};

fn cv(op: &'static str) -> impl FnOnce(opencv::Error) -> FrontendError {
    move |source| FrontendError::OpenCv { op, source }
}

/// Why the odometry could not estimate a frame's pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LostReason {
    /// Blank, over-exposed or textureless image (mean and standard deviation of the left one).
    BadImage { mean: f64, std: f64 },
    /// Too few stereo points to start a segment.
    TooFewPoints { points: usize },
    /// Too few descriptor matches or PnP inliers against the keyframe.
    TrackingFailed { matches: usize, inliers: usize },
    /// The refined motion is faster than `max_speed_mps`.
    Implausible { speed_mps: f64 },
    /// Frames missing for longer than `max_frame_gap_s` (dropped frames, a stopped camera).
    Gap { seconds: f64 },
}

impl std::fmt::Display for LostReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            LostReason::BadImage { mean, std } => write!(
                f,
                "unusable image (mean {mean:.0}, std {std:.1}: blank, over-exposed or textureless)"
            ),
            LostReason::TooFewPoints { points } => write!(f, "only {points} stereo points"),
            LostReason::TrackingFailed { matches, inliers } => {
                write!(f, "tracking failed ({matches} matches, {inliers} inliers)")
            }
            LostReason::Implausible { speed_mps } => {
                write!(f, "implausible motion ({speed_mps:.1} m/s)")
            }
            LostReason::Gap { seconds } => write!(f, "no frames for {seconds:.2} s"),
        }
    }
}

/// What the odometry made of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackState {
    /// The frame started a segment (the first one, or after being lost).
    Initialized,
    /// Tracked against the current keyframe.
    Tracking,
    /// No pose for this frame.
    Lost,
}

/// The odometry's output for one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameResult {
    pub frame: u64,
    pub state: TrackState,
    /// Why the track was lost at this frame (also set on the frame that re-initializes at
    /// once after a [`LostReason::Gap`]).
    pub lost_reason: Option<LostReason>,
    /// Segment of the pose (the last segment while lost).
    pub segment: u32,
    /// Left-camera pose in the odometry's world frame; `None` exactly when `Lost`.
    pub pose: Option<SE3>,
    /// A new keyframe made from this frame.
    pub keyframe: Option<Keyframe>,
    /// The edge from the previous keyframe of the segment to the new one.
    pub edge: Option<OdometryEdge>,
    /// The weak prior from the previous segment, when this frame starts a new one.
    pub link: Option<SegmentLink>,
    /// PnP/refinement inliers against the keyframe (0 when not tracked).
    pub inliers: usize,
}

/// Counters of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct VoStats {
    pub frames: u64,
    pub keyframes: u64,
    /// Times the track was lost.
    pub lost: u64,
    /// Frames without a pose.
    pub lost_frames: u64,
    pub segments: u32,
}

/// The keyframe being tracked against: its stereo points only.
#[derive(Debug, Clone)]
struct ActiveKeyframe {
    id: u64,
    pose: SE3,
    points: Vec<Vector3<f64>>,
    point_jacobians: Vec<Matrix3<f64>>,
    pixels: Vec<[f32; 2]>,
    descriptors: Vec<[u8; 32]>,
}

/// The state while tracking.
#[derive(Debug, Clone)]
struct Track {
    keyframe: ActiveKeyframe,
    /// Last frame's pose (world) and stamp.
    pose: SE3,
    stamp_ns: u64,
    /// Body-frame velocity (tangent per second) of the last motion.
    velocity: Tangent,
}

/// Where the last segment ended, to link the next one.
#[derive(Debug, Clone, Copy)]
struct LastGood {
    keyframe: u64,
    keyframe_pose: SE3,
    pose: SE3,
    stamp_ns: u64,
    velocity: Tangent,
}

/// Stereo visual odometry on rectified pairs.
#[derive(Debug)]
pub struct StereoVo {
    calib: StereoCalibration,
    config: VoConfig,
    extractor: Extractor,
    track: Option<Track>,
    last_good: Option<LastGood>,
    next_keyframe: u64,
    stats: VoStats,
}

/// Tells glibc's allocator to keep freed memory in the process (once per process): OpenCV
/// allocates and frees image-sized buffers every frame, and with the default thresholds
/// each free returned them to the kernel and each allocation faulted them back in, zeroed:
/// a third of the odometry's CPU time at 752×480 (`perf`; 12.0 → 7.9 ms per frame,
/// BENCHMARKS.md). The working set stays what the odometry uses (tens of MB).
fn keep_freed_memory() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: mallopt only changes allocator parameters; it is called once, before
        // this thread allocates for the odometry, and is safe to call at any time.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            libc::mallopt(libc::M_TRIM_THRESHOLD, 512 << 20);
        }
    });
}

fn seconds(from_ns: u64, to_ns: u64) -> f64 {
    to_ns.saturating_sub(from_ns) as f64 * 1e-9
}

impl StereoVo {
    /// Checks the configuration and sets OpenCV's thread count (`threads`, 1 by default).
    pub fn new(calib: StereoCalibration, config: VoConfig) -> Result<Self, FrontendError> {
        config.validate()?;
        keep_freed_memory();
        opencv::core::set_num_threads(config.threads as i32).map_err(cv("setNumThreads"))?;
        Ok(Self {
            extractor: Extractor::new(&config)?,
            calib,
            config,
            track: None,
            last_good: None,
            next_keyframe: 0,
            stats: VoStats::default(),
        })
    }

    pub fn stats(&self) -> VoStats {
        self.stats
    }

    pub fn config(&self) -> &VoConfig {
        &self.config
    }

    /// Processes frame `frame` taken at `stamp_ns` (stamps must not decrease).
    pub fn process(
        &mut self,
        frame: u64,
        stamp_ns: u64,
        left: &Gray<'_>,
        right: &Gray<'_>,
    ) -> Result<FrameResult, FrontendError> {
        if (left.width, left.height) != (right.width, right.height) {
            return Err(FrontendError::ImageSize {
                width: right.width,
                height: right.height,
                bytes: right.pixels.len(),
            });
        }
        self.stats.frames += 1;
        let mut gap_reason = None;
        if let Some(track) = &self.track {
            let gap = seconds(track.stamp_ns, stamp_ns);
            if gap > self.config.max_frame_gap_s {
                gap_reason = Some(LostReason::Gap { seconds: gap });
                self.lose(frame, LostReason::Gap { seconds: gap });
            }
        }
        for image in [left, right] {
            let (mean, std) = image.mean_std();
            if mean < self.config.min_mean_intensity
                || mean > self.config.max_mean_intensity
                || std < self.config.min_intensity_std
            {
                return Ok(self.lost_frame(frame, LostReason::BadImage { mean, std }));
            }
        }
        let features = self.extractor.extract(left, right)?;
        let mut result = match self.track.is_some() {
            true => self.track(frame, stamp_ns, &features),
            false => self.initialize(frame, stamp_ns, &features),
        };
        if gap_reason.is_some() {
            result.lost_reason = gap_reason;
        }
        Ok(result)
    }

    /// Marks the track lost (counted and logged once per loss).
    fn lose(&mut self, frame: u64, reason: LostReason) {
        if let Some(track) = self.track.take() {
            self.stats.lost += 1;
            tracing::warn!(frame, %reason, "visual odometry lost");
            self.last_good = Some(LastGood {
                keyframe: track.keyframe.id,
                keyframe_pose: track.keyframe.pose,
                pose: track.pose,
                stamp_ns: track.stamp_ns,
                velocity: track.velocity,
            });
        }
    }

    fn lost_frame(&mut self, frame: u64, reason: LostReason) -> FrameResult {
        self.lose(frame, reason);
        self.stats.lost_frames += 1;
        tracing::debug!(frame, %reason, "frame without pose");
        FrameResult {
            frame,
            state: TrackState::Lost,
            lost_reason: Some(reason),
            segment: self.stats.segments.saturating_sub(1),
            pose: None,
            keyframe: None,
            edge: None,
            link: None,
            inliers: 0,
        }
    }

    /// Stereo points of a frame as a keyframe (`None` when too few).
    fn make_keyframe(
        &mut self,
        frame: u64,
        stamp_ns: u64,
        pose: SE3,
        features: &FrameFeatures,
    ) -> Option<(ActiveKeyframe, Keyframe)> {
        let stereo = stereo_points(features);
        if stereo.len() < self.config.min_keyframe_points {
            return None;
        }
        let id = self.next_keyframe;
        self.next_keyframe += 1;
        self.stats.keyframes += 1;
        let mut active = ActiveKeyframe {
            id,
            pose,
            points: Vec::with_capacity(stereo.len()),
            point_jacobians: Vec::with_capacity(stereo.len()),
            pixels: Vec::with_capacity(stereo.len()),
            descriptors: Vec::with_capacity(stereo.len()),
        };
        for &(f, d) in &stereo {
            let (u, v) = (f.pixel[0] as f64, f.pixel[1] as f64);
            active.points.push(triangulate(&self.calib, u, v, d).coords);
            active
                .point_jacobians
                .push(triangulation_jacobian(&self.calib, u, v, d));
            active.pixels.push(f.pixel);
            active.descriptors.push(f.descriptor);
        }
        let keyframe = Keyframe {
            id,
            segment: self.stats.segments.saturating_sub(1),
            frame,
            stamp_ns,
            pose,
            features: keyframe_features(&self.calib, &self.config, &stereo),
        };
        Some((active, keyframe))
    }

    /// The features a keyframe made of this pair would carry (strongest first), without
    /// touching the odometry's state: for verifying arbitrary frames (benchmarks, tools).
    pub fn keyframe_features(
        &mut self,
        left: &Gray<'_>,
        right: &Gray<'_>,
    ) -> Result<Vec<Feature>, FrontendError> {
        let features = self.extractor.extract(left, right)?;
        Ok(keyframe_features(
            &self.calib,
            &self.config,
            &stereo_points(&features),
        ))
    }

    fn initialize(&mut self, frame: u64, stamp_ns: u64, features: &FrameFeatures) -> FrameResult {
        // A new segment starts where the last one was seen, moved on by its last motion
        // over the time lost; the link's covariance says how little that guess is worth.
        let (pose, velocity) = match &self.last_good {
            Some(g) => {
                let dt = seconds(g.stamp_ns, stamp_ns);
                (g.pose.oplus(&(g.velocity * dt)), g.velocity)
            }
            None => (SE3::identity(), Tangent::zeros()),
        };
        let points = features
            .features
            .iter()
            .filter(|f| f.disparity.is_some())
            .count();
        self.stats.segments += 1;
        let Some((active, keyframe)) = self.make_keyframe(frame, stamp_ns, pose, features) else {
            self.stats.segments -= 1;
            return self.lost_frame(frame, LostReason::TooFewPoints { points });
        };
        let link = self.last_good.take().map(|g| SegmentLink {
            from: g.keyframe,
            to: keyframe.id,
            relative: g.keyframe_pose.inverse() * pose,
            information: self
                .config
                .segment_prior_information(seconds(g.stamp_ns, stamp_ns)),
        });
        tracing::info!(
            frame,
            segment = keyframe.segment,
            points = keyframe.features.len(),
            "visual odometry initialized"
        );
        self.track = Some(Track {
            keyframe: active,
            pose,
            stamp_ns,
            velocity,
        });
        FrameResult {
            frame,
            state: TrackState::Initialized,
            lost_reason: None,
            segment: keyframe.segment,
            pose: Some(pose),
            keyframe: Some(keyframe),
            edge: None,
            link,
            inliers: 0,
        }
    }

    fn track(&mut self, frame: u64, stamp_ns: u64, features: &FrameFeatures) -> FrameResult {
        let track = self.track.as_ref().expect("tracking");
        let kf = &track.keyframe;
        let dt = seconds(track.stamp_ns, stamp_ns);
        let predicted = track.pose.oplus(&(track.velocity * dt));
        let prior = kf.pose.inverse() * predicted;

        let mut pairs = match_projected(
            kf,
            &prior,
            features,
            &self.calib,
            &self.config,
            self.config.search_radius_px,
        );
        if pairs.len() < 4 * self.config.min_inliers {
            let wide = match_projected(
                kf,
                &prior,
                features,
                &self.calib,
                &self.config,
                self.config.wide_search_radius_px,
            );
            if wide.len() > pairs.len() {
                pairs = wide;
            }
        }
        let fail = |inliers| LostReason::TrackingFailed {
            matches: pairs.len(),
            inliers,
        };
        if pairs.len() < self.config.min_inliers {
            return self.lost_frame(frame, fail(0));
        }
        let (pnp_pose, pnp_inliers) =
            match pnp_ransac(kf, &pairs, features, &self.calib, &self.config) {
                Ok(Some(x)) => x,
                Ok(None) | Err(_) => return self.lost_frame(frame, fail(0)),
            };
        if pnp_inliers.len() < self.config.min_inliers {
            return self.lost_frame(frame, fail(pnp_inliers.len()));
        }
        let correspondences: Vec<Correspondence> = pairs
            .iter()
            .map(|&(k, c)| {
                let f = &features.features[c];
                Correspondence {
                    point: kf.points[k],
                    point_jacobian: kf.point_jacobians[k],
                    pixel: [f.pixel[0] as f64, f.pixel[1] as f64],
                    disparity: f.disparity.map(|d| d as f64),
                }
            })
            .collect();
        let noise = Noise {
            pixel_sigma_px: self.config.pixel_sigma_px,
            disparity_sigma_px: self.config.disparity_sigma_px,
            posterior_variance: self.config.posterior_variance,
            scale_sigma: self.config.scale_sigma,
            rotation_sigma_rad: self.config.rotation_sigma_deg.to_radians(),
            translation_sigma_m: self.config.translation_sigma_m,
        };
        let Some(refined) = refine(
            &self.calib,
            &noise,
            &correspondences,
            pnp_pose,
            &pnp_inliers,
            self.config.outlier_chi2,
            self.config.min_inliers,
        ) else {
            return self.lost_frame(frame, fail(pnp_inliers.len()));
        };
        let pose = kf.pose * refined.pose;
        let step = track.pose.inverse() * pose;
        let speed = step.translation.vector.norm() / dt.max(1e-3);
        if speed > self.config.max_speed_mps {
            return self.lost_frame(frame, LostReason::Implausible { speed_mps: speed });
        }
        let velocity = if dt > 0.0 {
            step.log() / dt
        } else {
            track.velocity
        };

        // Keyframe selection: the keyframe's points are running out, or the view has
        // changed enough (distance, rotation, parallax) that a fresh set tracks better.
        let inliers = refined.inliers.len();
        let tracked_fraction = inliers as f64 / kf.points.len() as f64;
        let mut parallax: Vec<f32> = refined
            .inliers
            .iter()
            .map(|&i| {
                let (k, c) = pairs[i];
                let (a, b) = (kf.pixels[k], features.features[c].pixel);
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
            })
            .collect();
        let mid = parallax.len() / 2;
        let median_parallax = *parallax.select_nth_unstable_by(mid, f32::total_cmp).1 as f64;
        let need_keyframe = tracked_fraction < self.config.keyframe_min_tracked_fraction
            || refined.pose.translation.vector.norm() > self.config.keyframe_max_distance_m
            || refined.pose.rotation.angle().to_degrees() > self.config.keyframe_max_rotation_deg
            || median_parallax > self.config.keyframe_max_parallax_px;

        let from = kf.id;
        let mut result = FrameResult {
            frame,
            state: TrackState::Tracking,
            lost_reason: None,
            segment: self.stats.segments - 1,
            pose: Some(pose),
            keyframe: None,
            edge: None,
            link: None,
            inliers,
        };
        if need_keyframe {
            if let Some((active, keyframe)) = self.make_keyframe(frame, stamp_ns, pose, features) {
                result.edge = Some(OdometryEdge {
                    from,
                    to: keyframe.id,
                    relative: refined.pose,
                    information: refined.information,
                });
                result.keyframe = Some(keyframe);
                self.track.as_mut().expect("tracking").keyframe = active;
            }
        }
        let track = self.track.as_mut().expect("tracking");
        track.pose = pose;
        track.stamp_ns = stamp_ns;
        track.velocity = velocity;
        result
    }
}

/// The features of a frame that have a disparity, strongest first (the order keyframes
/// keep, so the first N of a keyframe are its best).
fn stereo_points(features: &FrameFeatures) -> Vec<(&FrameFeature, f64)> {
    let mut stereo: Vec<_> = features
        .features
        .iter()
        .filter_map(|f| f.disparity.map(|d| (f, d as f64)))
        .collect();
    stereo.sort_by(|a, b| b.0.response.total_cmp(&a.0.response));
    stereo
}

/// Keyframe features of stereo points: each triangulated, with its depth σ.
fn keyframe_features(
    calib: &StereoCalibration,
    config: &VoConfig,
    stereo: &[(&FrameFeature, f64)],
) -> Vec<Feature> {
    stereo
        .iter()
        .map(|&(f, d)| {
            let p = triangulate(calib, f.pixel[0] as f64, f.pixel[1] as f64, d);
            Feature {
                pixel: f.pixel,
                descriptor: f.descriptor,
                point: [p.x as f32, p.y as f32, p.z as f32],
                depth_sigma_m: (p.z / d * config.disparity_sigma_px) as f32,
            }
        })
        .collect()
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

/// Matches keyframe points to current features near where the prior pose `prior` (current
/// camera in the keyframe frame) projects them: best Hamming distance within `radius` px,
/// below `max_hamming`, clearly better than the second best, one-to-one.
fn match_projected(
    kf: &ActiveKeyframe,
    prior: &SE3,
    features: &FrameFeatures,
    calib: &StereoCalibration,
    config: &VoConfig,
    radius: f64,
) -> Vec<(usize, usize)> {
    let cell = radius.max(8.0);
    let (mut umax, mut vmax) = (0.0f32, 0.0f32);
    for f in &features.features {
        umax = umax.max(f.pixel[0]);
        vmax = vmax.max(f.pixel[1]);
    }
    let cols = (umax as f64 / cell) as usize + 1;
    let rows = (vmax as f64 / cell) as usize + 1;
    let mut grid: Vec<Vec<u32>> = vec![Vec::new(); cols * rows];
    for (i, f) in features.features.iter().enumerate() {
        let (cx, cy) = (
            (f.pixel[0] as f64 / cell) as usize,
            (f.pixel[1] as f64 / cell) as usize,
        );
        grid[cy * cols + cx].push(i as u32);
    }
    let inv = prior.inverse();
    // owner[c] = (distance, keyframe index) of the best claim on current feature c.
    let mut owner: Vec<Option<(u32, usize)>> = vec![None; features.features.len()];
    let r2 = (radius * radius) as f32;
    for (k, p) in kf.points.iter().enumerate() {
        let q = inv * nalgebra::Point3::from(*p);
        if q.z < 0.1 {
            continue;
        }
        let u = calib.fx * q.x / q.z + calib.cx;
        let v = calib.fy * q.y / q.z + calib.cy;
        if !(u > -radius && v > -radius && u < umax as f64 + radius && v < vmax as f64 + radius) {
            continue;
        }
        let (c0, c1) = (
            ((u - radius).max(0.0) / cell) as usize,
            (((u + radius).max(0.0) / cell) as usize).min(cols - 1),
        );
        let (r0, r1) = (
            ((v - radius).max(0.0) / cell) as usize,
            (((v + radius).max(0.0) / cell) as usize).min(rows - 1),
        );
        let (mut best, mut second, mut best_i) = (u32::MAX, u32::MAX, usize::MAX);
        for gy in r0..=r1 {
            for gx in c0..=c1 {
                for &i in &grid[gy * cols + gx] {
                    let f = &features.features[i as usize];
                    let (du, dv) = (f.pixel[0] - u as f32, f.pixel[1] - v as f32);
                    if du * du + dv * dv > r2 {
                        continue;
                    }
                    let d = hamming(&kf.descriptors[k], &f.descriptor);
                    if d < best {
                        second = best;
                        best = d;
                        best_i = i as usize;
                    } else if d < second {
                        second = d;
                    }
                }
            }
        }
        if best > config.max_hamming
            || (second != u32::MAX && best as f64 > config.match_ratio * second as f64)
        {
            continue;
        }
        match owner[best_i] {
            Some((d, _)) if d <= best => {}
            _ => owner[best_i] = Some((best, k)),
        }
    }
    owner
        .iter()
        .enumerate()
        .filter_map(|(c, o)| o.map(|(_, k)| (k, c)))
        .collect()
}

/// solvePnPRansac of keyframe points against current pixels: the current camera's pose in
/// the keyframe frame and the indices (into `pairs`) of its inliers.
fn pnp_ransac(
    kf: &ActiveKeyframe,
    pairs: &[(usize, usize)],
    features: &FrameFeatures,
    calib: &StereoCalibration,
    config: &VoConfig,
) -> Result<Option<(SE3, Vec<usize>)>, FrontendError> {
    let points: Vec<Vector3<f64>> = pairs.iter().map(|&(k, _)| kf.points[k]).collect();
    let pixels: Vec<[f32; 2]> = pairs
        .iter()
        .map(|&(_, c)| features.features[c].pixel)
        .collect();
    pnp_from_points(
        &points,
        &pixels,
        calib,
        config.ransac_iterations,
        config.ransac_threshold_px,
    )
}

/// solvePnPRansac of 3-D points (in a reference camera frame) against the pixels where a
/// second camera sees them: that camera's pose in the reference frame, and the inliers.
pub(crate) fn pnp_from_points(
    points: &[Vector3<f64>],
    pixels: &[[f32; 2]],
    calib: &StereoCalibration,
    iterations: i32,
    threshold_px: f64,
) -> Result<Option<(SE3, Vec<usize>)>, FrontendError> {
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
