//! The one error type of the simulation crate.

use std::path::PathBuf;

/// Everything that can go wrong while building cameras, rendering or writing images.
#[derive(Debug, thiserror::Error)]
pub enum HilError {
    /// A camera parameter is out of its valid range; names the field.
    #[error("invalid camera: {field} = {value} ({reason})")]
    InvalidCamera {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },
    /// A realistic-camera setting is out of its valid range; names the field.
    #[error("invalid camera model: {field} = {value} ({reason})")]
    InvalidSensor {
        field: &'static str,
        value: f64,
        reason: String,
    },
    /// Two images that must share a size do not.
    #[error("image size mismatch: {left_width}x{left_height} vs {right_width}x{right_height}")]
    SizeMismatch {
        left_width: u32,
        left_height: u32,
        right_width: u32,
        right_height: u32,
    },
    /// A building refers to a style id that [`crate::World::add_style`] never returned.
    #[error("unknown building style {0}")]
    UnknownStyle(u32),
    /// A building box that is empty, inverted or not finite.
    #[error("invalid building bounds: min {min:?}, max {max:?}")]
    InvalidBounds { min: [f64; 3], max: [f64; 3] },
    /// A pixel buffer whose length is not width × height.
    #[error("image buffer of {actual} bytes for a {width}x{height} image")]
    BufferLength {
        width: u32,
        height: u32,
        actual: usize,
    },
    /// A pose whose viewing direction is undefined (eye == target, or looking along `up`).
    #[error("degenerate look-at pose: {0}")]
    DegeneratePose(&'static str),
    /// Creating or writing an image file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The PNG encoder refused the image.
    #[error("cannot encode {path} as PNG: {source}")]
    Png {
        path: PathBuf,
        #[source]
        source: png::EncodingError,
    },
}
