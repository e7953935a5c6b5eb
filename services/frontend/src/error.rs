//! Failures of the front-end's image processing.

use doorslam_vision::VisionError;

/// Failures of the odometry and verification: the images (sizes, OpenCV) or the settings.
#[derive(Debug, thiserror::Error)]
pub enum FrontendError {
    #[error(transparent)]
    Vision(#[from] VisionError),
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
}
