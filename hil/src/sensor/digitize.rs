//! From radiance to 8-bit pixels: exposure, vignetting, shot and read noise, rounding
//! and clipping.
//!
//! Expected value of a pixel, in DN: `μ = L · B · v(x)` (radiance in the ideal camera's
//! units, the frame's brightness, the lens falloff). With `K = 255 / full_well_e` DN per
//! electron at unity gain and gain `g`, the pixel holds `μ / (g K)` electrons, whose
//! Poisson variance is their number, and the read noise σ_r (DN at unity gain) is
//! amplified by the gain too:
//!
//! ```text
//! σ²(μ) = g K μ + g² σ_r²          DN = clip(round(μ + σ(μ) n), 0, 255),  n ~ N(0, 1)
//! ```

use rayon::prelude::*;

use crate::camera::StereoCamera;
use crate::error::HilError;
use crate::image::GrayImage;
use crate::rng::SplitMix64;

use super::{mix, FrameExposure, SensorModel};

/// Bits of each of the six uniform terms of [`standard_normal_approx`].
const TERM_BITS: u32 = 10;
const TERMS: u32 = 6;

/// A standard normal deviate from 64 random bits: the sum of six 10-bit uniforms,
/// centred and scaled (Irwin–Hall). Mean 0 and variance 1 exactly, tails cut at ±4.24 σ,
/// one generator call and no transcendental function per pixel (Box–Muller would cost
/// a logarithm, a square root and a sine per pixel, several times the rest of
/// [`digitize`]). For 1–3 DN of sensor noise rounded to integers the shape beyond 4 σ
/// is invisible.
#[inline]
pub fn standard_normal_approx(bits: u64) -> f32 {
    let levels = (1u64 << TERM_BITS) as f64;
    // Mean and σ of one term uniform on {0, …, 1023}: (L − 1)/2 and √((L² − 1)/12).
    let mean = TERMS as f64 * (levels - 1.0) / 2.0;
    let sigma = (TERMS as f64 * (levels * levels - 1.0) / 12.0).sqrt();
    let mask = (1u64 << TERM_BITS) - 1;
    let sum: u64 = (0..TERMS).map(|i| (bits >> (i * TERM_BITS)) & mask).sum();
    ((sum as f64 - mean) / sigma) as f32
}

/// Lens falloff at pixel (u, v): `1 − a · r² / r_max²`, `r` the distance to the principal
/// point and `r_max` that of the farthest image corner.
pub fn vignetting_factor(camera: &StereoCamera, strength: f64, u: f64, v: f64) -> f64 {
    let corners = [
        (-0.5, -0.5),
        (camera.width() as f64 - 0.5, -0.5),
        (-0.5, camera.height() as f64 - 0.5),
        (camera.width() as f64 - 0.5, camera.height() as f64 - 0.5),
    ];
    let r2 = |(x, y): (f64, f64)| (x - camera.cx()).powi(2) + (y - camera.cy()).powi(2);
    let r_max2 = corners.into_iter().map(r2).fold(0.0, f64::max);
    1.0 - strength * r2((u, v)) / r_max2.max(1e-12)
}

/// The 8-bit image the sensor reads out for `radiance` (row-major, the camera's size)
/// under `exposure`, with noise from `noise_seed` (one independent stream per row, so
/// rows run in parallel and the bytes do not depend on the thread count).
pub fn digitize(
    radiance: &[f32],
    camera: &StereoCamera,
    model: &SensorModel,
    exposure: &FrameExposure,
    noise_seed: u64,
) -> Result<GrayImage, HilError> {
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    if radiance.len() != w * h {
        return Err(HilError::BufferLength {
            width: camera.width(),
            height: camera.height(),
            actual: radiance.len(),
        });
    }
    let g = exposure.gain as f32;
    let shot = if model.full_well_e > 0.0 {
        g * (255.0 / model.full_well_e) as f32
    } else {
        0.0
    };
    let read_var = (g * model.read_noise_dn as f32).powi(2);
    let brightness = exposure.brightness as f32;
    // The falloff is separable in its r² form: 1 − a (dx² + dy²) / r_max².
    let a = model.vignetting;
    let falloff_row: Vec<f32> = (0..h)
        .map(|r| (vignetting_factor(camera, a, camera.cx(), r as f64) - 1.0) as f32)
        .collect();
    let falloff_col: Vec<f32> = (0..w)
        .map(|c| vignetting_factor(camera, a, c as f64, camera.cy()) as f32)
        .collect();
    let mut pixels = vec![0u8; w * h];
    pixels
        .par_chunks_mut(w)
        .zip(radiance.par_chunks(w))
        .enumerate()
        .for_each(|(row, (out, input))| {
            let mut rng = SplitMix64::new(mix(noise_seed, row as u64));
            let row_falloff = falloff_row[row];
            for ((o, &l), &col_falloff) in out.iter_mut().zip(input).zip(&falloff_col) {
                let mean = (l * brightness * (col_falloff + row_falloff)).max(0.0);
                let sigma = (shot * mean + read_var).sqrt();
                let value = mean + sigma * standard_normal_approx(rng.next_u64());
                *o = (value.clamp(0.0, 255.0) + 0.5) as u8;
            }
        });
    Ok(GrayImage::from_parts_unchecked(
        camera.width(),
        camera.height(),
        pixels,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_normal_approximation_has_unit_variance() {
        let mut rng = SplitMix64::new(11);
        let n = 200_000;
        let xs: Vec<f64> = (0..n)
            .map(|_| standard_normal_approx(rng.next_u64()) as f64)
            .collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.01, "variance {var}");
        // Two-sided tail beyond 2σ: 4.35 % for Irwin–Hall(6) (a Gaussian: 4.55 %).
        let tail = xs.iter().filter(|x| x.abs() > 2.0).count() as f64 / n as f64;
        assert!((tail - 0.0435).abs() < 0.002, "tail {tail}");
        assert!(xs.iter().all(|x| x.abs() < 4.3));
    }

    #[test]
    fn vignetting_is_one_at_the_principal_point_and_loses_a_at_the_far_corner() {
        let cam = StereoCamera::euroc_like();
        assert!((vignetting_factor(&cam, 0.3, cam.cx(), cam.cy()) - 1.0).abs() < 1e-12);
        let corners = [(-0.5, -0.5), (751.5, -0.5), (-0.5, 479.5), (751.5, 479.5)];
        let lowest = corners
            .iter()
            .map(|&(u, v)| vignetting_factor(&cam, 0.3, u, v))
            .fold(1.0, f64::min);
        assert!((lowest - 0.7).abs() < 1e-12, "{lowest}");
    }
}
