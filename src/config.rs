//! `robot.toml`: the configuration of one robot, one section per service.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use doorslam_camera::CameraConfig;
use serde::Deserialize;

/// The whole file. Unknown sections or keys are errors: a typo must not be silently ignored.
#[derive(Debug, Clone, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    #[serde(default)]
    pub robot: RobotSection,
    #[serde(default)]
    pub camera: CameraConfig,
}

/// `[robot]`: identity of this robot in the team.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSection {
    /// Stable robot id: lowercase letters, digits, `_` or `-` (used in service and key names).
    #[serde(default = "default_id")]
    pub id: String,
}

fn default_id() -> String {
    "a".into()
}

impl Default for RobotSection {
    fn default() -> Self {
        Self { id: default_id() }
    }
}

impl RobotConfig {
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

    /// The config at `path`, or the built-in defaults when no file is given.
    pub fn load_or_default(path: Option<&PathBuf>) -> Result<Self> {
        match path {
            Some(p) => Self::load(p),
            None => Ok(Self::default()),
        }
    }

    pub fn validate(&self) -> Result<()> {
        let id = &self.robot.id;
        let ok = !id.is_empty()
            && id.len() <= 32
            && id
                .bytes()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'_' || c == b'-');
        if !ok {
            bail!("robot.id = {id:?}: use 1-32 characters of [a-z0-9_-]");
        }
        self.camera.validate()?;
        Ok(())
    }
}
