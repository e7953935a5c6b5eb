//! Borrowed grayscale images and image files.

use std::path::Path;

use opencv::core::Mat;
use opencv::prelude::*;

use crate::error::{cv, VisionError};

/// A borrowed 8-bit grayscale image, row-major without padding.
#[derive(Debug, Clone, Copy)]
pub struct Gray<'a> {
    pub width: usize,
    pub height: usize,
    pub pixels: &'a [u8],
}

impl<'a> Gray<'a> {
    /// Checks that `pixels` holds `width × height` bytes.
    pub fn new(width: usize, height: usize, pixels: &'a [u8]) -> Result<Self, VisionError> {
        if width == 0 || height == 0 || pixels.len() != width * height {
            return Err(VisionError::ImageSize {
                width,
                height,
                bytes: pixels.len(),
            });
        }
        Ok(Self {
            width,
            height,
            pixels,
        })
    }

    /// Row `y` (must be below `height`).
    pub fn row(&self, y: usize) -> &'a [u8] {
        &self.pixels[y * self.width..(y + 1) * self.width]
    }

    /// Mean and standard deviation of the intensity on a sparse grid (every 4th pixel of
    /// every 4th row: enough to recognise a blank, saturated or flat frame cheaply).
    pub fn mean_std(&self) -> (f64, f64) {
        let (mut n, mut s, mut s2) = (0.0f64, 0.0f64, 0.0f64);
        for y in (0..self.height).step_by(4) {
            for &p in self.row(y).iter().step_by(4) {
                let p = p as f64;
                n += 1.0;
                s += p;
                s2 += p * p;
            }
        }
        let mean = s / n;
        (mean, (s2 / n - mean * mean).max(0.0).sqrt())
    }

    /// The image as an OpenCV matrix sharing the bytes (no copy).
    pub(crate) fn mat(&self) -> Result<opencv::boxed_ref::BoxedRef<'a, Mat>, VisionError> {
        Mat::new_rows_cols_with_data(self.height as i32, self.width as i32, self.pixels)
            .map_err(cv("Mat over image bytes"))
    }
}

/// Reads an image file as 8-bit grayscale.
pub fn load_gray(path: &Path) -> Result<Mat, VisionError> {
    let name = path.display().to_string();
    if !path.is_file() {
        return Err(VisionError::Image {
            path: name,
            reason: "no such file".into(),
        });
    }
    let img = opencv::imgcodecs::imread(&name, opencv::imgcodecs::IMREAD_GRAYSCALE)
        .map_err(cv("imread"))?;
    if img.empty() {
        return Err(VisionError::Image {
            path: name,
            reason: "not a decodable image".into(),
        });
    }
    Ok(img)
}
