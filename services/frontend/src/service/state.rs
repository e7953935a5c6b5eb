//! The front-end service's logic as a plain state machine fed by frames: checks on each
//! frame, the odometry, keyframe ids and poses that continue across restarts (of this
//! process or of the camera), the segment links that keep the back-end's graph connected,
//! counters and timing. The iceoryx2 loop ([`super::run`]) only moves samples, so all of
//! this is tested without shared memory.

use std::collections::VecDeque;
use std::time::Instant;

use doorslam_geometry::SE3;
use doorslam_ipc::FrameHeader;

use super::config::Calibration;
use crate::config::VoConfig;
use crate::error::FrontendError;
use crate::keyframe::{Keyframe, OdometryEdge};
use crate::run::{quantile, thread_cpu_s};
use crate::vo::{LostReason, StereoVo, TrackState, VoStats};
use doorslam_vision::Gray;

/// Timing statistics cover this many of the latest frames.
pub const TIMING_WINDOW: usize = 1000;

/// The last keyframe published: where the next odometry (after a restart of this process
/// or of the camera) continues, ids and pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Resume {
    pub keyframe: u64,
    pub stamp_ns: u64,
    pub pose: SE3,
    /// The odometry edge into that keyframe as it was published (none for a robot's first
    /// keyframe). A restarted process publishes it again: the edge goes out before its
    /// keyframe on another topic, so a kill of the whole robot can leave the back-end with
    /// the keyframe journalled and not the edge, and that keyframe would hang on the weak
    /// restart prior alone (metres off). The back-end counts a copy it has as a duplicate.
    pub edge: Option<OdometryEdge>,
}

/// A frame the service did not give to the odometry, and why.
#[derive(Debug, thiserror::Error)]
pub enum Refusal {
    #[error(
        "frame {seq}: {width}x{height}, but the calibration is for {want_width}x{want_height}"
    )]
    Size {
        seq: u64,
        width: u32,
        height: u32,
        want_width: u32,
        want_height: u32,
    },
    #[error("frame {seq}: from robot {robot}, this front-end serves robot {want}")]
    Robot { seq: u64, robot: u32, want: u32 },
    #[error("frame {seq}: {source}")]
    Frame {
        seq: u64,
        #[source]
        source: doorslam_ipc::FrameError,
    },
    #[error("frame {seq}: odometry failed: {source}")]
    Odometry {
        seq: u64,
        #[source]
        source: FrontendError,
    },
}

/// Why a new odometry instance starts within this process.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Restart {
    /// Frame sequence numbers or stamps went back: the camera (or replay) restarted.
    CameraRestarted { seq: u64, last_seq: u64 },
}

/// What one frame produced, ready to publish: keyframe ids and poses are the robot's
/// (continuing across restarts), edges include the segment links.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    pub seq: u64,
    pub state: TrackState,
    /// Set when the track was lost at this frame (also on a frame that re-initializes at
    /// once after a gap).
    pub lost: Option<LostReason>,
    /// The frame started a new segment.
    pub new_segment: bool,
    pub restart: Option<Restart>,
    pub keyframe: Option<Keyframe>,
    /// Odometry edges to publish after the keyframe: the edge from the previous keyframe,
    /// or the segment link (a weak prior) joining a new segment to the last one.
    pub edges: Vec<OdometryEdge>,
    /// Of `edges`, how many are segment links.
    pub links: usize,
    /// Sequence numbers skipped since the previous frame (frames are lossy).
    pub dropped: u64,
}

/// Counters of everything the service did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counters {
    /// Frames given to the odometry.
    pub frames: u64,
    /// Frames refused (wrong size or robot, malformed) or on which the odometry failed.
    pub refused: u64,
    /// Frames lost upstream (gaps in sequence numbers).
    pub dropped: u64,
    pub keyframes: u64,
    /// Odometry edges published, segment links included.
    pub edges: u64,
    pub links: u64,
    /// Times the camera restarted under a running front-end.
    pub camera_restarts: u64,
}

/// Per-frame times over the last [`TIMING_WINDOW`] frames (ms).
#[derive(Debug, Clone, Default)]
struct Timings {
    /// Wall time of `StereoVo::process`.
    wall: VecDeque<f64>,
    /// This thread's CPU time in `StereoVo::process` (the cost on one core).
    cpu: VecDeque<f64>,
    /// This thread's CPU time of the whole loop iteration: wake-up, receive, odometry,
    /// publishing (the odometry plus the IPC cost).
    iteration_cpu: VecDeque<f64>,
}

fn push(window: &mut VecDeque<f64>, value: f64) {
    if window.len() == TIMING_WINDOW {
        window.pop_front();
    }
    window.push_back(value);
}

/// Median and 90th percentile of a window (0 when empty).
fn median_p90(window: &VecDeque<f64>) -> (f64, f64) {
    let v: Vec<f64> = window.iter().copied().collect();
    (
        quantile(&v, 0.5).unwrap_or(0.0),
        quantile(&v, 0.9).unwrap_or(0.0),
    )
}

/// A snapshot of the counters and timing (what `frontend.json` shows).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Snapshot {
    /// `tracking`, `lost`, or `waiting` (no frame yet).
    pub state: &'static str,
    pub frames: u64,
    pub keyframes: u64,
    /// Times the track was lost.
    pub lost: u64,
    /// Frames without a pose.
    pub lost_frames: u64,
    pub segments: u32,
    pub edges: u64,
    pub links: u64,
    pub dropped_frames: u64,
    pub refused_frames: u64,
    pub camera_restarts: u64,
    pub last_lost_reason: Option<String>,
    pub first_keyframe: Option<u64>,
    pub last_keyframe: Option<u64>,
    pub ms_per_frame_median: f64,
    pub ms_per_frame_p90: f64,
    pub cpu_ms_per_frame_median: f64,
    pub cpu_ms_per_frame_p90: f64,
    pub iteration_cpu_ms_per_frame_median: f64,
    pub iteration_cpu_ms_per_frame_p90: f64,
    /// Frames the timing statistics cover.
    pub timing_frames: usize,
}

/// One robot's front-end.
pub struct FrontendState {
    calibration: Calibration,
    vo_config: VoConfig,
    robot_index: u32,
    vo: StereoVo,
    /// Counters of odometry instances this process replaced (camera restarts).
    retired: VoStats,
    /// The current odometry's keyframe ids start here, and its world frame is this pose
    /// of the robot's (the last keyframe's pose of the previous instance or process).
    id_base: u64,
    world_from_vo: SE3,
    /// The keyframe the current odometry's first keyframe is linked to by a weak prior.
    link_pending: Option<Resume>,
    last_keyframe: Option<Resume>,
    first_keyframe: Option<u64>,
    last_seq: Option<u64>,
    last_stamp_ns: u64,
    track: Option<TrackState>,
    last_lost_reason: Option<LostReason>,
    counters: Counters,
    timings: Timings,
}

impl FrontendState {
    /// A front-end for frames of `calibration`'s size; `resume` is the last keyframe a
    /// previous process published: the first new keyframe is linked to it, and ids
    /// continue one after the next, skipping one. A process that died between sending a
    /// keyframe (or the edge to it) and recording it in its resume file may have handed the
    /// back-end that id; reusing it would pair this process's keyframe with the dead one's
    /// edge, or be skipped as a duplicate. The back-end logs the skipped id as a gap.
    pub fn new(
        calibration: Calibration,
        vo_config: VoConfig,
        robot_index: u32,
        resume: Option<Resume>,
    ) -> Result<Self, FrontendError> {
        let vo = StereoVo::new(calibration.stereo, vo_config.clone())?;
        Ok(Self {
            calibration,
            vo_config,
            robot_index,
            vo,
            retired: VoStats::default(),
            id_base: resume.map_or(0, |r| r.keyframe + 2),
            world_from_vo: resume.map_or(SE3::identity(), |r| r.pose),
            link_pending: resume,
            last_keyframe: resume,
            first_keyframe: None,
            last_seq: None,
            last_stamp_ns: 0,
            track: None,
            last_lost_reason: None,
            counters: Counters::default(),
            timings: Timings::default(),
        })
    }

    /// The last keyframe published (what a restarted process resumes from).
    pub fn resume(&self) -> Option<Resume> {
        self.last_keyframe
    }

    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// The odometry's counters over this process (all instances).
    pub fn vo_stats(&self) -> VoStats {
        self.retired + self.vo.stats()
    }

    /// Records the CPU time (ms) of a whole loop iteration that processed a frame.
    pub fn record_iteration_cpu(&mut self, ms: f64) {
        push(&mut self.timings.iteration_cpu, ms);
    }

    /// Counters and timing as shown in the status file.
    pub fn snapshot(&self) -> Snapshot {
        let s = self.vo_stats();
        let (wall_median, wall_p90) = median_p90(&self.timings.wall);
        let (cpu_median, cpu_p90) = median_p90(&self.timings.cpu);
        let (it_median, it_p90) = median_p90(&self.timings.iteration_cpu);
        Snapshot {
            state: match self.track {
                None => "waiting",
                Some(TrackState::Lost) => "lost",
                Some(_) => "tracking",
            },
            frames: self.counters.frames,
            keyframes: self.counters.keyframes,
            lost: s.lost,
            lost_frames: s.lost_frames,
            segments: s.segments,
            edges: self.counters.edges,
            links: self.counters.links,
            dropped_frames: self.counters.dropped,
            refused_frames: self.counters.refused,
            camera_restarts: self.counters.camera_restarts,
            last_lost_reason: self.last_lost_reason.map(|r| r.to_string()),
            first_keyframe: self.first_keyframe,
            last_keyframe: self.last_keyframe.map(|r| r.keyframe),
            ms_per_frame_median: wall_median,
            ms_per_frame_p90: wall_p90,
            cpu_ms_per_frame_median: cpu_median,
            cpu_ms_per_frame_p90: cpu_p90,
            iteration_cpu_ms_per_frame_median: it_median,
            iteration_cpu_ms_per_frame_p90: it_p90,
            timing_frames: self.timings.cpu.len(),
        }
    }

    /// Checks a frame and runs the odometry on it. A refused frame changes nothing but the
    /// refusal counter.
    pub fn on_frame(
        &mut self,
        header: &FrameHeader,
        left: &[u8],
        right: &[u8],
    ) -> Result<Step, Refusal> {
        let refusal = self.check(header, left, right);
        if let Err(e) = refusal {
            self.counters.refused += 1;
            return Err(e);
        }
        let seq = header.seq;
        let mut restart = None;
        let mut dropped = 0;
        if let Some(last_seq) = self.last_seq {
            if seq <= last_seq || header.stamp_ns < self.last_stamp_ns {
                restart = Some(Restart::CameraRestarted { seq, last_seq });
                self.restart_odometry()
                    .map_err(|source| self.failed(seq, source))?;
            } else {
                dropped = seq - last_seq - 1;
            }
        }
        self.last_seq = Some(seq);
        self.last_stamp_ns = header.stamp_ns;
        self.counters.dropped += dropped;

        let (w, h) = (header.width as usize, header.height as usize);
        // Sizes were checked against the calibration above, so these cannot fail.
        let left = Gray::new(w, h, left).map_err(|source| self.failed(seq, source.into()))?;
        let right = Gray::new(w, h, right).map_err(|source| self.failed(seq, source.into()))?;
        let (t0, c0) = (Instant::now(), thread_cpu_s());
        let result = self
            .vo
            .process(seq, header.stamp_ns, &left, &right)
            .map_err(|source| self.failed(seq, source))?;
        push(&mut self.timings.cpu, (thread_cpu_s() - c0) * 1e3);
        push(&mut self.timings.wall, t0.elapsed().as_secs_f64() * 1e3);
        self.counters.frames += 1;
        self.track = Some(result.state);
        if let Some(reason) = result.lost_reason {
            self.last_lost_reason = Some(reason);
        }

        let mut step = Step {
            seq,
            state: result.state,
            lost: result.lost_reason,
            new_segment: result.state == TrackState::Initialized,
            restart,
            keyframe: None,
            edges: Vec::new(),
            links: 0,
            dropped,
        };
        if let Some(kf) = result.keyframe {
            let kf = Keyframe {
                id: self.id_base + kf.id,
                pose: self.world_from_vo * kf.pose,
                ..kf
            };
            if let Some(prev) = self.link_pending.take() {
                step.edges.push(self.restart_link(&prev, &kf));
                step.links += 1;
            }
            self.last_keyframe = Some(Resume {
                keyframe: kf.id,
                stamp_ns: kf.stamp_ns,
                pose: kf.pose,
                edge: None,
            });
            self.first_keyframe.get_or_insert(kf.id);
            step.keyframe = Some(kf);
        }
        if let Some(link) = result.link {
            step.edges.push(OdometryEdge {
                from: self.id_base + link.from,
                to: self.id_base + link.to,
                relative: link.relative,
                information: link.information,
            });
            step.links += 1;
        }
        if let Some(e) = result.edge {
            step.edges.push(OdometryEdge {
                from: self.id_base + e.from,
                to: self.id_base + e.to,
                ..e
            });
        }
        // The edge into the new keyframe (its odometry, or the restart link of a segment's
        // first keyframe), kept with it for a restart.
        if let (Some(kf), Some(last)) = (&step.keyframe, self.last_keyframe.as_mut()) {
            last.edge = step.edges.iter().rev().find(|e| e.to == kf.id).copied();
        }
        self.counters.keyframes += step.keyframe.is_some() as u64;
        self.counters.edges += step.edges.len() as u64;
        self.counters.links += step.links as u64;
        Ok(step)
    }

    fn check(&self, header: &FrameHeader, left: &[u8], right: &[u8]) -> Result<(), Refusal> {
        let seq = header.seq;
        if header.robot != self.robot_index {
            return Err(Refusal::Robot {
                seq,
                robot: header.robot,
                want: self.robot_index,
            });
        }
        let c = &self.calibration;
        if (header.width, header.height) != (c.width, c.height) {
            return Err(Refusal::Size {
                seq,
                width: header.width,
                height: header.height,
                want_width: c.width,
                want_height: c.height,
            });
        }
        let n = header
            .pixels()
            .map_err(|source| Refusal::Frame { seq, source })?;
        for (side, image) in [("left", left), ("right", right)] {
            if image.len() != n {
                return Err(Refusal::Frame {
                    seq,
                    source: doorslam_ipc::FrameError::WrongLength {
                        side,
                        got: image.len(),
                        want: n,
                        width: header.width,
                        height: header.height,
                    },
                });
            }
        }
        Ok(())
    }

    fn failed(&mut self, seq: u64, source: FrontendError) -> Refusal {
        self.counters.refused += 1;
        Refusal::Odometry { seq, source }
    }

    /// A new odometry instance continuing the robot's ids and pose after the last keyframe
    /// (the camera restarted: the motion prior and the keyframe mean nothing now).
    fn restart_odometry(&mut self) -> Result<(), FrontendError> {
        let vo = StereoVo::new(self.calibration.stereo, self.vo_config.clone())?;
        let old = std::mem::replace(&mut self.vo, vo).stats();
        self.retired = self.retired + old;
        self.counters.camera_restarts += 1;
        self.id_base = self.last_keyframe.map_or(self.id_base, |r| r.keyframe + 1);
        self.world_from_vo = self.last_keyframe.map_or(self.world_from_vo, |r| r.pose);
        self.link_pending = self.last_keyframe;
        self.last_seq = None;
        Ok(())
    }

    /// The weak prior from the last keyframe before a restart to the first one after: the
    /// new odometry starts at that keyframe's pose, with the covariance of the odometry's
    /// own segment links for the time between them.
    fn restart_link(&self, from: &Resume, to: &Keyframe) -> OdometryEdge {
        let seconds = to.stamp_ns.saturating_sub(from.stamp_ns) as f64 * 1e-9;
        OdometryEdge {
            from: from.keyframe,
            to: to.id,
            relative: from.pose.inverse() * to.pose,
            information: self.vo_config.segment_prior_information(seconds),
        }
    }
}
