//! Absolute trajectory error (ATE, evo's APE translation part) and relative pose error
//! (RPE translation part), with the statistics evo reports.
//!
//! Matching evo (evo/core/metrics.py, filters.py): the ATE of pose k is
//! `||t_ref,k - (c R t_est,k + t)||` after aligning the estimate to the reference; the RPE of
//! a pair (i, j) is `||trans(E_ij)||` with `E_ij = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)` (Q reference,
//! P estimate, not aligned: RPE does not depend on a global transform of the estimate
//! unless it is scaled). Pairs are consecutive: every `delta` frames, or every `delta`
//! meters travelled along the *estimate*.

use nalgebra::{Isometry3, Similarity3};

use super::align::{align, Alignment};
use super::error::EvalError;
use super::trajectory::Trajectory;

/// Summary of a list of errors; `std` is the population standard deviation (numpy's
/// `np.std`), the median averages the two middle values of an even count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    pub rmse: f64,
    pub mean: f64,
    pub median: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
    /// Sum of squared errors.
    pub sse: f64,
    /// How many errors (pose pairs) were summarized.
    pub pairs: usize,
}

impl ErrorStats {
    /// Fails on an empty list.
    pub fn from_errors(errors: &[f64]) -> Result<Self, EvalError> {
        if errors.is_empty() {
            return Err(EvalError::NoErrors);
        }
        let n = errors.len() as f64;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let mean = errors.iter().sum::<f64>() / n;
        let variance = errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len() % 2 == 1 {
            sorted[mid]
        } else {
            0.5 * (sorted[mid - 1] + sorted[mid])
        };
        Ok(Self {
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: variance.sqrt(),
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            sse,
            pairs: errors.len(),
        })
    }
}

/// ATE: statistics, the error of each pose, and the alignment that was applied.
#[derive(Debug, Clone, PartialEq)]
pub struct AteResult {
    pub stats: ErrorStats,
    pub errors: Vec<f64>,
    /// Maps estimate positions onto the reference (identity for [`Alignment::None`]).
    pub alignment: Similarity3<f64>,
}

/// ATE of associated trajectories (pose k of one corresponds to pose k of the other).
pub fn absolute_trajectory_error(
    reference: &Trajectory,
    estimate: &Trajectory,
    alignment: Alignment,
) -> Result<AteResult, EvalError> {
    let transform = align(reference, estimate, alignment)?;
    let errors: Vec<f64> = reference
        .poses()
        .iter()
        .zip(estimate.poses())
        .map(|(q, p)| {
            let aligned = transform * nalgebra::Point3::from(p.translation.vector);
            (q.translation.vector - aligned.coords).norm()
        })
        .collect();
    Ok(AteResult {
        stats: ErrorStats::from_errors(&errors)?,
        errors,
        alignment: transform,
    })
}

/// Distance between the two poses of an RPE pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RpeDelta {
    /// Pairs `(0, d), (d, 2d), ...` by index.
    Frames(usize),
    /// Pairs of consecutive poses where the travelled path of the estimate reaches `d`
    /// meters (see [`pairs_by_path`]).
    Meters(f64),
}

impl Default for RpeDelta {
    /// evo's default: one frame.
    fn default() -> Self {
        Self::Frames(1)
    }
}

/// RPE: statistics, the error of each pair, and the pairs `(i, j)` (pose indices).
#[derive(Debug, Clone, PartialEq)]
pub struct RpeResult {
    pub stats: ErrorStats,
    pub errors: Vec<f64>,
    pub pairs: Vec<(usize, usize)>,
}

/// RPE translation part of associated trajectories, pairs chosen on the estimate.
pub fn relative_pose_error(
    reference: &Trajectory,
    estimate: &Trajectory,
    delta: RpeDelta,
) -> Result<RpeResult, EvalError> {
    if reference.len() != estimate.len() {
        return Err(EvalError::LengthMismatch {
            reference: reference.len(),
            estimate: estimate.len(),
        });
    }
    let (pairs, delta_text) = match delta {
        RpeDelta::Frames(0) => {
            return Err(EvalError::InvalidParameter(
                "RPE delta must be >= 1 frame".into(),
            ))
        }
        RpeDelta::Frames(d) => (pairs_by_index(estimate.len(), d), format!("{d} frames")),
        RpeDelta::Meters(d) if !(d.is_finite() && d >= 0.0) => {
            return Err(EvalError::InvalidParameter(format!(
                "RPE delta must be a finite number of meters >= 0, got {d}"
            )))
        }
        RpeDelta::Meters(d) => (pairs_by_path(estimate.poses(), d), format!("{d} m")),
    };
    if pairs.is_empty() {
        return Err(EvalError::NoPairs {
            delta: delta_text,
            poses: estimate.len(),
        });
    }
    let (q, p) = (reference.poses(), estimate.poses());
    let errors: Vec<f64> = pairs
        .iter()
        .map(|&(i, j)| {
            relative_error(&q[i], &q[j], &p[i], &p[j])
                .translation
                .vector
                .norm()
        })
        .collect();
    Ok(RpeResult {
        stats: ErrorStats::from_errors(&errors)?,
        errors,
        pairs,
    })
}

/// `E_ij = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)`: identity when the estimate moved exactly as the
/// reference between i and j.
fn relative_error(
    q_i: &Isometry3<f64>,
    q_j: &Isometry3<f64>,
    p_i: &Isometry3<f64>,
    p_j: &Isometry3<f64>,
) -> Isometry3<f64> {
    (q_i.inv_mul(q_j)).inv_mul(&p_i.inv_mul(p_j))
}

/// Consecutive pairs `(0, d), (d, 2d), ...` among `len` poses (evo's
/// `filter_pairs_by_index`, `all_pairs = false`).
pub fn pairs_by_index(len: usize, delta: usize) -> Vec<(usize, usize)> {
    if delta == 0 {
        return Vec::new();
    }
    let ids: Vec<usize> = (0..len).step_by(delta).collect();
    ids.windows(2).map(|w| (w[0], w[1])).collect()
}

/// evo's `filter_pairs_by_path` with `all_pairs = false`: walk the poses accumulating the
/// distance between successive positions, starting at pose 0; each time it reaches
/// `delta`, record the index and restart from 0. Pairs are consecutive recorded indices,
/// so pose 0 starts no pair unless `delta` is 0.
pub fn pairs_by_path(poses: &[Isometry3<f64>], delta: f64) -> Vec<(usize, usize)> {
    let mut ids = Vec::new();
    let mut current_path = 0.0;
    let mut previous = match poses.first() {
        Some(p) => p.translation.vector,
        None => return Vec::new(),
    };
    for (i, pose) in poses.iter().enumerate() {
        let t = pose.translation.vector;
        current_path += (t - previous).norm();
        previous = t;
        if current_path >= delta {
            ids.push(i);
            current_path = 0.0;
        }
    }
    ids.windows(2).map(|w| (w[0], w[1])).collect()
}
