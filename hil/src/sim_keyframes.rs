//! `sim-keyframes`: a stand-in for the front-end until visual odometry exists. It turns
//! every N-th replayed frame that carries ground truth into a keyframe whose pose IS the
//! ground truth, plus the odometry edge from the previous keyframe. Simulation only: it
//! says so in its name and logs, and its keyframes are marked
//! [`KeyframeSource::SimulatedTruth`], never visual odometry.

use std::time::Duration;

use doorslam_geometry::information::upper_from_diagonal;
use doorslam_geometry::{pose_from_array, pose_to_array, PoseError};
use doorslam_ipc::{
    create_node, Feature, Keyframe, KeyframeSource, Lifecycle, OdometryEdge, Receiver, Sender,
    StereoFrame, Topic, FRAME_HAS_TRUTH, MAX_KEYFRAME_FEATURES,
};
use nalgebra::Isometry3;

/// Failures of the sim-keyframes service.
#[derive(Debug, thiserror::Error)]
pub enum SimKeyframesError {
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
    #[error("frame {seq} has no ground-truth pose: sim-keyframes only works on replayed datasets with truth or simulation; on a real camera run the front-end")]
    NoTruth { seq: u64 },
    #[error("frame {seq}: ground-truth pose in the frame header: {source}")]
    BadTruth {
        seq: u64,
        #[source]
        source: PoseError,
    },
    #[error("sim_keyframes.every must be >= 1")]
    Every,
}

/// Settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SimKeyframesConfig {
    pub robot: String,
    pub robot_index: u32,
    /// Make a keyframe of every frame whose sequence number is a multiple of this.
    pub every: u64,
}

/// Counts, logged at exit.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SimKeyframesReport {
    pub frames: u64,
    /// Frames lost upstream (gaps in sequence numbers: frames are lossy by design).
    pub dropped_frames: u64,
    pub keyframes: u64,
    /// Id of the first keyframe this process published (frames published before it
    /// subscribed, or while a loaded machine kept it from reading, are not counted as
    /// dropped: it cannot tell them from frames of an earlier run).
    pub first_keyframe: Option<u64>,
}

/// Runs until SIGTERM/SIGINT.
pub fn run(config: &SimKeyframesConfig) -> Result<SimKeyframesReport, SimKeyframesError> {
    if config.every == 0 {
        return Err(SimKeyframesError::Every);
    }
    tracing::warn!("sim-keyframes: forwarding ground-truth poses of replayed frames as keyframes (simulation only, NOT visual odometry)");
    let (node, _) = create_node("doorslam-sim-keyframes")?;
    let frames = Receiver::<StereoFrame>::new(&node, &config.robot, Topic::Frames)?;
    let keyframes = Sender::<Keyframe>::new(&node, &config.robot, Topic::Keyframes)?;
    let odometry = Sender::<OdometryEdge>::new(&node, &config.robot, Topic::Odometry)?;
    let mut lifecycle = Lifecycle::new();
    lifecycle.ready("sim-keyframes (simulation only)");
    let mut report = SimKeyframesReport::default();
    let mut last_seq: Option<u64> = None;
    let mut previous: Option<(u64, Isometry3<f64>)> = None;
    while lifecycle.keep_going(&node) {
        let Some(sample) = frames.recv_timeout(Duration::from_millis(100))? else {
            // Idle: a consumer restarted since the last keyframe gets what it missed now.
            keyframes.catch_up_receivers()?;
            odometry.catch_up_receivers()?;
            continue;
        };
        let h = *sample.payload().header();
        drop(sample);
        report.frames += 1;
        if let Some(prev) = last_seq {
            report.dropped_frames += h.seq.saturating_sub(prev + 1);
        }
        last_seq = Some(h.seq);
        if h.seq % config.every != 0 {
            continue;
        }
        if h.flags & FRAME_HAS_TRUTH == 0 {
            return Err(SimKeyframesError::NoTruth { seq: h.seq });
        }
        let pose = pose_from_array(&h.truth_pose)
            .map_err(|source| SimKeyframesError::BadTruth { seq: h.seq, source })?;
        // Ids follow the frame sequence, so a restarted sim-keyframes continues the
        // numbering instead of reusing ids the back-end already has.
        let id = h.seq / config.every;
        report.first_keyframe.get_or_insert(id);
        keyframes.send_with(|slot| {
            slot.write(Keyframe {
                robot: config.robot_index,
                source: KeyframeSource::SimulatedTruth as u32,
                id,
                frame_seq: h.seq,
                stamp_ns: h.stamp_ns,
                pose: h.truth_pose,
                n_features: 0,
                reserved: 0,
                features: [Feature::default(); MAX_KEYFRAME_FEATURES],
            });
            Ok::<(), std::convert::Infallible>(())
        })?;
        if let Some((prev_id, prev_pose)) = previous {
            let edge = OdometryEdge {
                robot: config.robot_index,
                reserved: 0,
                from: prev_id,
                to: id,
                stamp_ns: h.stamp_ns,
                relative: pose_to_array(&(prev_pose.inverse() * pose)),
                // σ_R = 0.01 rad, σ_t = 0.1 m: the noise level of the paper's simulation.
                information: upper_from_diagonal([1e4, 1e4, 1e4, 1e2, 1e2, 1e2]),
            };
            odometry.send_copy(&edge)?;
        }
        previous = Some((id, pose));
        report.keyframes += 1;
        tracing::debug!(id, seq = h.seq, "sim-keyframes: keyframe published");
    }
    lifecycle.stopping();
    // A consumer restarted since our last send has not been handed what it missed yet:
    // hand it over now, while this process still holds the history.
    keyframes.catch_up_receivers()?;
    odometry.catch_up_receivers()?;
    let undelivered = keyframes.undelivered() + odometry.undelivered();
    if undelivered > 0 {
        tracing::warn!(
            undelivered,
            "sim-keyframes: samples reached fewer consumers than were connected"
        );
    }
    tracing::info!(
        frames = report.frames,
        dropped = report.dropped_frames,
        keyframes = report.keyframes,
        first_keyframe = report.first_keyframe.unwrap_or(0),
        undelivered,
        "sim-keyframes: stopped"
    );
    Ok(report)
}
