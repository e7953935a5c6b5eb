//! Robust kernels on the squared Mahalanobis norm `s = rᵀΩr` of an edge.
//!
//! A kernel ρ(s) replaces s in the cost; iteratively reweighted least squares uses the
//! weight w = ρ'(s). Truncated least squares is not smooth, so it is solved by graduated
//! non-convexity (GNC, Yang et al. 2020) in [`crate::solver`], not as a plain kernel.

use statrs::distribution::{ChiSquared, ContinuousCDF};

/// A robust kernel, selectable per edge class.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Kernel {
    /// Plain least squares.
    #[default]
    None,
    /// Quadratic up to `s = k²`, linear in √s beyond.
    Huber { k: f64 },
    /// `c² ln(1 + s/c²)`.
    Cauchy { c: f64 },
    /// Truncated least squares at `s = c²`, solved by GNC.
    Gnc { c2: f64 },
}

impl Kernel {
    /// ρ(s).
    pub fn cost(&self, s: f64) -> f64 {
        match *self {
            Kernel::None => s,
            Kernel::Huber { k } => {
                if s <= k * k {
                    s
                } else {
                    2.0 * k * s.sqrt() - k * k
                }
            }
            Kernel::Cauchy { c } => c * c * (1.0 + s / (c * c)).ln(),
            Kernel::Gnc { c2 } => s.min(c2),
        }
    }

    /// ρ'(s), the IRLS weight (GNC's weights come from its own schedule, not from here).
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            Kernel::None | Kernel::Gnc { .. } => 1.0,
            Kernel::Huber { k } => {
                if s <= k * k {
                    1.0
                } else {
                    k / s.sqrt()
                }
            }
            Kernel::Cauchy { c } => 1.0 / (1.0 + s / (c * c)),
        }
    }
}

/// `χ²` quantile: the squared Mahalanobis norm below which a residual of `dof` dimensions
/// falls with probability `p` (for kernel thresholds and PCM's γ).
pub fn chi2_quantile(p: f64, dof: usize) -> Option<f64> {
    if !(p > 0.0 && p < 1.0) || dof == 0 {
        return None;
    }
    ChiSquared::new(dof as f64).ok().map(|d| d.inverse_cdf(p))
}

/// GNC-TLS weight of a residual `s` at control parameter `mu` (Yang et al. 2020, eq. 14).
pub fn gnc_tls_weight(s: f64, c2: f64, mu: f64) -> f64 {
    let lower = mu / (mu + 1.0) * c2;
    let upper = (mu + 1.0) / mu * c2;
    if s <= lower {
        1.0
    } else if s >= upper {
        0.0
    } else {
        (c2 * mu * (mu + 1.0) / s).sqrt() - mu
    }
}
