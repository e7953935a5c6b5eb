//! Procedural-texture building blocks: lattice hashing, value noise, and the analytic
//! box filters that stand in for supersampling.
//!
//! Every function here is a pure function of its arguments, so a surface point has the
//! same intensity from every viewpoint. Filtering takes the pixel *footprint* (the size
//! of one pixel on the surface, in the texture's units): detail finer than about two
//! footprints is replaced by its mean instead of being point-sampled, which is what
//! keeps distant facades from turning into aliasing noise at one sample per pixel.

/// `floor(x)` as an integer. `f64::floor` is a libm call on baseline x86-64 (no SSE4.1),
/// and the renderer floors several times per pixel; truncation plus a fix-up is one
/// instruction pair. Saturates far outside the i64 range, which no texture reaches.
#[inline]
pub(crate) fn floor_i(x: f64) -> i64 {
    let t = x as i64;
    t - ((t as f64) > x) as i64
}

/// Multipliers of the lattice hash (odd, high-entropy constants).
const HASH_X: u32 = 0x9E37_79B1;
const HASH_Y: u32 = 0x85EB_CA77;

/// Xorshift–multiply–xorshift finaliser of the lattice hash. One multiply round is
/// enough to hide the lattice in a texture (four hashes per noise octave per pixel are
/// a large share of the frame time); it is not meant for anything statistical.
#[inline]
fn finalise(mut h: u32) -> u32 {
    h = (h ^ (h >> 15)).wrapping_mul(0x2C1B_3C6D);
    h ^ (h >> 13)
}

/// Integer lattice hash of a 2D cell and a seed: one multiply per coordinate, then a
/// multiply–xorshift finaliser (enough avalanche for texture, and cheap: it runs four
/// times per noise octave per pixel). Coordinates wrap modulo 2^32 cells.
#[inline]
pub(crate) fn hash2(ix: i64, iy: i64, seed: u32) -> u32 {
    finalise((ix as u32).wrapping_mul(HASH_X) ^ (iy as u32).wrapping_mul(HASH_Y) ^ seed)
}

#[inline]
fn to_unit(h: u32) -> f64 {
    (h >> 8) as f64 * (1.0 / (1u32 << 24) as f64)
}

/// A hash mapped to [0, 1).
#[inline]
pub(crate) fn hash_unit(ix: i64, iy: i64, seed: u32) -> f64 {
    to_unit(hash2(ix, iy, seed))
}

#[inline]
fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// Value noise in [0, 1): random values on the integer lattice, smoothly interpolated.
#[inline]
pub(crate) fn value_noise(x: f64, y: f64, seed: u32) -> f64 {
    let (ix, iy) = (floor_i(x), floor_i(y));
    let (tx, ty) = (smooth(x - ix as f64), smooth(y - iy as f64));
    // The four corner hashes share their per-coordinate products (same values as hash2).
    let hx0 = (ix as u32).wrapping_mul(HASH_X);
    let hx1 = hx0.wrapping_add(HASH_X);
    let hy0 = (iy as u32).wrapping_mul(HASH_Y) ^ seed;
    let hy1 = (iy as u32).wrapping_add(1).wrapping_mul(HASH_Y) ^ seed;
    let a = to_unit(finalise(hx0 ^ hy0));
    let b = to_unit(finalise(hx1 ^ hy0));
    let c = to_unit(finalise(hx0 ^ hy1));
    let d = to_unit(finalise(hx1 ^ hy1));
    let top = a + (b - a) * tx;
    let bottom = c + (d - c) * tx;
    top + (bottom - top) * ty
}

/// How much of a pattern with `cycles_per_footprint` cycles per pixel survives filtering:
/// 1 below a quarter cycle per pixel, 0 from the Nyquist limit (half a cycle) on.
#[inline]
pub(crate) fn nyquist_weight(cycles_per_footprint: f64) -> f64 {
    let t = ((cycles_per_footprint - 0.25) / 0.25).clamp(0.0, 1.0);
    1.0 - smooth(t)
}

/// One octave of value noise at `freq` cycles per unit, centred on 0 with amplitude ≤ 1,
/// fading to its mean (0) above the Nyquist limit of the footprint.
#[inline]
pub(crate) fn noise1(x: f64, y: f64, seed: u32, freq: f64, fp: Footprint) -> f64 {
    let w = nyquist_weight(freq * fp.width());
    if w <= 0.0 {
        return 0.0;
    }
    2.0 * w * (value_noise(x * freq, y * freq, seed) - 0.5)
}

/// Two octaves of value noise (frequencies `freq` and `2 freq` cycles per unit, weights
/// 1 and 1/2), centred on 0 with amplitude ≤ 1. An octave above the Nyquist limit of
/// the footprint fades to its mean, 0, and is not evaluated. Two octaves per layer is
/// the renderer's budget: noise is most of the cost of a pixel.
#[inline]
pub(crate) fn fbm2(x: f64, y: f64, seed: u32, freq: f64, fp: Footprint) -> f64 {
    let w0 = nyquist_weight(freq * fp.width());
    if w0 <= 0.0 {
        return 0.0;
    }
    let mut sum = w0 * (value_noise(x * freq, y * freq, seed) - 0.5);
    let w1 = nyquist_weight(2.0 * freq * fp.width());
    if w1 > 0.0 {
        sum += 0.5 * w1 * (value_noise(2.0 * freq * x, 2.0 * freq * y, seed ^ 0x68E3_1DA4) - 0.5);
    }
    // (n - 0.5) ∈ [-0.5, 0.5); weights sum to 1.5.
    sum * (2.0 / 1.5)
}

/// A pixel's footprint on a surface (its width in texture units) and the reciprocal:
/// box filtering divides by the width many times per pixel, and divisions dominated
/// the renderer's profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Footprint {
    width: f64,
    inv_width: f64,
}

impl Footprint {
    pub(crate) fn new(width: f64) -> Self {
        let width = if width.is_finite() {
            width.max(0.0)
        } else {
            f64::MAX
        };
        let inv_width = if width > 1e-12 { 1.0 / width } else { 0.0 };
        Self { width, inv_width }
    }

    /// The footprint of a pixel whose ray meets a surface at camera depth `depth`: a
    /// pixel of angular size `pixel_angle` (1/√(fx fy)) covers the surface area
    /// `depth² pixel_angle² / |n·d|` when its ray `d` is scaled to unit camera z (the
    /// off-axis solid angle and the distance cancel out), so the width is
    /// `depth pixel_angle / √|n·d|`. Grazing rays stretch the footprint along one
    /// direction only; the square root of the area is their geometric mean, and
    /// `min_cos` keeps the horizon from blurring to a constant. The width and its
    /// reciprocal are two independent divisions, so they do not add up in latency.
    #[inline]
    pub(crate) fn of_pixel(
        depth: f32,
        pixel_angle: f32,
        normal_dot_ray: f32,
        min_cos: f32,
    ) -> Self {
        let s = normal_dot_ray.abs().max(min_cos).sqrt();
        let base = depth * pixel_angle;
        if base > 0.0 && base.is_finite() {
            Self {
                width: (base / s) as f64,
                inv_width: (s / base) as f64,
            }
        } else {
            Self::new(base as f64 / s as f64)
        }
    }

    pub(crate) fn width(self) -> f64 {
        self.width
    }

    /// The indicator of [a, b] box-filtered around `x`: the fraction of
    /// [x - w/2, x + w/2] inside [a, b]. Exact for one interval; point-sampled at w = 0.
    #[inline]
    pub(crate) fn interval(self, x: f64, a: f64, b: f64) -> f64 {
        if self.inv_width == 0.0 {
            return if x >= a && x <= b { 1.0 } else { 0.0 };
        }
        let lo = (x - 0.5 * self.width).clamp(a, b);
        let hi = (x + 0.5 * self.width).clamp(a, b);
        (hi - lo) * self.inv_width
    }
}

/// A pattern repeating with `period` along one axis, seen through a footprint.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Lattice {
    period: f64,
    inv_period: f64,
    /// How much of the per-period detail survives filtering (1 = all, 0 = none).
    detail: f64,
}

impl Lattice {
    pub(crate) fn new(period: f64, fp: Footprint) -> Self {
        let inv_period = 1.0 / period;
        Self {
            period,
            inv_period,
            detail: nyquist_weight(fp.width() * inv_period),
        }
    }

    /// Cell index of `x` and its offset in [0, period) within the cell.
    #[inline]
    pub(crate) fn split(self, x: f64) -> (i64, f64) {
        let cell = floor_i(x * self.inv_period);
        (cell, x - cell as f64 * self.period)
    }

    pub(crate) fn detail(self) -> f64 {
        self.detail
    }

    /// The indicator of [a, b] in every period, box-filtered; `offset` is from
    /// [`Lattice::split`]. A single-interval box filter would fade to 0 once the footprint
    /// spans several periods; the true average is the duty cycle, so the result blends to
    /// it as the period approaches the Nyquist limit.
    #[inline]
    pub(crate) fn interval(self, offset: f64, a: f64, b: f64, fp: Footprint) -> f64 {
        let duty = (b - a) * self.inv_period;
        if self.detail <= 0.0 {
            return duty;
        }
        mix(duty, fp.interval(offset, a, b), self.detail)
    }
}

/// Linear interpolation from `a` (t = 0) to `b` (t = 1).
#[inline]
pub(crate) fn mix(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_noise_is_continuous_across_cells() {
        let s = 7;
        for i in -5..5 {
            let x = i as f64;
            let left = value_noise(x - 1e-9, 0.3, s);
            let right = value_noise(x + 1e-9, 0.3, s);
            assert!((left - right).abs() < 1e-6);
        }
    }

    #[test]
    fn fbm_fades_to_zero_when_footprint_is_huge() {
        assert_eq!(fbm2(3.3, 4.4, 9, 1.0, Footprint::new(1e6)), 0.0);
        let near = fbm2(3.3, 4.4, 9, 1.0, Footprint::new(0.0));
        assert!(near.abs() <= 1.0);
    }

    #[test]
    fn value_noise_corners_are_the_lattice_hash() {
        for (x, y) in [(3.0, -2.0), (-7.0, 11.0)] {
            assert_eq!(value_noise(x, y, 5), hash_unit(x as i64, y as i64, 5));
        }
    }

    #[test]
    fn floor_matches_std() {
        for x in [-3.5, -3.0, -0.2, 0.0, 0.7, 2.0, 1e9 + 0.5, -1e9 - 0.5] {
            assert_eq!(floor_i(x) as f64, x.floor(), "{x}");
        }
    }

    #[test]
    fn box_interval_is_coverage() {
        let fp = Footprint::new(0.2);
        assert!((fp.interval(0.5, 0.0, 1.0) - 1.0).abs() < 1e-12);
        assert!((fp.interval(0.0, 0.0, 1.0) - 0.5).abs() < 1e-12);
        assert_eq!(fp.interval(2.0, 0.0, 1.0), 0.0);
        assert_eq!(Footprint::new(0.0).interval(0.5, 0.0, 1.0), 1.0);
    }

    #[test]
    fn lattice_blends_to_the_duty_cycle() {
        let coarse = Lattice::new(1.0, Footprint::new(10.0));
        assert!((coarse.interval(0.5, 0.2, 0.6, Footprint::new(10.0)) - 0.4).abs() < 1e-12);
        let fine = Lattice::new(1.0, Footprint::new(0.01));
        assert_eq!(fine.split(-0.25), (-1, 0.75));
        assert!((fine.interval(0.5, 0.2, 0.6, Footprint::new(0.01)) - 1.0).abs() < 1e-12);
    }
}
