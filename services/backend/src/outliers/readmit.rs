//! Beyond PCM: a pairwise test plus a maximum clique necessarily drops some inliers (a
//! closure that fails one pairwise test can be left out of the clique, and a lone closure
//! of a robot pair cannot be tested at all). After optimizing with the clique, each
//! rejected closure is re-tested against the optimized estimate: if its own residual is
//! within the χ²₆ quantile, it agrees with the map the clique built and is re-admitted.
//! Re-optimizing with GNC on the loop closures then still drops a wrong re-admission.

use nalgebra::Isometry3;

use crate::graph::{between_residual, BetweenFactor, PoseGraph};

/// Indices (into `rejected`) of the closures whose squared Mahalanobis residual at the
/// `estimate` is at most `gamma`. Each closure is given as (key i, key j, factor); closures
/// touching poses missing from the estimate are not re-admitted.
pub fn readmit(
    estimate: &PoseGraph<Isometry3<f64>>,
    rejected: &[(u64, u64, &BetweenFactor<Isometry3<f64>>)],
    gamma: f64,
) -> Vec<usize> {
    rejected
        .iter()
        .enumerate()
        .filter(
            |(_, (a, b, e))| match (estimate.index_of(*a), estimate.index_of(*b)) {
                (Some(i), Some(j)) => {
                    let r =
                        between_residual(&estimate.poses()[i], &estimate.poses()[j], &e.measured);
                    r.dot(&(e.information * r)) <= gamma
                }
                _ => false,
            },
        )
        .map(|(k, _)| k)
        .collect()
}
