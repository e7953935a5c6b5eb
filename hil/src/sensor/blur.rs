//! Motion blur of a global-shutter exposure from one render and its depth.
//!
//! Pixel x sees, at time t of the exposure, the scene point that the mid-exposure image
//! shows at `x − f_t`, where `f_t` is the image motion (mid → t) of the point at x. So
//! the blurred pixel is the mean of the sharp image along the segment from `x − f_start`
//! to `x − f_end`, and `f` follows exactly from the pixel's depth and the camera's poses
//! at the exposure's start and end. Assumes the image motion is uniform around x (it is,
//! except across depth discontinuities) and straight within one exposure (a few ms).

use nalgebra::{Isometry3, Matrix3, Translation3, Vector3};
use rayon::prelude::*;

use crate::camera::StereoCamera;
use crate::error::HilError;

/// Samples per pixel of smear length: bilinear samples one pixel apart average the
/// bilinearly interpolated image along the smear closely (the test against sub-pose
/// renders measures it).
const SAMPLES_PER_PX: f32 = 1.0;
/// At most this many samples per pixel (a 31 px smear; more is a failed exposure anyway).
const MAX_SAMPLES: usize = 64;
/// Smears shorter than this (pixels) are left sharp.
const MIN_SMEAR_PX: f32 = 0.05;

/// Where the camera is at the start and end of the exposure relative to where it is at
/// mid-exposure (the frame's pose): `T_mid⁻¹ · T_start` and `T_mid⁻¹ · T_end`, both
/// camera-to-camera (a point `p` in the start camera is `start * p` in the mid camera).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExposureMotion {
    pub start: Isometry3<f64>,
    pub end: Isometry3<f64>,
}

impl ExposureMotion {
    /// No motion: a sharp image.
    pub fn still() -> Self {
        Self {
            start: Isometry3::identity(),
            end: Isometry3::identity(),
        }
    }

    /// From world poses (camera-to-world) at mid-exposure, start and end.
    pub fn from_poses(mid: &Isometry3<f64>, start: &Isometry3<f64>, end: &Isometry3<f64>) -> Self {
        let inv = mid.inverse();
        Self {
            start: inv * start,
            end: inv * end,
        }
    }

    /// The same rig motion seen by the right camera, `baseline` to the left camera's
    /// right: `B⁻¹ · Δ · B` with `B` the left-to-right offset.
    pub fn of_right_camera(&self, baseline: f64) -> Self {
        let b = Isometry3::from_parts(Translation3::new(baseline, 0.0, 0.0), Default::default());
        Self {
            start: b.inverse() * self.start * b,
            end: b.inverse() * self.end * b,
        }
    }
}

/// `Δ⁻¹` as f32: rotation `Rᵀ` and translation `−Rᵀ t`, to map mid-camera points into the
/// camera at an exposure end.
fn inverse_f32(delta: &Isometry3<f64>) -> (Matrix3<f32>, Vector3<f32>) {
    let inv = delta.inverse();
    (
        inv.rotation.to_rotation_matrix().into_inner().cast::<f32>(),
        inv.translation.vector.cast::<f32>(),
    )
}

/// Fractional bits of the fixed-point sample positions along a smear.
const FRACTION_BITS: u32 = 16;
const ONE: f32 = (1u32 << FRACTION_BITS) as f32;

/// Bilinear sample of a row-major image at the fixed-point position (u, v), which must lie
/// in `[0, w − 1) × [0, h − 1)` so all four neighbours exist. Fixed point: stepping along
/// a smear is an integer add, and the pixel and the weights come out of it without a
/// float-to-integer conversion per sample (the hot loop of the blur).
#[inline]
fn sample(image: &[f32], w: usize, u: i32, v: i32) -> f32 {
    let (u, v) = (u.max(0) as usize, v.max(0) as usize);
    let i = (v >> FRACTION_BITS) * w + (u >> FRACTION_BITS);
    let mask = (1 << FRACTION_BITS) - 1;
    let (a, b) = ((u & mask) as f32 / ONE, (v & mask) as f32 / ONE);
    let quad = &image[i..i + w + 2];
    let t = quad[0] + (quad[1] - quad[0]) * a;
    let d = quad[w] + (quad[w + 1] - quad[w]) * a;
    t + (d - t) * b
}

/// The exposure's average of `radiance` (row-major, the camera's size) for a camera that
/// moved by `motion`, using the z-depth of every pixel (`f32::INFINITY`: sky, moved only
/// by rotation). Rows run in parallel; the output does not depend on the thread count.
/// Both buffers must hold `width × height` values.
pub fn motion_blur(
    radiance: &[f32],
    depth: &[f32],
    camera: &StereoCamera,
    motion: &ExposureMotion,
) -> Result<Vec<f32>, HilError> {
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    for len in [radiance.len(), depth.len()] {
        if len != w * h {
            return Err(HilError::BufferLength {
                width: camera.width(),
                height: camera.height(),
                actual: len,
            });
        }
    }
    if w < 2 || h < 2 {
        return Ok(radiance.to_vec());
    }
    let (fx, fy, cx, cy) = (
        camera.fx() as f32,
        camera.fy() as f32,
        camera.cx() as f32,
        camera.cy() as f32,
    );
    let ends = [inverse_f32(&motion.start), inverse_f32(&motion.end)];
    // Just inside the last column and row, so the top-left neighbour of every sample has
    // a right and a lower neighbour.
    let (u_max, v_max) = ((w - 1) as f32 - 1.0 / 256.0, (h - 1) as f32 - 1.0 / 256.0);
    let mut out = vec![0f32; w * h];
    out.par_chunks_mut(w)
        .zip(radiance.par_chunks(w))
        .zip(depth.par_chunks(w))
        .enumerate()
        .for_each(|(row, ((out, input), depth))| {
            let v = row as f32;
            // Per exposure end: R · ray of column 0, its change per column, and t. A
            // mid-camera point z · ray appears at z R ray + t; a direction (sky) at R ray.
            let rows = ends.map(|(r, t)| {
                let ray0 = Vector3::new(-cx / fx, (v - cy) / fy, 1.0);
                (r * ray0, r.column(0) / fx, t)
            });
            for (col, ((o, &sharp), &z)) in out.iter_mut().zip(input).zip(depth).enumerate() {
                let u = col as f32;
                let mut smear = [(0.0f32, 0.0f32); 2];
                let mut visible = true;
                for ((r0, step, t), end) in rows.iter().zip(&mut smear) {
                    let rr = r0 + step * u;
                    let q = if z.is_finite() { rr * z + t } else { rr };
                    // Behind (or at) the camera at that instant: no smear to follow.
                    visible &= q.z > 1e-6;
                    let inv = 1.0 / q.z;
                    // This end of the smear, x − f with f = projection − x, kept inside
                    // the image (which is convex, so every sample between is inside too).
                    *end = (
                        (2.0 * u - (fx * q.x * inv + cx)).clamp(0.0, u_max),
                        (2.0 * v - (fy * q.y * inv + cy)).clamp(0.0, v_max),
                    );
                }
                let [(ua, va), (ub, vb)] = smear;
                let length = ((ub - ua) * (ub - ua) + (vb - va) * (vb - va)).sqrt();
                if !visible || length.is_nan() || length < MIN_SMEAR_PX {
                    *o = sharp;
                    continue;
                }
                // Midpoints of n equal slices, less than a pixel apart (at least two, so a
                // sub-pixel smear still softens the pixel).
                let n = ((length * SAMPLES_PER_PX) as usize + 2).min(MAX_SAMPLES);
                let (du, dv) = ((ub - ua) / n as f32, (vb - va) / n as f32);
                let fixed = |x: f32| (x * ONE) as i32;
                let (du, dv) = (fixed(du), fixed(dv));
                let (mut su, mut sv) = (fixed(ua) + du / 2, fixed(va) + dv / 2);
                let mut sum = 0.0;
                for _ in 0..n {
                    sum += sample(radiance, w, su, sv);
                    su += du;
                    sv += dv;
                }
                *o = sum / n as f32;
            }
        });
    Ok(out)
}
