//! Failures of image-level vision code.

/// Failures of the vision crate: unreadable images, wrong sizes, OpenCV errors.
#[derive(Debug, thiserror::Error)]
pub enum VisionError {
    #[error("cannot read image {path}: {reason}")]
    Image { path: String, reason: String },
    #[error("OpenCV {op}: {source}")]
    OpenCv {
        op: &'static str,
        #[source]
        source: opencv::Error,
    },
    #[error("ORB descriptors are {cols} bytes wide, expected 32")]
    DescriptorWidth { cols: i32 },
    #[error("image of {width}x{height} pixels has {bytes} bytes (8-bit grayscale expected, both images of a pair the same size)")]
    ImageSize {
        width: usize,
        height: usize,
        bytes: usize,
    },
}

/// Maps an OpenCV error to [`VisionError::OpenCv`] naming the operation.
pub(crate) fn cv_error(op: &'static str) -> impl FnOnce(opencv::Error) -> VisionError {
    move |source| VisionError::OpenCv { op, source }
}

pub(crate) use cv_error as cv;
