//! Stereo visual odometry (paper §III-A). Each frame goes through the same stages:
//!
//! 1. **predict** the camera's pose from the last motion (constant velocity);
//! 2. **track** the local map's landmarks from the previous frame by pyramidal KLT, seeded
//!    where the prediction projects them, forward-backward checked, and measure their
//!    disparity ([`crate::tracking`]);
//! 3. **estimate** the pose against the landmarks (PnP-RANSAC, then the stereo
//!    reprojection refinement) and **validate** it: enough inliers, a large enough share
//!    of the tracks, agreement with the prediction, a plausible speed ([`crate::motion`]);
//!    a pose that fails is a loss, never an output;
//! 4. decide on a **keyframe**: its features (GFTT + ORB + stereo, what downstream
//!    services get), the landmarks' fused positions ([`crate::map`]), new landmarks where
//!    the image has none, and the odometry edge from the previous keyframe.
//!
//! Losses start a new segment on the next good frame, linked to the previous one by a
//! weak prior; every loss is counted by its reason.

use nalgebra::{Point3, Vector3};

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{LieGroup, Tangent, SE3};
use doorslam_vision::{
    triangulate, Extractor, FrameFeature, FrameFeatures, Gray, KltConfig, KltScratch, Pyramid,
    VisionError,
};

use crate::config::VoConfig;
use crate::error::FrontendError;
use crate::keyframe::{Feature, Keyframe, OdometryEdge, SegmentLink};
use crate::map::{LocalMap, WindowEdge};
use crate::motion::{estimate_motion, prediction_error, MotionSettings};
use crate::refine::{with_blur_errors, with_shared_errors, Correspondence, Noise};
use crate::run::thread_cpu_s;
use crate::tracking::{track_landmarks, TrackSettings, TrackedPoint};

/// Why the odometry could not estimate a frame's pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LostReason {
    /// Blank, over-exposed or textureless image (mean and standard deviation of the left one).
    BadImage { mean: f64, std: f64 },
    /// Too few stereo points to start a segment.
    TooFewPoints { points: usize },
    /// Too few tracked landmarks or pose inliers among them.
    TrackingFailed { matches: usize, inliers: usize },
    /// The refined motion is faster than `max_speed_mps`.
    Implausible { speed_mps: f64 },
    /// The pose disagrees with the motion prediction by more than a drone can change its
    /// motion in the time (`max_prediction_error_deg`, `max_prediction_error_m`).
    Unpredicted {
        rotation_deg: f64,
        translation_m: f64,
    },
    /// Frames missing for longer than `max_frame_gap_s` (dropped frames, a stopped camera).
    Gap { seconds: f64 },
}

impl LostReason {
    /// A short name per kind (the keys of `doorslam vo --json`'s `lost_by_reason`).
    pub fn name(&self) -> &'static str {
        match self {
            LostReason::BadImage { .. } => "bad_image",
            LostReason::TooFewPoints { .. } => "too_few_points",
            LostReason::TrackingFailed { .. } => "tracking_failed",
            LostReason::Implausible { .. } => "implausible",
            LostReason::Unpredicted { .. } => "unpredicted",
            LostReason::Gap { .. } => "gap",
        }
    }
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
                write!(f, "tracking failed ({matches} tracked, {inliers} inliers)")
            }
            LostReason::Implausible { speed_mps } => {
                write!(f, "implausible motion ({speed_mps:.1} m/s)")
            }
            LostReason::Unpredicted {
                rotation_deg,
                translation_m,
            } => write!(
                f,
                "pose {rotation_deg:.1} deg / {translation_m:.2} m away from the prediction"
            ),
            LostReason::Gap { seconds } => write!(f, "no frames for {seconds:.2} s"),
        }
    }
}

/// What the odometry made of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackState {
    /// The frame started a segment (the first one, or after being lost).
    Initialized,
    /// Tracked against the local map.
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
    /// Pose inliers among the tracked landmarks (0 when not tracked).
    pub inliers: usize,
}

/// Losses of a run by their reason ([`LostReason::name`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LostByReason {
    pub bad_image: u64,
    pub too_few_points: u64,
    pub tracking_failed: u64,
    pub implausible: u64,
    pub unpredicted: u64,
    pub gap: u64,
}

impl LostByReason {
    fn count(&mut self, reason: &LostReason) {
        let slot = match reason {
            LostReason::BadImage { .. } => &mut self.bad_image,
            LostReason::TooFewPoints { .. } => &mut self.too_few_points,
            LostReason::TrackingFailed { .. } => &mut self.tracking_failed,
            LostReason::Implausible { .. } => &mut self.implausible,
            LostReason::Unpredicted { .. } => &mut self.unpredicted,
            LostReason::Gap { .. } => &mut self.gap,
        };
        *slot += 1;
    }

    /// (name, count) of every reason, in a fixed order.
    pub fn entries(&self) -> [(&'static str, u64); 6] {
        [
            ("bad_image", self.bad_image),
            ("too_few_points", self.too_few_points),
            ("tracking_failed", self.tracking_failed),
            ("implausible", self.implausible),
            ("unpredicted", self.unpredicted),
            ("gap", self.gap),
        ]
    }
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
    /// `lost`, split by the reason of each loss.
    pub lost_by_reason: LostByReason,
}

impl std::ops::Add for LostByReason {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self {
            bad_image: self.bad_image + o.bad_image,
            too_few_points: self.too_few_points + o.too_few_points,
            tracking_failed: self.tracking_failed + o.tracking_failed,
            implausible: self.implausible + o.implausible,
            unpredicted: self.unpredicted + o.unpredicted,
            gap: self.gap + o.gap,
        }
    }
}

/// Counters of two odometry instances (a restarted camera's), together.
impl std::ops::Add for VoStats {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self {
            frames: self.frames + o.frames,
            keyframes: self.keyframes + o.keyframes,
            lost: self.lost + o.lost,
            lost_frames: self.lost_frames + o.lost_frames,
            segments: self.segments + o.segments,
            lost_by_reason: self.lost_by_reason + o.lost_by_reason,
        }
    }
}

/// CPU time (ms, this thread) spent in each stage over a run: where a frame's cost goes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StageCpu {
    /// Image checks and the pyramid.
    pub prepare_ms: f64,
    /// KLT of the landmarks and their disparities.
    pub track_ms: f64,
    /// PnP-RANSAC, refinement, checks.
    pub estimate_ms: f64,
    /// Keyframe features (GFTT, ORB, stereo), new landmarks.
    pub keyframe_ms: f64,
    /// The window's bundle adjustment.
    pub adjust_ms: f64,
}

impl StageCpu {
    /// (name, ms) of every stage, in frame order.
    pub fn entries(&self) -> [(&'static str, f64); 5] {
        [
            ("prepare", self.prepare_ms),
            ("track", self.track_ms),
            ("estimate", self.estimate_ms),
            ("keyframe", self.keyframe_ms),
            ("adjust", self.adjust_ms),
        ]
    }
}

/// A stopwatch on this thread's CPU clock.
struct Lap(f64);

impl Lap {
    fn start() -> Self {
        Self(thread_cpu_s())
    }
    /// Milliseconds since the last lap (or the start), and restarts.
    fn lap(&mut self) -> f64 {
        let now = thread_cpu_s();
        let ms = (now - self.0) * 1e3;
        self.0 = now;
        ms
    }
}

/// The keyframe the current frame's pose is estimated against.
#[derive(Debug, Clone, Copy)]
struct Reference {
    id: u64,
    pose: SE3,
    /// Landmarks tracked when it was made.
    landmarks: usize,
    /// The camera's angular velocity (rad/s, body frame) when it was made: how far its
    /// image's motion blur may have moved its pose ([`with_blur_errors`]).
    angular_velocity: Vector3<f64>,
}

/// The state while tracking.
#[derive(Debug, Clone)]
struct Track {
    reference: Reference,
    /// Last frame's pose (world) and stamp.
    pose: SE3,
    stamp_ns: u64,
    /// Body-frame velocity (tangent per second) of the last motion.
    velocity: Tangent,
    /// False on a segment's first frame without a recent motion to carry over: the
    /// prediction is then a guess, and a pose is not checked against it.
    velocity_known: bool,
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
pub struct StereoVo {
    calib: StereoCalibration,
    config: VoConfig,
    extractor: Extractor,
    klt: KltConfig,
    scratch: KltScratch,
    /// The previous frame's pyramid and the current one's (swapped after each frame).
    previous: Pyramid,
    current: Pyramid,
    map: LocalMap,
    tracked: Vec<TrackedPoint>,
    track: Option<Track>,
    last_good: Option<LastGood>,
    next_keyframe: u64,
    stats: VoStats,
    stages: StageCpu,
}

impl std::fmt::Debug for StereoVo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StereoVo")
            .field("stats", &self.stats)
            .field("landmarks", &self.map.landmarks.len())
            .finish()
    }
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
        doorslam_vision::set_threads(config.threads)?;
        Ok(Self {
            extractor: Extractor::new(&config.features())?,
            klt: config.klt(),
            scratch: KltScratch::default(),
            previous: Pyramid::default(),
            current: Pyramid::default(),
            map: LocalMap::default(),
            tracked: Vec::new(),
            calib,
            config,
            track: None,
            last_good: None,
            next_keyframe: 0,
            stats: VoStats::default(),
            stages: StageCpu::default(),
        })
    }

    pub fn stats(&self) -> VoStats {
        self.stats
    }

    /// CPU time per stage so far.
    pub fn stage_cpu(&self) -> StageCpu {
        self.stages
    }

    pub fn config(&self) -> &VoConfig {
        &self.config
    }

    fn noise(&self) -> Noise {
        Noise {
            pixel_sigma_px: self.config.pixel_sigma_px,
            disparity_sigma_px: self.config.disparity_sigma_px,
            posterior_variance: self.config.posterior_variance,
            scale_sigma: self.config.scale_sigma,
            rotation_sigma_rad: self.config.rotation_sigma_deg.to_radians(),
            rotation_sigma_rad_per_m: self.config.rotation_sigma_deg_per_m.to_radians(),
            translation_sigma_m: self.config.translation_sigma_m,
            translation_sigma_per_m: self.config.translation_sigma_per_m,
        }
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
            return Err(VisionError::ImageSize {
                width: right.width,
                height: right.height,
                bytes: right.pixels.len(),
            }
            .into());
        }
        self.stats.frames += 1;
        let mut lap = Lap::start();
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
                self.stages.prepare_ms += lap.lap();
                return Ok(self.lost_frame(frame, LostReason::BadImage { mean, std }));
            }
        }
        self.current.build(left, self.klt.levels)?;
        self.stages.prepare_ms += lap.lap();
        let mut result = match self.track.is_some() {
            true => self.track(frame, stamp_ns, left, right)?,
            false => self.initialize(frame, stamp_ns, left, right)?,
        };
        if result.state != TrackState::Lost {
            // This frame is the one the next is tracked from.
            std::mem::swap(&mut self.previous, &mut self.current);
        }
        if gap_reason.is_some() {
            result.lost_reason = gap_reason;
        }
        Ok(result)
    }

    /// Marks the track lost (counted and logged once per loss).
    fn lose(&mut self, frame: u64, reason: LostReason) {
        if let Some(track) = self.track.take() {
            self.stats.lost += 1;
            self.stats.lost_by_reason.count(&reason);
            tracing::warn!(frame, %reason, "visual odometry lost");
            self.last_good = Some(LastGood {
                keyframe: track.reference.id,
                keyframe_pose: track.reference.pose,
                pose: track.pose,
                stamp_ns: track.stamp_ns,
                velocity: track.velocity,
            });
            self.map.clear();
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

    /// A keyframe at `pose` from this frame: its features, the tracked landmarks'
    /// measurements in it, the window adjusted (when `adjust`, returning the adjusted edge
    /// from the previous keyframe), and new landmarks where the image has none. `None`, and
    /// nothing changed, when the pair has too few stereo points.
    fn make_keyframe(
        &mut self,
        frame: u64,
        stamp_ns: u64,
        pose: SE3,
        images: (&Gray<'_>, &Gray<'_>),
        adjust: bool,
    ) -> Result<Option<(Reference, Keyframe, Option<WindowEdge>)>, FrontendError> {
        let (left, right) = images;
        let mut lap = Lap::start();
        let features = self.extractor.extract(left, right)?;
        let stereo = stereo_points(&features);
        self.stages.keyframe_ms += lap.lap();
        if stereo.len() < self.config.min_keyframe_points {
            return Ok(None);
        }
        let id = self.next_keyframe;
        self.next_keyframe += 1;
        self.stats.keyframes += 1;
        let noise = self.noise();
        self.map
            .add_keyframe(&self.calib, &noise, id, pose, self.config.window_keyframes);
        let edge = match adjust {
            true => self.map.adjust(
                &self.calib,
                &noise,
                self.config.outlier_chi2,
                self.config.window_iterations,
            ),
            false => None,
        };
        self.stages.adjust_ms += lap.lap();
        let pose = self.map.newest_pose().unwrap_or(pose);
        // New landmarks only in image cells without a tracked one.
        let cell = self.config.min_feature_distance_px.max(2.0) as f32;
        let cols = (left.width as f32 / cell) as usize + 1;
        let rows = (left.height as f32 / cell) as usize + 1;
        let mut occupied = vec![false; cols * rows];
        let cell_of = |p: [f32; 2]| {
            let (x, y) = ((p[0] / cell) as usize, (p[1] / cell) as usize);
            x.min(cols - 1) + cols * y.min(rows - 1)
        };
        let mut tracked = 0;
        for l in self.map.landmarks.iter().filter(|l| l.tracked) {
            occupied[cell_of(l.pixel)] = true;
            tracked += 1;
        }
        for &(f, d) in &stereo {
            if tracked >= self.config.max_tracks {
                break;
            }
            let c = cell_of(f.pixel);
            if occupied[c] {
                continue;
            }
            occupied[c] = true;
            self.map
                .add_landmark(&self.calib, &noise, id, &pose, f.pixel, d);
            tracked += 1;
        }
        let keyframe = Keyframe {
            id,
            segment: self.stats.segments.saturating_sub(1),
            frame,
            stamp_ns,
            pose,
            features: keyframe_features(&self.calib, &self.config, &stereo),
        };
        let reference = Reference {
            id,
            pose,
            landmarks: self.map.tracked(),
            angular_velocity: Vector3::zeros(),
        };
        self.stages.keyframe_ms += lap.lap();
        Ok(Some((reference, keyframe, edge)))
    }

    /// The information of an adjusted edge: the adjustment's covariance, scaled by its
    /// a-posteriori variance factor when the residuals exceed the noise model, plus the
    /// errors every feature shares.
    fn adjusted_information(&self, edge: &WindowEdge) -> Option<nalgebra::Matrix6<f64>> {
        let mut covariance = edge.covariance;
        if self.config.posterior_variance && edge.variance_factor > 1.0 {
            covariance *= edge.variance_factor;
        }
        let information = covariance.try_inverse()?;
        with_shared_errors(&information, &edge.relative, &self.noise())
    }

    fn initialize(
        &mut self,
        frame: u64,
        stamp_ns: u64,
        left: &Gray<'_>,
        right: &Gray<'_>,
    ) -> Result<FrameResult, FrontendError> {
        // A new segment starts where the last one was seen, moved on by its last motion
        // over the time lost; the link's covariance says how little that guess is worth.
        let (pose, velocity, velocity_known) = match &self.last_good {
            Some(g) => {
                let dt = seconds(g.stamp_ns, stamp_ns);
                (
                    g.pose.oplus(&(g.velocity * dt)),
                    g.velocity,
                    dt <= self.config.max_frame_gap_s,
                )
            }
            None => (SE3::identity(), Tangent::zeros(), false),
        };
        self.map.clear();
        self.stats.segments += 1;
        let Some((mut reference, keyframe, _)) =
            self.make_keyframe(frame, stamp_ns, pose, (left, right), false)?
        else {
            self.stats.segments -= 1;
            let points = self.extractor.extract(left, right)?.features;
            let points = points.len();
            return Ok(self.lost_frame(frame, LostReason::TooFewPoints { points }));
        };
        let link = self.last_good.take().map(|g| SegmentLink {
            from: g.keyframe,
            to: keyframe.id,
            relative: g.keyframe_pose.inverse() * pose,
            information: self
                .config
                .segment_prior_information(seconds(g.stamp_ns, stamp_ns)),
        });
        reference.angular_velocity = velocity.fixed_rows::<3>(0).into_owned();
        tracing::info!(
            frame,
            segment = keyframe.segment,
            points = keyframe.features.len(),
            "visual odometry initialized"
        );
        self.track = Some(Track {
            reference,
            pose,
            stamp_ns,
            velocity,
            velocity_known,
        });
        Ok(FrameResult {
            frame,
            state: TrackState::Initialized,
            lost_reason: None,
            segment: keyframe.segment,
            pose: Some(pose),
            keyframe: Some(keyframe),
            edge: None,
            link,
            inliers: 0,
        })
    }

    fn track(
        &mut self,
        frame: u64,
        stamp_ns: u64,
        left: &Gray<'_>,
        right: &Gray<'_>,
    ) -> Result<FrameResult, FrontendError> {
        let track = self.track.clone().expect("tracking");
        let reference = track.reference;
        let mut lap = Lap::start();

        // 1. Predict.
        let dt = seconds(track.stamp_ns, stamp_ns);
        let predicted = track.pose.oplus(&(track.velocity * dt));

        // 2. Track the landmarks into this frame.
        let features = self.config.features();
        let settings = TrackSettings {
            klt: &self.klt,
            features: &features,
            max_back_error_px: self.config.klt_max_back_error_px as f32,
        };
        let mut tracked = std::mem::take(&mut self.tracked);
        let counts = track_landmarks(
            &self.calib,
            &self.map.landmarks,
            &predicted,
            &self.previous,
            &self.current,
            right,
            &settings,
            &mut self.scratch,
            &mut tracked,
        );
        tracing::trace!(frame, ?counts, "tracked");
        self.stages.track_ms += lap.lap();

        // 3. Estimate the pose in the reference keyframe's frame, and validate it.
        let to_reference = reference.pose.inverse();
        let r = to_reference.rotation.to_rotation_matrix().into_inner();
        let correspondences: Vec<Correspondence> = tracked
            .iter()
            .map(|t| {
                let l = &self.map.landmarks[t.landmark];
                Correspondence {
                    point: (to_reference * Point3::from(l.point)).coords,
                    point_covariance: r * l.covariance * r.transpose(),
                    pixel: [t.pixel[0] as f64, t.pixel[1] as f64],
                    disparity: t.disparity.map(|d| d as f64),
                }
            })
            .collect();
        let motion = MotionSettings {
            noise: self.noise(),
            ransac_iterations: self.config.ransac_iterations,
            ransac_threshold_px: self.config.ransac_threshold_px,
            outlier_chi2: self.config.outlier_chi2,
            min_inliers: self.config.min_inliers,
            min_inlier_fraction: self.config.min_inlier_fraction,
        };
        let prior = to_reference * predicted;
        let refined = match estimate_motion(&self.calib, &correspondences, &prior, &motion) {
            Ok(r) => r,
            Err(failure) => {
                self.tracked = tracked;
                return Ok(self.lost_frame(
                    frame,
                    LostReason::TrackingFailed {
                        matches: failure.correspondences,
                        inliers: failure.inliers,
                    },
                ));
            }
        };
        let pose = reference.pose * refined.pose;
        let step = track.pose.inverse() * pose;
        let speed = step.translation.vector.norm() / dt.max(1e-3);
        if speed > self.config.max_speed_mps {
            self.tracked = tracked;
            return Ok(self.lost_frame(frame, LostReason::Implausible { speed_mps: speed }));
        }
        let (rotation_deg, translation_m) = prediction_error(&predicted, &pose);
        tracing::trace!(frame, rotation_deg, translation_m, "prediction error");
        let growth = (dt / 0.1).max(1.0).powi(2);
        if track.velocity_known
            && (rotation_deg > self.config.max_prediction_error_deg * growth
                || translation_m > self.config.max_prediction_error_m * growth)
        {
            self.tracked = tracked;
            return Ok(self.lost_frame(
                frame,
                LostReason::Unpredicted {
                    rotation_deg,
                    translation_m,
                },
            ));
        }

        // The inliers stay tracked, at their new pixels; the rest are no longer followed.
        let mut keep = vec![false; self.map.landmarks.len()];
        let mut parallax = Vec::with_capacity(refined.inliers.len());
        for &i in &refined.inliers {
            let t = tracked[i];
            let l = &mut self.map.landmarks[t.landmark];
            l.pixel = t.pixel;
            l.disparity = t.disparity;
            if let Some(k) = l.keyframe_pixel {
                parallax.push(((k[0] - t.pixel[0]).powi(2) + (k[1] - t.pixel[1]).powi(2)).sqrt());
            }
            keep[t.landmark] = true;
        }
        for (l, keep) in self.map.landmarks.iter_mut().zip(keep) {
            l.tracked &= keep;
        }
        self.tracked = tracked;

        // 4. Keyframe: the reference's landmarks are running out, or the view has changed
        // enough (distance, rotation, parallax) that fresh ones track better.
        let inliers = refined.inliers.len();
        let tracked_fraction = inliers as f64 / reference.landmarks.max(1) as f64;
        let median_parallax = if parallax.is_empty() {
            0.0
        } else {
            let mid = parallax.len() / 2;
            *parallax.select_nth_unstable_by(mid, f32::total_cmp).1 as f64
        };
        let need_keyframe = tracked_fraction < self.config.keyframe_min_tracked_fraction
            || refined.pose.translation.vector.norm() > self.config.keyframe_max_distance_m
            || refined.pose.rotation.angle().to_degrees() > self.config.keyframe_max_rotation_deg
            || median_parallax > self.config.keyframe_max_parallax_px;

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
        self.stages.estimate_ms += lap.lap();
        let mut next_reference = reference;
        let mut pose = pose;
        if need_keyframe {
            if let Some((mut new_reference, keyframe, adjusted)) =
                self.make_keyframe(frame, stamp_ns, pose, (left, right), true)?
            {
                // The adjusted window's edge when it has one, else the frame's own
                // refinement against the reference keyframe; then the blur of both.
                let (relative, information) = adjusted
                    .and_then(|e| self.adjusted_information(&e).map(|i| (e.relative, i)))
                    .unwrap_or((refined.pose, refined.information));
                new_reference.angular_velocity = if dt > 0.0 {
                    step.log().fixed_rows::<3>(0) / dt
                } else {
                    reference.angular_velocity
                };
                let information = with_blur_errors(
                    &information,
                    &relative,
                    &reference.angular_velocity,
                    &new_reference.angular_velocity,
                    self.config.blur_exposure_s,
                )
                .unwrap_or(information);
                result.edge = Some(OdometryEdge {
                    from: reference.id,
                    to: keyframe.id,
                    relative,
                    information,
                });
                pose = keyframe.pose;
                result.pose = Some(pose);
                result.keyframe = Some(keyframe);
                next_reference = new_reference;
            }
        }
        let step = track.pose.inverse() * pose;
        let velocity = if dt > 0.0 {
            step.log() / dt
        } else {
            track.velocity
        };
        self.track = Some(Track {
            reference: next_reference,
            pose,
            stamp_ns,
            velocity,
            velocity_known: true,
        });
        Ok(result)
    }
}

/// The features of a frame that have a disparity, strongest first (the order keyframes
/// keep, so the first N of a keyframe are its best).
fn stereo_points(features: &FrameFeatures) -> Vec<(&FrameFeature, f64)> {
    let mut stereo: Vec<_> = features
        .features
        .iter()
        .map(|f| (f, f.disparity as f64))
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
