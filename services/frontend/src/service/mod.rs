//! The front-end service of one robot (`doorslam service frontend`): stereo frames in over
//! iceoryx2, visual odometry on each, keyframes (features with pixel, 3-D point and ORB
//! descriptor) and odometry edges out.
//!
//! All decisions live in the plain state machine [`FrontendState`]; this loop only moves
//! samples: a frame is read in place from shared memory (the odometry borrows the
//! subscriber's sample), a keyframe is written in place into the loaned sample.
//!
//! Lost and segments: every loss is logged with its reason (`visual odometry lost`) and
//! counted; the next good frame starts a new segment whose first keyframe is joined to the
//! last keyframe of the previous segment by the odometry's weak prior (a [`crate::SegmentLink`]),
//! published as an ordinary odometry edge, so the back-end keeps one connected graph.
//! The same holds across restarts: of the camera (sequence numbers go back: a new odometry,
//! linked to the last keyframe) and of this process (`frontend.resume`: ids continue, the
//! first keyframe is linked to the last one published). The tracking state and counters
//! are in `<run_dir>/<robot>/frontend.json`, rewritten every second, and in systemd's
//! `STATUS=` line.

pub mod config;
pub mod files;
pub mod state;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use doorslam_geometry::information::upper_from_matrix;
use doorslam_geometry::pose_to_array;
use doorslam_ipc::{create_node, KeyframeSource, Lifecycle, Receiver, Sender, StereoFrame, Topic};

pub use config::{Calibration, CalibrationSource, FrontendSection};
pub use files::{Files, Status};
pub use state::{Counters, FrontendState, Refusal, Restart, Resume, Snapshot, Step};

use crate::error::FrontendError;
use crate::keyframe::{Keyframe, OdometryEdge};
use crate::run::thread_cpu_s;

/// Failures of the front-end service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
    #[error(transparent)]
    Frontend(#[from] FrontendError),
    #[error("frontend config: {0}")]
    Config(String),
    #[error(transparent)]
    VoConfig(#[from] crate::config::ConfigError),
    #[error("frontend calibration {path}: {why}")]
    Calibration { path: PathBuf, why: String },
    #[error("frontend calibration: {0}")]
    CalibrationFile(#[source] doorslam_dataset::DatasetError),
    #[error("{path}: {source}")]
    File {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {why} (the front-end's resume state; delete it together with the back-end's journal to start the robot afresh)")]
    Resume { path: PathBuf, why: String },
}

/// Settings of one front-end process.
#[derive(Debug, Clone, PartialEq)]
pub struct FrontendConfig {
    /// Robot id (service names) and index (in every sample).
    pub robot: String,
    pub robot_index: u32,
    pub calibration: Calibration,
    /// Where the calibration came from (for logs and the status file).
    pub calibration_origin: String,
    /// `<run_dir>/<robot>`: `frontend.json` and `frontend.resume`.
    pub dir: PathBuf,
    pub vo: crate::config::VoConfig,
}

/// Writes a keyframe in place into a loaned (zeroed) sample.
pub fn fill_keyframe(out: &mut doorslam_ipc::Keyframe, robot_index: u32, kf: &Keyframe) {
    out.robot = robot_index;
    out.source = KeyframeSource::VisualOdometry as u32;
    out.id = kf.id;
    out.frame_seq = kf.frame;
    out.stamp_ns = kf.stamp_ns;
    out.pose = pose_to_array(&kf.pose);
    // The configuration keeps max_features within the sample's capacity; the bound is
    // applied anyway so a larger set could never write past it.
    let n = kf.features.len().min(out.features.len());
    out.n_features = n as u32;
    for (slot, f) in out.features.iter_mut().zip(&kf.features[..n]) {
        slot.uv = f.pixel;
        slot.point = f.point;
        slot.descriptor = f.descriptor;
    }
}

/// The odometry edge as the back-end receives it.
pub fn ipc_edge(robot_index: u32, stamp_ns: u64, e: &OdometryEdge) -> doorslam_ipc::OdometryEdge {
    doorslam_ipc::OdometryEdge {
        robot: robot_index,
        reserved: 0,
        from: e.from,
        to: e.to,
        stamp_ns,
        relative: pose_to_array(&e.relative),
        information: upper_from_matrix(&e.information),
    }
}

/// The channels of one front-end.
struct Channels {
    frames: Receiver<StereoFrame>,
    keyframes: Sender<doorslam_ipc::Keyframe>,
    odometry: Sender<doorslam_ipc::OdometryEdge>,
}

impl Channels {
    fn undelivered(&self) -> u64 {
        self.keyframes.undelivered() + self.odometry.undelivered()
    }

    /// Hands the history to consumers that (re)connected since the last send.
    fn catch_up(&self) -> Result<(), ServiceError> {
        self.keyframes.catch_up_receivers()?;
        self.odometry.catch_up_receivers()?;
        Ok(())
    }
}

/// Logs what a frame did (losses are logged by the odometry itself, with their reason).
fn log_step(step: &Step) {
    if let Some(Restart::CameraRestarted { seq, last_seq }) = step.restart {
        tracing::warn!(
            seq,
            last_seq,
            "frontend: frame numbers went back (the camera restarted): new odometry, linked to the last keyframe"
        );
    }
    if step.dropped > 0 {
        tracing::debug!(
            seq = step.seq,
            dropped = step.dropped,
            "frontend: frames dropped upstream"
        );
    }
    if step.new_segment && step.links > 0 {
        if let Some(kf) = &step.keyframe {
            tracing::info!(
                keyframe = kf.id,
                segment = kf.segment,
                links = step.links,
                "frontend: new segment linked to the previous one by a weak prior"
            );
        }
    }
}

fn power_of_ten(mut n: u64) -> bool {
    while n >= 10 && n.is_multiple_of(10) {
        n /= 10;
    }
    n == 1
}

/// Processes one frame sample: odometry, then its keyframe and edges published.
fn on_sample(
    state: &mut FrontendState,
    channels: &Channels,
    config: &FrontendConfig,
    writer: &mut Writer,
    frame: &StereoFrame,
) -> Result<(), ServiceError> {
    let header = *frame.header();
    let images = frame
        .left_image()
        .and_then(|l| Ok((l, frame.right_image()?)));
    let step = match images {
        Ok((left, right)) => state.on_frame(&header, left, right),
        Err(source) => Err(Refusal::Frame {
            seq: header.seq,
            source,
        }),
    };
    let step = match step {
        Ok(step) => step,
        Err(refusal) => {
            // Counted by the state (frontend.json). Logged the 1st, 10th, 100th... time:
            // a misconfigured camera shows at once without flooding the journal.
            let n = state.counters().refused;
            if power_of_ten(n) {
                tracing::error!(refused_so_far = n, "frontend: refused {refusal}");
            }
            return Ok(());
        }
    };
    log_step(&step);
    // Edges first: they wait in the back-end for their keyframe, which then joins the
    // graph with its edge. The other order lets the back-end optimize (it does on a new
    // keyframe) a graph whose newest keyframe is not connected yet.
    for e in &step.edges {
        channels
            .odometry
            .send_copy(&ipc_edge(config.robot_index, header.stamp_ns, e))?;
    }
    if let Some(kf) = &step.keyframe {
        channels.keyframes.send_with(|slot| {
            fill_keyframe(
                doorslam_ipc::Keyframe::zeroed_in(slot),
                config.robot_index,
                kf,
            );
            Ok::<(), std::convert::Infallible>(())
        })?;
    }
    if step.keyframe.is_some() {
        if let Some(resume) = state.resume() {
            writer.outcome(writer.files.write_resume(&resume));
        }
    }
    Ok(())
}

/// Writes the status and resume files. A file that cannot be written once the service
/// runs (a full disk) is logged, counted and survived: the odometry matters more than its
/// status; the first status write, at start, fails the service instead (a run_dir that
/// cannot be written is a configuration error, better found on the bench).
struct Writer {
    files: Files,
    start: Instant,
    failures: u64,
}

impl Writer {
    fn outcome(&mut self, result: Result<(), ServiceError>) {
        if let Err(e) = result {
            self.failures += 1;
            if power_of_ten(self.failures) {
                tracing::error!(failures = self.failures, "frontend: {e}");
            }
        }
    }

    fn status(
        &self,
        state: &FrontendState,
        channels: &Channels,
        config: &FrontendConfig,
    ) -> Result<Snapshot, ServiceError> {
        let snapshot = state.snapshot();
        self.files.write_status(&Status {
            robot: &config.robot,
            time_s: self.start.elapsed().as_secs_f64(),
            calibration: config.calibration_origin.clone(),
            undelivered: channels.undelivered(),
            snapshot: snapshot.clone(),
        })?;
        doorslam_ipc::sd_notify(&format!(
            "STATUS={}: {} frames, {} keyframes, lost {} times, {} segments",
            snapshot.state, snapshot.frames, snapshot.keyframes, snapshot.lost, snapshot.segments
        ));
        Ok(snapshot)
    }
}

/// Runs until SIGTERM/SIGINT; returns the final counters.
pub fn run(config: &FrontendConfig) -> Result<Snapshot, ServiceError> {
    let files = Files::in_dir(&config.dir);
    let resume = files.read_resume()?;
    let resume_path = files.resume.clone();
    if let Some(r) = &resume {
        tracing::info!(
            last_keyframe = r.keyframe,
            file = %resume_path.display(),
            "frontend: resuming after the last keyframe a previous process published"
        );
    }
    let mut state = FrontendState::new(
        config.calibration,
        config.vo.clone(),
        config.robot_index,
        resume,
    )?;
    let (node, cleaned) = create_node("doorslam-frontend")?;
    if cleaned > 0 {
        tracing::warn!(cleaned, "frontend: removed shared memory of dead processes");
    }
    let channels = Channels {
        frames: Receiver::new(&node, &config.robot, Topic::Frames)?,
        keyframes: Sender::new(&node, &config.robot, Topic::Keyframes)?,
        odometry: Sender::new(&node, &config.robot, Topic::Odometry)?,
    };
    // The edge into the last keyframe, again: the previous process may have died with it
    // published and not yet taken by the back-end (see `Resume::edge`). Senders keep their
    // history for consumers that connect later, so the back-end gets it when it is up.
    if let Some((stamp_ns, edge)) = resume.and_then(|r| Some((r.stamp_ns, r.edge?))) {
        channels
            .odometry
            .send_copy(&ipc_edge(config.robot_index, stamp_ns, &edge))?;
        tracing::info!(
            from = edge.from,
            to = edge.to,
            "frontend: published again the odometry edge into the last keyframe"
        );
    }
    let mut writer = Writer {
        files,
        start: Instant::now(),
        failures: 0,
    };
    writer.status(&state, &channels, config)?;
    let mut lifecycle = Lifecycle::new();
    lifecycle.ready("waiting for frames");
    let c = &config.calibration;
    tracing::info!(
        robot = %config.robot,
        calibration = %config.calibration_origin,
        width = c.width,
        height = c.height,
        threads = config.vo.threads,
        "frontend: ready (subscribed to frames)"
    );
    let mut last_status = Instant::now();
    while lifecycle.keep_going(&node) {
        let c0 = thread_cpu_s();
        match channels.frames.recv_timeout(Duration::from_millis(100))? {
            Some(sample) => {
                on_sample(&mut state, &channels, config, &mut writer, sample.payload())?;
                drop(sample);
                state.record_iteration_cpu((thread_cpu_s() - c0) * 1e3);
            }
            // Idle: a consumer restarted since the last keyframe gets what it missed now.
            None => channels.catch_up()?,
        }
        if last_status.elapsed() >= Duration::from_secs(1) {
            let written = writer.status(&state, &channels, config).map(|_| ());
            writer.outcome(written);
            last_status = Instant::now();
        }
    }
    lifecycle.stopping();
    // Frames already queued were sent before the stop (the camera stops first): process
    // them, so every keyframe they make reaches the back-end, which stops after us.
    while let Some(sample) = channels.frames.try_recv()? {
        on_sample(&mut state, &channels, config, &mut writer, sample.payload())?;
    }
    // A consumer restarted since our last send has not been handed what it missed yet.
    channels.catch_up()?;
    let snapshot = state.snapshot();
    let written = writer.status(&state, &channels, config).map(|_| ());
    writer.outcome(written);
    let undelivered = channels.undelivered();
    if undelivered > 0 {
        tracing::warn!(
            undelivered,
            "frontend: samples reached fewer consumers than were connected"
        );
    }
    tracing::info!(
        frames = snapshot.frames,
        keyframes = snapshot.keyframes,
        lost = snapshot.lost,
        segments = snapshot.segments,
        links = snapshot.links,
        dropped = snapshot.dropped_frames,
        refused = snapshot.refused_frames,
        cpu_ms_per_frame_median = snapshot.cpu_ms_per_frame_median,
        iteration_cpu_ms_per_frame_median = snapshot.iteration_cpu_ms_per_frame_median,
        undelivered,
        "frontend: stopped"
    );
    Ok(snapshot)
}
