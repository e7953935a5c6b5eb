//! The simulator's random numbers: SplitMix64 with Box-Muller Gaussians.
//!
//! Written here rather than shared with the renderer's layout generator: a dataset is
//! pinned byte for byte by its seed, so its generator must not change when the
//! renderer's does. Each purpose (trajectories, closure selection, noise, ...) draws from
//! its own stream, so changing e.g. the outlier fraction leaves the trajectories and the
//! inlier closures of a seed untouched.

use doorslam_geometry::{LieGroup, Tangent};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// Independent streams of one seed.
#[derive(Debug, Clone, Copy)]
pub(super) enum Stream {
    Trajectories = 1,
    InlierSelection = 2,
    MeasurementNoise = 3,
    UniformOutliers = 4,
    CorrelatedGroups = 5,
    IntraSelection = 6,
}

/// SplitMix64 (Steele, Lea, Flood 2014): passes BigCrush, seedable from any integer.
#[derive(Debug, Clone)]
pub(super) struct Rng {
    state: u64,
    /// Second Box-Muller output, kept so no draw is wasted.
    spare: Option<f64>,
}

impl Rng {
    pub(super) fn new(seed: u64, stream: Stream) -> Self {
        // Mixing the stream id through one SplitMix64 step decorrelates the streams.
        let mut mixer = Rng {
            state: seed ^ (stream as u64).wrapping_mul(0xD1B5_4A32_D192_ED03),
            spare: None,
        };
        Rng {
            state: mixer.next_u64(),
            spare: None,
        }
    }

    pub(super) fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1), from the top 53 bits.
    pub(super) fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    pub(super) fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform integer in [0, n), n > 0 (Lemire's multiply-shift; bias < n / 2⁶⁴).
    pub(super) fn below(&mut self, n: usize) -> usize {
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }

    /// True with probability `p`.
    pub(super) fn bernoulli(&mut self, p: f64) -> bool {
        self.unit() < p
    }

    /// Standard normal (Box-Muller).
    pub(super) fn gaussian(&mut self) -> f64 {
        if let Some(z) = self.spare.take() {
            return z;
        }
        // 1 - unit() is in (0, 1]: the log is finite.
        let r = (-2.0 * (1.0 - self.unit()).ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * self.unit()).sin_cos();
        self.spare = Some(r * s);
        r * c
    }

    /// ξ ~ N(0, diag(σr², σr², σr², σt², σt², σt²)), rotation first.
    pub(super) fn tangent_noise(&mut self, sigma_r: f64, sigma_t: f64) -> Tangent {
        let mut xi = Tangent::zeros();
        for k in 0..6 {
            xi[k] = self.gaussian() * if k < 3 { sigma_r } else { sigma_t };
        }
        xi
    }

    /// `t · Exp(ξ)`: a measurement of `t` with right-perturbation noise.
    pub(super) fn perturb(
        &mut self,
        t: &Isometry3<f64>,
        sigma_r: f64,
        sigma_t: f64,
    ) -> Isometry3<f64> {
        t * Isometry3::exp(&self.tangent_noise(sigma_r, sigma_t))
    }

    /// Rotation uniform on SO(3) (Shoemake's subgroup algorithm).
    pub(super) fn rotation(&mut self) -> UnitQuaternion<f64> {
        let (u1, u2, u3) = (self.unit(), self.unit(), self.unit());
        let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
        let (s2, c2) = (std::f64::consts::TAU * u2).sin_cos();
        let (s3, c3) = (std::f64::consts::TAU * u3).sin_cos();
        UnitQuaternion::from_quaternion(Quaternion::new(b * c3, a * s2, a * c2, b * s3))
    }

    /// A unit vector uniform on the sphere.
    pub(super) fn direction(&mut self) -> Vector3<f64> {
        let z = self.uniform(-1.0, 1.0);
        let (s, c) = self.uniform(0.0, std::f64::consts::TAU).sin_cos();
        let r = (1.0 - z * z).sqrt();
        Vector3::new(r * c, r * s, z)
    }

    /// A pose with translation uniform in [-h, h]³ and rotation uniform on SO(3).
    pub(super) fn pose_in_cube(&mut self, h: f64) -> Isometry3<f64> {
        let t = Translation3::new(
            self.uniform(-h, h),
            self.uniform(-h, h),
            self.uniform(-h, h),
        );
        Isometry3::from_parts(t, self.rotation())
    }
}
