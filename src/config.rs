//! `robot.toml`: the configuration of one robot, one section per service.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use doorslam_backend::service::BackendSection;
use doorslam_camera::CameraConfig;
use doorslam_frontend::service::FrontendSection;
use serde::Deserialize;

/// The whole file. Unknown sections or keys are errors: a typo must not be silently ignored.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    #[serde(default)]
    pub robot: RobotSection,
    #[serde(default)]
    pub camera: CameraConfig,
    #[serde(default)]
    pub backend: BackendSection,
    #[serde(default)]
    pub frontend: FrontendSection,
    #[serde(default)]
    pub sim_keyframes: SimKeyframesSection,
    #[serde(default)]
    pub up: UpSection,
    #[serde(default)]
    pub team: doorslam_team::runner::TeamSection,
    #[serde(default)]
    pub place: doorslam_place_recognition::service::PlaceSection,
    #[serde(default)]
    pub rendezvous: doorslam_rendezvous::RendezvousSection,
    #[serde(default)]
    pub record: RecordSection,
    #[serde(default)]
    pub ros2: doorslam_ros2::Ros2Section,
}

/// `[record]`: what `doorslam up` records when it stops.
#[derive(Debug, Clone, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordSection {
    /// Write the robot's state folder (`[backend] state_dir`: `<state_dir>/<robot id>/`)
    /// as ROS 2 messages in MCAP to this file when `up` stops (`doorslam ros2 record`).
    #[serde(default)]
    pub mcap: Option<PathBuf>,
}

/// `[sim_keyframes]`: the simulation stand-in for the front-end (never visual odometry).
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimKeyframesSection {
    /// Make a keyframe of every frame whose sequence number is a multiple of this.
    #[serde(default = "default_every")]
    pub every: u64,
}

fn default_every() -> u64 {
    5
}

impl Default for SimKeyframesSection {
    fn default() -> Self {
        Self {
            every: default_every(),
        }
    }
}

/// `[up]`: which services `doorslam up` starts, in this order, and how often each hands
/// freed memory back.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UpSection {
    #[serde(default = "default_services")]
    pub services: Vec<String>,
    /// Every service process hands the allocator's free memory back to the system this
    /// often (glibc `malloc_trim(0)`; 0: never). Without it freed memory stays resident:
    /// an hour's soak measured the front-end holding 12 MB of heap for 3.9 MB in use.
    #[serde(default = "default_trim_every_s")]
    pub trim_every_s: f64,
}

fn default_trim_every_s() -> f64 {
    10.0
}

fn default_services() -> Vec<String> {
    ["backend", "frontend", "place-recognition", "team", "camera"]
        .map(String::from)
        .to_vec()
}

impl Default for UpSection {
    fn default() -> Self {
        Self {
            services: default_services(),
            trim_every_s: default_trim_every_s(),
        }
    }
}

/// `[robot]`: identity of this robot in the team.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSection {
    /// Stable robot id: lowercase letters, digits, `_` or `-` (used in service and key names).
    #[serde(default = "default_id")]
    pub id: String,
    /// Index in the team (0 = 'a' in multi-robot keys), below 52 ('a'..'z', then 'A'..'Z').
    #[serde(default)]
    pub index: u32,
}

fn default_id() -> String {
    "a".into()
}

impl Default for RobotSection {
    fn default() -> Self {
        Self {
            id: default_id(),
            index: 0,
        }
    }
}

impl RobotConfig {
    /// The services `doorslam up` starts, in order: `[up] services`, and `ros2` last when
    /// `[ros2] enabled` (a reader of the back-end's files, it stops first).
    pub fn up_services(&self) -> Vec<String> {
        let mut out = self.up.services.clone();
        if self.ros2.enabled && !out.iter().any(|s| s == "ros2") {
            out.push("ros2".into());
        }
        out
    }

    /// Reads and validates a config file; errors name the file and the offending key.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read config {}", path.display()))?;
        let config: RobotConfig =
            toml::from_str(&text).with_context(|| format!("invalid config {}", path.display()))?;
        config
            .validate()
            .with_context(|| format!("invalid config {}", path.display()))?;
        Ok(config)
    }

    /// The robot's rectified stereo calibration, as the front-end resolves it
    /// (`[frontend] calibration`, else the replayed dataset's): verification at a
    /// rendezvous must use the camera model the keyframes were made with.
    pub fn calibration(&self) -> Result<doorslam_dataset::StereoCalibration> {
        let camera = &self.camera;
        let replay = match (camera.source, &camera.replay) {
            (doorslam_camera::CameraSource::Replay, Some(r)) => Some(r.path.as_path()),
            _ => None,
        };
        let source = self
            .frontend
            .calibration_source(replay, [camera.width, camera.height])?;
        let c = doorslam_frontend::service::Calibration::load(&source)
            .with_context(|| format!("the stereo calibration ({source})"))?;
        Ok(c.stereo)
    }

    /// The config at `path`, or the built-in defaults when no file is given.
    pub fn load_or_default(path: Option<&PathBuf>) -> Result<Self> {
        match path {
            Some(p) => Self::load(p),
            None => Ok(Self::default()),
        }
    }

    pub fn validate(&self) -> Result<()> {
        // The id travels in every wire message's header: one rule for both (the wire's).
        let id = &self.robot.id;
        if doorslam_ipc::wire::RobotId::new(id).is_err() {
            bail!("robot.id = {id:?}: use 1-32 characters of [a-z0-9_-]");
        }
        if let Err(e) = doorslam_geometry::key::robot_index(self.robot.index) {
            bail!("robot.index = {}: {e}", self.robot.index);
        }
        self.camera.validate()?;
        self.backend.validate()?;
        self.frontend.validate()?;
        self.team.validate()?;
        self.place.validate()?;
        self.rendezvous.validate().map_err(anyhow::Error::msg)?;
        if self.sim_keyframes.every == 0 {
            bail!("sim_keyframes.every must be >= 1");
        }
        self.ros2.validate(id)?;
        let trim = self.up.trim_every_s;
        if !(trim == 0.0 || (1.0..=3600.0).contains(&trim)) {
            bail!("up.trim_every_s = {trim}: 0 (never) or from 1 to 3600 s");
        }
        let ros2_listed = self.up.services.iter().any(|s| s == "ros2");
        if ros2_listed && !self.ros2.enabled {
            bail!("up.services lists ros2 but ros2.enabled = false: set ros2.enabled = true (then `up` starts it without the list)");
        }
        for s in &self.up.services {
            if crate::cli::service_names().iter().all(|n| n != s) {
                bail!(
                    "up.services: unknown service {s:?} (known: {})",
                    crate::cli::service_names().join(", ")
                );
            }
        }
        Ok(())
    }
}
