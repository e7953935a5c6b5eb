//! # doorslam-camera
//!
//! The camera service: stereo capture with v4l2 into the robot's iceoryx2 frame service.
//! On a machine without a camera it refuses to start with an error that points at replay
//! (`doorslam replay`, from `hil/`), which feeds the same frame service from a dataset.

use std::path::{Path, PathBuf};

use serde::Deserialize;

pub mod capture;
pub mod replay;

pub use replay::{ReplayReport, ReplayStatus};

/// Failures of the camera service.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("no camera found at {path} (v4l2 devices present: {found}); use replay instead: `doorslam replay DATASET --config robot.toml`")]
    NoCamera { path: PathBuf, found: String },
    #[error("camera config: {0}")]
    Config(String),
    #[error("camera {path}: {reason}")]
    Device { path: PathBuf, reason: String },
    #[error("camera frame: {0}")]
    Frame(#[from] doorslam_ipc::FrameError),

    #[error("replay: {0}")]
    Replay(#[from] doorslam_dataset::DatasetError),
    #[error(transparent)]
    Ipc(#[from] doorslam_ipc::IpcError),
}

/// Where frames come from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraSource {
    /// A v4l2 stereo camera.
    #[default]
    V4l,
    /// A dataset folder played into the pipeline ([`ReplayConfig`]).
    Replay,
}

/// `[camera.replay]`: dataset replay (hardware-in-the-loop without the camera).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayConfig {
    /// KITTI (`image_0/`, `image_1/`, `times.txt`) or EuRoC (`[mav0/]cam0/data`, `cam1/data`) folder.
    pub path: PathBuf,
    /// Playback speed: 1 = real time, 2 = twice as fast, 0 = as fast as possible.
    #[serde(default = "default_rate")]
    pub rate: f64,
    /// Ground-truth poses (KITTI format), if not `poses.txt` inside the folder.
    #[serde(default)]
    pub truth: Option<PathBuf>,
    /// `[k, n]`: play only part k of n equal consecutive parts (one sequence, n robots).
    #[serde(default)]
    pub split: Option<[usize; 2]>,
    /// Wait up to this long for a first subscriber before playing (frames are lossy).
    #[serde(default = "default_wait")]
    pub wait_for_subscribers_s: f64,
    /// Stepped playback: one frame per line read on standard input (end of input stops).
    #[serde(default)]
    pub step: bool,
    /// Wall-clock start of the recording (Unix milliseconds): frame k is due at this time
    /// plus its dataset time divided by `rate`, whenever the replay starts. A replay
    /// (re)started late skips the frames whose time has passed, like a camera that was
    /// off: several robots' replays stay on one clock, and a robot restarted mid-run
    /// resumes where the flight is now. Absent: play from the first frame at start.
    #[serde(default)]
    pub start_unix_ms: Option<u64>,
    /// A JSON file the replay keeps current (every second and at the end): frames
    /// published and skipped, and how late frames went out after their due time — the
    /// camera's share of the real-time check of a run ([`replay::ReplayStatus`]).
    #[serde(default)]
    pub status_file: Option<PathBuf>,
}

fn default_rate() -> f64 {
    1.0
}
fn default_wait() -> f64 {
    10.0
}

/// `[camera]` section of `robot.toml`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// `v4l` (default) or `replay`.
    #[serde(default)]
    pub source: CameraSource,
    /// Settings of `source = "replay"`.
    #[serde(default)]
    pub replay: Option<ReplayConfig>,
    /// Left camera device, or the one side-by-side stereo device.
    #[serde(default = "default_left")]
    pub left: PathBuf,
    /// Right camera device; absent for a side-by-side stereo device.
    #[serde(default)]
    pub right: Option<PathBuf>,
    /// Image width of one eye, pixels.
    #[serde(default = "default_width")]
    pub width: u32,
    /// Image height, pixels.
    #[serde(default = "default_height")]
    pub height: u32,
    /// Exposure in units of 100 µs (`V4L2_CID_EXPOSURE_ABSOLUTE`); driver default if absent.
    #[serde(default)]
    pub exposure_100us: Option<u32>,
    /// Frames per second requested from the driver.
    #[serde(default = "default_fps")]
    pub fps: u32,
}

fn default_left() -> PathBuf {
    PathBuf::from("/dev/video0")
}
fn default_width() -> u32 {
    752
}
fn default_height() -> u32 {
    480
}
fn default_fps() -> u32 {
    20
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            source: CameraSource::V4l,
            replay: None,
            left: default_left(),
            right: None,
            width: default_width(),
            height: default_height(),
            fps: default_fps(),
            exposure_100us: None,
        }
    }
}

impl CameraConfig {
    /// Checks values a driver would reject later with a less clear message.
    pub fn validate(&self) -> Result<(), CameraError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if w == 0
            || h == 0
            || w > doorslam_ipc::MAX_FRAME_WIDTH
            || h > doorslam_ipc::MAX_FRAME_HEIGHT
        {
            return Err(CameraError::Config(format!(
                "camera.width x camera.height = {w}x{h}, must be within 1x1..{}x{}",
                doorslam_ipc::MAX_FRAME_WIDTH,
                doorslam_ipc::MAX_FRAME_HEIGHT
            )));
        }
        if self.fps == 0 || self.fps > 200 {
            return Err(CameraError::Config(format!(
                "camera.fps = {}, must be within 1..200",
                self.fps
            )));
        }
        match (&self.source, &self.replay) {
            (CameraSource::Replay, None) => {
                return Err(CameraError::Config(
                    "camera.source = \"replay\" needs a [camera.replay] section with a path".into(),
                ))
            }
            (_, Some(r))
                if !(r.rate == 0.0 || (MIN_REPLAY_RATE..=MAX_REPLAY_RATE).contains(&r.rate)) =>
            {
                return Err(CameraError::Config(format!(
                    "camera.replay.rate = {}, must be 0 (as fast as possible) or from {MIN_REPLAY_RATE} to {MAX_REPLAY_RATE}",
                    r.rate
                )))
            }
            (_, Some(r))
                if !(0.0..=MAX_WAIT_FOR_SUBSCRIBERS_S).contains(&r.wait_for_subscribers_s) =>
            {
                return Err(CameraError::Config(format!(
                    "camera.replay.wait_for_subscribers_s = {}, must be from 0 to {MAX_WAIT_FOR_SUBSCRIBERS_S} s",
                    r.wait_for_subscribers_s
                )))
            }
            _ => {}
        }
        Ok(())
    }

    /// The devices this config needs, left first.
    pub fn devices(&self) -> Vec<&Path> {
        std::iter::once(self.left.as_path())
            .chain(self.right.as_deref())
            .collect()
    }
}

/// Replay speeds (× real time) a config may ask for; 0 means as fast as possible. Bounded
/// so that every frame's due time is a representable `Duration`.
pub const MIN_REPLAY_RATE: f64 = 1e-3;
pub const MAX_REPLAY_RATE: f64 = 1e3;
/// The longest a replay waits for its first subscriber (an hour).
pub const MAX_WAIT_FOR_SUBSCRIBERS_S: f64 = 3600.0;

/// The v4l2 video devices present on this machine, sorted by path.
pub fn enumerate_devices() -> Vec<PathBuf> {
    let mut paths: Vec<PathBuf> = v4l::context::enum_devices()
        .iter()
        .map(|n| n.path().to_path_buf())
        .collect();
    paths.sort();
    paths
}

/// Checks that every configured device exists and opens as a v4l2 device.
pub fn open_devices(config: &CameraConfig) -> Result<Vec<v4l::Device>, CameraError> {
    config.validate()?;
    let present = enumerate_devices();
    let found = if present.is_empty() {
        "none".to_string()
    } else {
        present
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    };
    config
        .devices()
        .into_iter()
        .map(|path| {
            if !present.iter().any(|p| p == path) {
                return Err(CameraError::NoCamera {
                    path: path.to_path_buf(),
                    found: found.clone(),
                });
            }
            v4l::Device::with_path(path).map_err(|e| CameraError::Device {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })
        })
        .collect()
}

/// Runs the camera service for robot `robot`: replays a dataset, or opens the devices and
/// captures into the frame service.
pub fn run(config: &CameraConfig, robot: &str, robot_index: u32) -> Result<(), CameraError> {
    config.validate()?;
    if let (CameraSource::Replay, Some(replay)) = (config.source, &config.replay) {
        return replay::run(replay, robot, robot_index).map(|_| ());
    }
    capture::run(config, robot, robot_index)
}
