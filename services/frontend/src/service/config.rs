//! `[frontend]` of robot.toml: the odometry's settings (any field of [`VoConfig`], at the
//! section's top level), where the stereo calibration comes from, and where the service
//! keeps its status and resume files.

use std::path::{Path, PathBuf};

use doorslam_dataset::{Dataset, StereoCalibration};
use doorslam_ipc::{MAX_FRAME_HEIGHT, MAX_FRAME_WIDTH, MAX_KEYFRAME_FEATURES};
use serde::Deserialize;

use super::{FrontendConfig, ServiceError};
use crate::config::VoConfig;

/// `[frontend]` of `robot.toml`. Unknown keys are errors (they are neither a service key
/// nor a [`VoConfig`] field).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(try_from = "RawSection")]
pub struct FrontendSection {
    /// A KITTI-style `calib.txt` (rectified `P0`/`P1`), or a KITTI-layout dataset folder
    /// (its `calib.txt`, and the image size of its first frame). Absent: the replayed
    /// dataset's (`[camera.replay] path`).
    pub calibration: Option<PathBuf>,
    /// `[width, height]` the calibration file is for; absent: the camera's `[camera]`
    /// width and height. Not used with a dataset folder (its images say).
    pub image_size: Option<[u32; 2]>,
    /// Status (`frontend.json`) and resume state (`frontend.resume`) go to
    /// `<run_dir>/<robot id>/`.
    pub run_dir: PathBuf,
    /// The odometry's settings.
    pub vo: VoConfig,
}

/// The section as written: service keys, everything else a [`VoConfig`] field.
#[derive(Deserialize)]
struct RawSection {
    #[serde(default)]
    calibration: Option<PathBuf>,
    #[serde(default)]
    image_size: Option<[u32; 2]>,
    #[serde(default = "default_run_dir")]
    run_dir: PathBuf,
    #[serde(flatten)]
    vo: toml::Table,
}

impl TryFrom<RawSection> for FrontendSection {
    type Error = String;
    fn try_from(raw: RawSection) -> Result<Self, String> {
        // VoConfig denies unknown fields, so a typo in any key of the section is caught
        // here (serde's flatten alone would drop it silently).
        let vo: VoConfig = raw
            .vo
            .try_into()
            .map_err(|e: toml::de::Error| format!("frontend: {}", e.message()))?;
        Ok(Self {
            calibration: raw.calibration,
            image_size: raw.image_size,
            run_dir: raw.run_dir,
            vo,
        })
    }
}

fn default_run_dir() -> PathBuf {
    PathBuf::from("/var/lib/doorslam/run")
}

impl Default for FrontendSection {
    fn default() -> Self {
        Self {
            calibration: None,
            image_size: None,
            run_dir: default_run_dir(),
            vo: VoConfig::default(),
        }
    }
}

impl FrontendSection {
    /// Checks the odometry's settings and what the keyframe channel can carry.
    pub fn validate(&self) -> Result<(), ServiceError> {
        self.vo.validate()?;
        if self.vo.max_features > MAX_KEYFRAME_FEATURES {
            return Err(ServiceError::Config(format!(
                "frontend.max_features = {}: a keyframe carries at most {MAX_KEYFRAME_FEATURES} features",
                self.vo.max_features
            )));
        }
        if let Some([w, h]) = self.image_size {
            check_size(w, h).map_err(|why| {
                ServiceError::Config(format!("frontend.image_size = [{w}, {h}]: {why}"))
            })?;
        }
        Ok(())
    }

    /// The settings of the front-end of robot `robot` (index `robot_index`): the
    /// calibration read (see [`Self::calibration_source`] for `replay` and `camera_size`).
    pub fn for_robot(
        &self,
        robot: &str,
        robot_index: u32,
        replay: Option<&Path>,
        camera_size: [u32; 2],
    ) -> Result<FrontendConfig, ServiceError> {
        self.validate()?;
        let source = self.calibration_source(replay, camera_size)?;
        Ok(FrontendConfig {
            robot: robot.to_string(),
            robot_index,
            calibration: Calibration::load(&source)?,
            calibration_origin: source.to_string(),
            dir: self.run_dir.join(robot),
            vo: self.vo.clone(),
        })
    }

    /// Where the calibration comes from: `calibration` if set, else the replayed dataset
    /// `replay` (`[camera.replay] path`); a file's image size is `image_size`, else
    /// `camera_size` (`[camera] width, height`).
    pub fn calibration_source(
        &self,
        replay: Option<&Path>,
        camera_size: [u32; 2],
    ) -> Result<CalibrationSource, ServiceError> {
        match (&self.calibration, replay) {
            (Some(path), _) if path.is_dir() => Ok(CalibrationSource::Dataset(path.clone())),
            (Some(path), _) => {
                let [width, height] = self.image_size.unwrap_or(camera_size);
                Ok(CalibrationSource::File {
                    path: path.clone(),
                    width,
                    height,
                })
            }
            (None, Some(dir)) => Ok(CalibrationSource::Dataset(dir.to_path_buf())),
            (None, None) => Err(ServiceError::Config(
                "frontend.calibration is not set and the camera is not a replay: set \
                 calibration = PATH (a calib.txt with the rectified P0 and P1)"
                    .into(),
            )),
        }
    }
}

/// Where the stereo calibration is read from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CalibrationSource {
    /// A KITTI-layout dataset folder: `calib.txt`, and the size of its first frame.
    Dataset(PathBuf),
    /// A KITTI-style `calib.txt` for images of `width × height`.
    File {
        path: PathBuf,
        width: u32,
        height: u32,
    },
}

impl std::fmt::Display for CalibrationSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Dataset(dir) => write!(f, "{}", dir.join("calib.txt").display()),
            Self::File {
                path,
                width,
                height,
            } => write!(f, "{} ({width}x{height})", path.display()),
        }
    }
}

/// A rectified stereo calibration and the image size it is for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    pub stereo: StereoCalibration,
    pub width: u32,
    pub height: u32,
}

fn check_size(width: u32, height: u32) -> Result<(), String> {
    if width == 0 || height == 0 {
        return Err("must be > 0".into());
    }
    if width as usize > MAX_FRAME_WIDTH || height as usize > MAX_FRAME_HEIGHT {
        return Err(format!(
            "exceeds the frame maximum {MAX_FRAME_WIDTH}x{MAX_FRAME_HEIGHT}"
        ));
    }
    Ok(())
}

impl Calibration {
    /// Reads the calibration; errors name the file (and line and field, from its parser).
    pub fn load(source: &CalibrationSource) -> Result<Self, ServiceError> {
        let bad = |path: &Path, why: String| ServiceError::Calibration {
            path: path.to_path_buf(),
            why,
        };
        // The dataset crate's errors name the file (and line and field).
        let file = ServiceError::CalibrationFile;
        let (path, stereo, width, height) = match source {
            CalibrationSource::Dataset(dir) => {
                let dataset = Dataset::open(dir).map_err(file)?;
                // The replay publishes EuRoC pairs rectified (same size): the calibration
                // of the rectified pair; KITTI layouts are rectified on disk.
                let stereo = dataset.stereo().map_err(file)?.calibration;
                let first = dataset.frames.first().ok_or_else(|| {
                    bad(
                        dir,
                        "no frames: the image size is taken from the first".into(),
                    )
                })?;
                let (w, h, _) = doorslam_dataset::read_gray_png(&first.left).map_err(file)?;
                (dir.join("calib.txt"), stereo, w, h)
            }
            CalibrationSource::File {
                path,
                width,
                height,
            } => {
                let stereo = StereoCalibration::from_kitti(path).map_err(file)?;
                (path.clone(), stereo, *width, *height)
            }
        };
        check_size(width, height)
            .map_err(|why| bad(&path, format!("image {width}x{height}: {why}")))?;
        // A principal point outside the image: a calibration for another resolution.
        if !(stereo.cx > 0.0
            && stereo.cx < width as f64
            && stereo.cy > 0.0
            && stereo.cy < height as f64)
        {
            return Err(bad(
                &path,
                format!(
                    "principal point ({}, {}) lies outside the {width}x{height} image: a \
                     calibration for another image size?",
                    stereo.cx, stereo.cy
                ),
            ));
        }
        Ok(Self {
            stereo,
            width,
            height,
        })
    }
}
