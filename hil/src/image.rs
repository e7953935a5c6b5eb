//! Row-major image buffers produced by the renderer, and PNG output.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use crate::error::HilError;

/// An 8-bit grayscale image, row-major, `width * height` bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GrayImage {
    width: u32,
    height: u32,
    pixels: Vec<u8>,
}

/// Camera z-depth per pixel (metres), `f32::INFINITY` where the ray meets only sky.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    width: u32,
    height: u32,
    depth: Vec<f32>,
}

fn check_same(a: (u32, u32), b: (u32, u32)) -> Result<(), HilError> {
    if a == b {
        Ok(())
    } else {
        Err(HilError::SizeMismatch {
            left_width: a.0,
            left_height: a.1,
            right_width: b.0,
            right_height: b.1,
        })
    }
}

impl GrayImage {
    /// Wraps a buffer; its length must be `width * height`.
    pub fn from_pixels(width: u32, height: u32, pixels: Vec<u8>) -> Result<Self, HilError> {
        if pixels.len() as u64 != width as u64 * height as u64 {
            return Err(HilError::BufferLength {
                width,
                height,
                actual: pixels.len(),
            });
        }
        Ok(Self {
            width,
            height,
            pixels,
        })
    }

    pub(crate) fn from_parts_unchecked(width: u32, height: u32, pixels: Vec<u8>) -> Self {
        Self {
            width,
            height,
            pixels,
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn pixels(&self) -> &[u8] {
        &self.pixels
    }

    /// Pixel at (col, row); `None` outside the image.
    pub fn get(&self, col: u32, row: u32) -> Option<u8> {
        (col < self.width && row < self.height)
            .then(|| self.pixels[(row * self.width + col) as usize])
    }

    /// Bilinear interpolation at continuous pixel coordinates (pixel centres at integers);
    /// `None` unless all four neighbours exist.
    pub fn sample_bilinear(&self, u: f64, v: f64) -> Option<f64> {
        let (u0, v0) = (u.floor(), v.floor());
        if u0 < 0.0 || v0 < 0.0 || u0 + 1.0 >= self.width as f64 || v0 + 1.0 >= self.height as f64 {
            return None;
        }
        let (c, r) = (u0 as u32, v0 as u32);
        let (a, b) = (u - u0, v - v0);
        let p = |dc: u32, dr: u32| self.pixels[((r + dr) * self.width + c + dc) as usize] as f64;
        let top = p(0, 0) * (1.0 - a) + p(1, 0) * a;
        let bottom = p(0, 1) * (1.0 - a) + p(1, 1) * a;
        Some(top * (1.0 - b) + bottom * b)
    }

    /// Mean and standard deviation of the intensities.
    pub fn mean_std(&self) -> (f64, f64) {
        let n = self.pixels.len().max(1) as f64;
        let mean = self.pixels.iter().map(|&p| p as f64).sum::<f64>() / n;
        let var = self
            .pixels
            .iter()
            .map(|&p| (p as f64 - mean).powi(2))
            .sum::<f64>()
            / n;
        (mean, var.sqrt())
    }

    /// Mean absolute intensity difference to an image of the same size.
    pub fn mean_abs_diff(&self, other: &GrayImage) -> Result<f64, HilError> {
        check_same((self.width, self.height), (other.width, other.height))?;
        let sum: u64 = self
            .pixels
            .iter()
            .zip(&other.pixels)
            .map(|(&a, &b)| a.abs_diff(b) as u64)
            .sum();
        Ok(sum as f64 / self.pixels.len().max(1) as f64)
    }

    /// Pearson correlation between horizontally adjacent pixels: near 1 for smooth
    /// images, near 0 for white noise. `None` for a flat image.
    pub fn neighbour_correlation(&self) -> Option<f64> {
        let w = self.width as usize;
        let pairs = || {
            self.pixels
                .chunks_exact(w.max(1))
                .flat_map(|row| row.windows(2).map(|p| (p[0] as f64, p[1] as f64)))
        };
        let n = pairs().count() as f64;
        let (ma, mb) = pairs().fold((0.0, 0.0), |(a, b), (x, y)| (a + x / n, b + y / n));
        let (mut cov, mut va, mut vb) = (0.0, 0.0, 0.0);
        for (x, y) in pairs() {
            cov += (x - ma) * (y - mb);
            va += (x - ma) * (x - ma);
            vb += (y - mb) * (y - mb);
        }
        (va > 0.0 && vb > 0.0).then(|| cov / (va * vb).sqrt())
    }

    /// `left` and `right` next to each other with a `gap`-pixel black separator.
    pub fn side_by_side(
        left: &GrayImage,
        right: &GrayImage,
        gap: u32,
    ) -> Result<GrayImage, HilError> {
        check_same((left.width, left.height), (right.width, right.height))?;
        let width = 2 * left.width + gap;
        let mut pixels = vec![0u8; (width * left.height) as usize];
        for (row, out) in pixels.chunks_exact_mut(width as usize).enumerate() {
            let w = left.width as usize;
            let src = row * w..(row + 1) * w;
            out[..w].copy_from_slice(&left.pixels[src.clone()]);
            out[w + gap as usize..].copy_from_slice(&right.pixels[src]);
        }
        Ok(GrayImage {
            width,
            height: left.height,
            pixels,
        })
    }

    /// Half-size image, each pixel the mean of a 2×2 block (odd last row/column dropped).
    pub fn downscale2(&self) -> GrayImage {
        let (w, h) = (self.width / 2, self.height / 2);
        let mut pixels = Vec::with_capacity((w * h) as usize);
        for r in 0..h {
            for c in 0..w {
                let p = |dc: u32, dr: u32| {
                    self.pixels[((2 * r + dr) * self.width + 2 * c + dc) as usize] as u32
                };
                pixels.push(((p(0, 0) + p(1, 0) + p(0, 1) + p(1, 1) + 2) / 4) as u8);
            }
        }
        GrayImage {
            width: w,
            height: h,
            pixels,
        }
    }

    /// Writes an 8-bit grayscale PNG.
    pub fn write_png(&self, path: &Path) -> Result<(), HilError> {
        let io = |source| HilError::Io {
            path: path.to_path_buf(),
            source,
        };
        let png_err = |source| HilError::Png {
            path: path.to_path_buf(),
            source,
        };
        let file = File::create(path).map_err(io)?;
        let mut encoder = png::Encoder::new(BufWriter::new(file), self.width, self.height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Best);
        let mut writer = encoder.write_header().map_err(png_err)?;
        writer.write_image_data(&self.pixels).map_err(png_err)?;
        writer.finish().map_err(png_err)
    }
}

impl DepthMap {
    pub(crate) fn from_parts_unchecked(width: u32, height: u32, depth: Vec<f32>) -> Self {
        Self {
            width,
            height,
            depth,
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn values(&self) -> &[f32] {
        &self.depth
    }

    /// Depth at (col, row); `None` outside the image.
    pub fn get(&self, col: u32, row: u32) -> Option<f32> {
        (col < self.width && row < self.height)
            .then(|| self.depth[(row * self.width + col) as usize])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_interpolates_and_refuses_the_border() {
        let img = GrayImage::from_pixels(2, 2, vec![0, 100, 100, 200]).unwrap();
        assert_eq!(img.sample_bilinear(0.5, 0.5), Some(100.0));
        assert_eq!(img.sample_bilinear(0.0, 0.0), Some(0.0));
        assert_eq!(img.sample_bilinear(1.0, 0.0), None);
    }

    #[test]
    fn statistics_tell_flat_from_structured() {
        let flat = GrayImage::from_pixels(4, 1, vec![7; 4]).unwrap();
        assert_eq!(flat.neighbour_correlation(), None);
        let ramp = GrayImage::from_pixels(4, 1, vec![0, 10, 20, 30]).unwrap();
        assert!((ramp.neighbour_correlation().unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(flat.mean_abs_diff(&ramp).unwrap(), 11.5);
        assert!(flat.mean_abs_diff(&ramp.downscale2()).is_err());
    }

    #[test]
    fn side_by_side_and_downscale_keep_pixels() {
        let a = GrayImage::from_pixels(2, 2, vec![10, 20, 30, 40]).unwrap();
        let b = GrayImage::from_pixels(2, 2, vec![50, 60, 70, 80]).unwrap();
        let s = GrayImage::side_by_side(&a, &b, 1).unwrap();
        assert_eq!(s.pixels(), &[10, 20, 0, 50, 60, 30, 40, 0, 70, 80]);
        assert_eq!(a.downscale2().pixels(), &[25]);
        assert!(GrayImage::from_pixels(3, 2, vec![0; 5]).is_err());
    }
}
