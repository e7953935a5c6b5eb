//! Pyramidal Lucas-Kanade tracking of points from one image into the next (Bouguet's
//! pyramidal KLT, translation only), seeded by a guess of where each point went.
//!
//! For a point `p` of the previous image, LK minimises `Σₓ (J(x + q) − T(x))²` over the
//! window `x ∈ [−r, r]²`, `T` the previous image around `p`, `J` the next one: with the
//! template's gradient `g`, `H = Σ g gᵀ` and `b = Σ g (J − T)`, each step is
//! `q ← q − H⁻¹ b`. It starts at the coarsest pyramid level from the guess, and each
//! level's result, doubled, seeds the next finer one, so a good guess (the motion
//! prediction's projection) plus a few levels covers a large image motion.
//!
//! Brightness changes between frames (auto-exposure after a shade step) are absorbed by
//! matching `J`'s patch to `T`'s mean and contrast before the difference
//! (`J' = μT + (J − μJ) σT/σJ`).
//!
//! Every sample is a bilinear interpolation with the same four weights across a patch (its
//! fractional offset is shared), so patch extraction is four multiply-adds per pixel over
//! contiguous rows, which the compiler vectorizes.

use opencv::core::{Mat, Size};
use opencv::prelude::*;

use crate::error::{cv, VisionError};
use crate::image::Gray;

/// Settings of [`track`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KltConfig {
    /// Half size of the window (px): `(2r+1)²` pixels at every level.
    pub window_radius: usize,
    /// Pyramid levels used (1: the full-resolution image only).
    pub levels: usize,
    /// Gauss-Newton steps per level, at most.
    pub max_iterations: usize,
    /// A step shorter than this (px, at the level) ends a level.
    pub epsilon_px: f32,
    /// Smallest eigenvalue of the template's `H / N` ((DN/px)²): flatter windows (a blank
    /// wall, an edge without a corner) are not tracked.
    pub min_eigenvalue: f32,
    /// Largest mean absolute difference (DN) between the brightness-matched patches at the
    /// full resolution: a larger one is an occlusion or a wrong match.
    pub max_residual_dn: f32,
}

impl Default for KltConfig {
    fn default() -> Self {
        Self {
            window_radius: 5,
            levels: 4,
            max_iterations: 15,
            epsilon_px: 0.02,
            min_eigenvalue: 4.0,
            max_residual_dn: 14.0,
        }
    }
}

/// An image pyramid: level 0 a copy of the image, each next level OpenCV's `pyrDown` of the
/// one before (5×5 Gaussian, every second pixel). The buffers are kept between frames.
#[derive(Default)]
pub struct Pyramid {
    levels: Vec<Mat>,
    used: usize,
}

impl std::fmt::Debug for Pyramid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pyramid")
            .field("levels", &self.used)
            .finish()
    }
}

/// One level's pixels.
#[derive(Clone, Copy)]
struct Level<'a> {
    width: usize,
    height: usize,
    pixels: &'a [u8],
}

impl Pyramid {
    /// Rebuilds the pyramid from `image` with `levels` levels (fewer when the image gets
    /// smaller than 16 px).
    pub fn build(&mut self, image: &Gray<'_>, levels: usize) -> Result<(), VisionError> {
        let levels = levels.max(1);
        while self.levels.len() < levels {
            self.levels.push(Mat::default());
        }
        image
            .mat()?
            .copy_to(&mut self.levels[0])
            .map_err(cv("pyramid level 0"))?;
        self.used = 1;
        for k in 1..levels {
            let (w, h) = (self.levels[k - 1].cols(), self.levels[k - 1].rows());
            if w < 32 || h < 32 {
                break;
            }
            let (done, rest) = self.levels.split_at_mut(k);
            opencv::imgproc::pyr_down(
                &done[k - 1],
                &mut rest[0],
                Size::new((w + 1) / 2, (h + 1) / 2),
                opencv::core::BORDER_DEFAULT,
            )
            .map_err(cv("pyrDown"))?;
            self.used = k + 1;
        }
        Ok(())
    }

    /// Levels built.
    pub fn len(&self) -> usize {
        self.used
    }

    pub fn is_empty(&self) -> bool {
        self.used == 0
    }

    fn level(&self, k: usize) -> Level<'_> {
        let m = &self.levels[k];
        Level {
            width: m.cols() as usize,
            height: m.rows() as usize,
            pixels: m.data_bytes().unwrap_or(&[]),
        }
    }

    /// Level 0 as a borrowed image.
    pub fn image(&self) -> Option<Gray<'_>> {
        (self.used > 0).then(|| {
            let l = self.level(0);
            Gray {
                width: l.width,
                height: l.height,
                pixels: l.pixels,
            }
        })
    }
}

/// Why a point was not tracked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KltFailure {
    /// The window left the image.
    OutOfImage,
    /// The template has too little texture in some direction.
    Flat,
    /// The iteration diverged or did not settle.
    NoConvergence,
    /// The matched patches differ too much.
    Residual,
}

/// A tracked point: its position in the next image and the final mean absolute
/// difference of the brightness-matched patches (DN).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tracked {
    pub pixel: [f32; 2],
    pub residual_dn: f32,
}

/// Scratch buffers of one point's tracking, reused over points and frames.
#[derive(Debug, Default)]
pub struct KltScratch {
    template: Vec<f32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
    grid: Vec<f32>,
    patch: Vec<f32>,
}

/// Tracks `from` (pixels of the previous image) into the next image, starting each from
/// `guess` (where it is expected, e.g. the motion prediction's projection).
pub fn track(
    prev: &Pyramid,
    next: &Pyramid,
    from: &[[f32; 2]],
    guess: &[[f32; 2]],
    config: &KltConfig,
    scratch: &mut KltScratch,
) -> Vec<Result<Tracked, KltFailure>> {
    from.iter()
        .zip(guess)
        .map(|(p, g)| track_point(prev, next, *p, *g, config.levels, config, scratch))
        .collect()
}

/// One point through the pyramid, from the coarsest level where its window fits.
pub fn track_point(
    prev: &Pyramid,
    next: &Pyramid,
    p: [f32; 2],
    guess: [f32; 2],
    levels: usize,
    config: &KltConfig,
    scratch: &mut KltScratch,
) -> Result<Tracked, KltFailure> {
    let r = config.window_radius;
    let levels = levels.clamp(1, prev.len().min(next.len()));
    // The coarsest level at which the template's window (plus a pixel for the gradient
    // and one for interpolation) lies inside the previous image.
    let fits = |k: usize| {
        let l = prev.level(k);
        let s = (1u32 << k) as f32;
        let (x, y) = (p[0] / s, p[1] / s);
        let m = r as f32 + 2.0;
        x >= m && y >= m && x < l.width as f32 - m && y < l.height as f32 - m
    };
    let Some(top) = (0..levels).rev().find(|&k| fits(k)) else {
        return Err(KltFailure::OutOfImage);
    };
    let mut d = [
        (guess[0] - p[0]) / (1u32 << top) as f32,
        (guess[1] - p[1]) / (1u32 << top) as f32,
    ];
    let mut residual = 0.0;
    for k in (0..=top).rev() {
        let s = (1u32 << k) as f32;
        let pl = [p[0] / s, p[1] / s];
        let (q, e) = track_level(prev.level(k), next.level(k), pl, d, k == 0, config, scratch)?;
        d = [q[0] - pl[0], q[1] - pl[1]];
        residual = e;
        if k > 0 {
            d = [2.0 * d[0], 2.0 * d[1]];
        }
    }
    if residual > config.max_residual_dn {
        return Err(KltFailure::Residual);
    }
    Ok(Tracked {
        pixel: [p[0] + d[0], p[1] + d[1]],
        residual_dn: residual,
    })
}

/// Samples `out` (size × size) from `level` with its top-left sample at `(x, y)`; false
/// when it would read outside the image.
fn sample_patch(level: Level<'_>, x: f32, y: f32, size: usize, out: &mut [f32]) -> bool {
    if !(x >= 0.0 && y >= 0.0) {
        return false;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    if x0 + size >= level.width || y0 + size >= level.height {
        return false;
    }
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let (w00, w01, w10, w11) = (
        (1.0 - fx) * (1.0 - fy),
        fx * (1.0 - fy),
        (1.0 - fx) * fy,
        fx * fy,
    );
    let w = level.width;
    for (j, out_row) in out.chunks_exact_mut(size).take(size).enumerate() {
        let a = &level.pixels[(y0 + j) * w + x0..][..size + 1];
        let b = &level.pixels[(y0 + j + 1) * w + x0..][..size + 1];
        for i in 0..size {
            out_row[i] = w00 * a[i] as f32
                + w01 * a[i + 1] as f32
                + w10 * b[i] as f32
                + w11 * b[i + 1] as f32;
        }
    }
    true
}

/// Lanes of the reductions below: independent partial sums the compiler keeps in one SIMD
/// register each (a single running sum would have to be added in order, one at a time).
const LANES: usize = 8;

/// `(Σ a, Σ a², Σ a·x, Σ a·y)` over buffers padded with zeros to a multiple of [`LANES`].
fn moments(a: &[f32], x: &[f32], y: &[f32]) -> [f32; 4] {
    let mut acc = [[0.0f32; LANES]; 4];
    for ((a, x), y) in a
        .chunks_exact(LANES)
        .zip(x.chunks_exact(LANES))
        .zip(y.chunks_exact(LANES))
    {
        for l in 0..LANES {
            acc[0][l] += a[l];
            acc[1][l] += a[l] * a[l];
            acc[2][l] += a[l] * x[l];
            acc[3][l] += a[l] * y[l];
        }
    }
    acc.map(|lanes| lanes.iter().sum())
}

/// `(Σ x², Σ x·y, Σ y², Σ x, Σ y)` over padded buffers.
fn structure(x: &[f32], y: &[f32]) -> [f32; 5] {
    let mut acc = [[0.0f32; LANES]; 5];
    for (x, y) in x.chunks_exact(LANES).zip(y.chunks_exact(LANES)) {
        for l in 0..LANES {
            acc[0][l] += x[l] * x[l];
            acc[1][l] += x[l] * y[l];
            acc[2][l] += y[l] * y[l];
            acc[3][l] += x[l];
            acc[4][l] += y[l];
        }
    }
    acc.map(|lanes| lanes.iter().sum())
}

/// LK at one level from displacement `d`: the position in `next`, and (when `residual`)
/// the mean absolute difference of the brightness-matched windows there (else 0).
///
/// With `J' = μT + (J − μJ) γ`, `γ = σT / σJ`, the gradient term
/// `b = Σ g (J' − T) = γ (Σ g J − μJ Σ g) + Σ g (μT − T)`: per step only `Σ J`, `Σ J²` and
/// `Σ g J` over the window are needed, one pass.
fn track_level(
    prev: Level<'_>,
    next: Level<'_>,
    p: [f32; 2],
    d: [f32; 2],
    residual: bool,
    config: &KltConfig,
    s: &mut KltScratch,
) -> Result<([f32; 2], f32), KltFailure> {
    let r = config.window_radius;
    let n = 2 * r + 1;
    let g = n + 2;
    let padded = (n * n).div_ceil(LANES) * LANES;
    s.grid.resize(g * g, 0.0);
    for buffer in [&mut s.template, &mut s.gx, &mut s.gy, &mut s.patch] {
        buffer.clear();
        buffer.resize(padded, 0.0);
    }
    let half = r as f32;
    if !sample_patch(prev, p[0] - half - 1.0, p[1] - half - 1.0, g, &mut s.grid) {
        return Err(KltFailure::OutOfImage);
    }
    // Template and central-difference gradients from the (n+2)² grid around it.
    for j in 0..n {
        let (above, row, below) = (
            &s.grid[j * g..(j + 1) * g],
            &s.grid[(j + 1) * g..(j + 2) * g],
            &s.grid[(j + 2) * g..(j + 3) * g],
        );
        let (t, gx, gy) = (
            &mut s.template[j * n..(j + 1) * n],
            &mut s.gx[j * n..(j + 1) * n],
            &mut s.gy[j * n..(j + 1) * n],
        );
        for i in 0..n {
            t[i] = row[i + 1];
            gx[i] = 0.5 * (row[i + 2] - row[i]);
            gy[i] = 0.5 * (below[i + 1] - above[i + 1]);
        }
    }
    let [hxx, hxy, hyy, sum_gx, sum_gy] = structure(&s.gx, &s.gy);
    let count = (n * n) as f32;
    let trace = 0.5 * (hxx + hyy);
    let min_eig = (trace - (0.25 * (hxx - hyy).powi(2) + hxy * hxy).sqrt()) / count;
    if min_eig < config.min_eigenvalue {
        return Err(KltFailure::Flat);
    }
    let det = hxx * hyy - hxy * hxy;
    let [st_sum, st_sq, gx_t, gy_t] = moments(&s.template, &s.gx, &s.gy);
    let mt = st_sum / count;
    let st = (st_sq / count - mt * mt).max(0.0).sqrt();
    // Σ g (μT − T), constant over the steps.
    let (cx, cy) = (mt * sum_gx - gx_t, mt * sum_gy - gy_t);
    let mut q = [p[0] + d[0], p[1] + d[1]];
    let mut step = f32::INFINITY;
    let (mut mj, mut gain) = (0.0f32, 1.0f32);
    for _ in 0..config.max_iterations {
        if !sample_patch(next, q[0] - half, q[1] - half, n, &mut s.patch) {
            return Err(KltFailure::OutOfImage);
        }
        let [sj, sj_sq, gx_j, gy_j] = moments(&s.patch, &s.gx, &s.gy);
        mj = sj / count;
        let std = (sj_sq / count - mj * mj).max(0.0).sqrt();
        if std < 1e-3 {
            return Err(KltFailure::Flat);
        }
        gain = st / std;
        let bx = gain * (gx_j - mj * sum_gx) + cx;
        let by = gain * (gy_j - mj * sum_gy) + cy;
        let dx = (hyy * bx - hxy * by) / det;
        let dy = (hxx * by - hxy * bx) / det;
        if !(dx.is_finite() && dy.is_finite()) {
            return Err(KltFailure::NoConvergence);
        }
        q = [q[0] - dx, q[1] - dy];
        step = (dx * dx + dy * dy).sqrt();
        if step < config.epsilon_px {
            break;
        }
    }
    // Not settled within the steps: accepted only when the last step was small (an
    // oscillation around the optimum), which the residual check at level 0 then judges.
    if step > 0.25 {
        return Err(KltFailure::NoConvergence);
    }
    let mut abs = 0.0;
    if residual {
        // On the last window sampled (a step under `epsilon_px` before the result).
        for k in 0..n * n {
            abs += (mt + (s.patch[k] - mj) * gain - s.template[k]).abs();
        }
    }
    Ok((q, abs / count))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(x: f32, y: f32) -> f32 {
        128.0
            + 40.0 * (0.21 * x + 0.05 * y).sin()
            + 35.0 * (0.11 * x - 0.19 * y).cos()
            + 25.0 * (0.37 * x * 0.5 + 0.31 * y).sin() * (0.07 * x).cos()
    }

    fn image(w: usize, h: usize, shift: [f32; 2], gain: f32) -> Vec<u8> {
        let mut out = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let v = texture(x as f32 - shift[0], y as f32 - shift[1]);
                out[y * w + x] = (128.0 + (v - 128.0) * gain).round().clamp(0.0, 255.0) as u8;
            }
        }
        out
    }

    #[test]
    fn a_shifted_darker_texture_is_tracked_to_a_tenth_of_a_pixel_from_a_poor_guess() {
        let (w, h) = (320, 240);
        let shift = [17.3f32, -6.6];
        let a = image(w, h, [0.0, 0.0], 1.0);
        // The next frame is darker and flatter (an exposure change) as well as shifted.
        let b = image(w, h, shift, 0.6);
        let (mut pa, mut pb) = (Pyramid::default(), Pyramid::default());
        pa.build(&Gray::new(w, h, &a).unwrap(), 4).unwrap();
        pb.build(&Gray::new(w, h, &b).unwrap(), 4).unwrap();
        let config = KltConfig::default();
        let mut scratch = KltScratch::default();
        let from = [[100.0f32, 100.0], [160.4, 120.7], [200.0, 80.2]];
        // The guess is 6 px off the truth (a fifth of the texture's shortest period).
        let guess: Vec<[f32; 2]> = from
            .iter()
            .map(|p| [p[0] + shift[0] + 4.8, p[1] + shift[1] - 3.6])
            .collect();
        for (p, t) in from
            .iter()
            .zip(track(&pa, &pb, &from, &guess, &config, &mut scratch))
        {
            let t = t.unwrap();
            let err = ((t.pixel[0] - p[0] - shift[0]).powi(2)
                + (t.pixel[1] - p[1] - shift[1]).powi(2))
            .sqrt();
            assert!(err < 0.1, "{p:?} -> {t:?}: error {err} px");
        }
    }

    #[test]
    fn flat_and_outside_points_are_refused() {
        let (w, h) = (200, 120);
        let flat = vec![100u8; w * h];
        let textured = image(w, h, [0.0, 0.0], 1.0);
        let (mut pf, mut pt) = (Pyramid::default(), Pyramid::default());
        pf.build(&Gray::new(w, h, &flat).unwrap(), 3).unwrap();
        pt.build(&Gray::new(w, h, &textured).unwrap(), 3).unwrap();
        let config = KltConfig::default();
        let mut scratch = KltScratch::default();
        let r = track_point(
            &pf,
            &pt,
            [100.0, 60.0],
            [100.0, 60.0],
            3,
            &config,
            &mut scratch,
        );
        assert_eq!(r, Err(KltFailure::Flat));
        let r = track_point(&pt, &pt, [1.0, 60.0], [1.0, 60.0], 3, &config, &mut scratch);
        assert_eq!(r, Err(KltFailure::OutOfImage));
        // Into a flat image: no texture to match.
        let r = track_point(
            &pt,
            &pf,
            [100.0, 60.0],
            [100.0, 60.0],
            3,
            &config,
            &mut scratch,
        );
        assert!(r.is_err(), "{r:?}");
    }
}
