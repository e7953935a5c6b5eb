//! Pairing the poses of a reference and an estimate before comparing them.
//!
//! By timestamp this reproduces evo's `sync.associate_trajectories` (evo/core/sync.py):
//! each stamp of the *shorter* trajectory is paired with the nearest stamp of the longer
//! one (`argmin |t_long - t_short|`, the lowest index on ties) when they are at most
//! `max_diff` apart. Like evo, a stamp of the longer trajectory may be used twice if two
//! stamps of the shorter one are nearest to it; that cannot happen when the shorter one
//! is sampled more sparsely than `2 * max_diff`, the usual case.

use super::error::EvalError;
use super::trajectory::Trajectory;

/// evo's default maximum time difference for timestamp association, seconds.
pub const DEFAULT_MAX_TIME_DIFF: f64 = 0.01;

/// Pairs pose k with pose k (KITTI: both files have one line per image); both must have
/// the same length. Returns copies of (reference, estimate).
pub fn associate_by_index(
    reference: &Trajectory,
    estimate: &Trajectory,
) -> Result<(Trajectory, Trajectory), EvalError> {
    if reference.len() != estimate.len() {
        return Err(EvalError::LengthMismatch {
            reference: reference.len(),
            estimate: estimate.len(),
        });
    }
    Ok((reference.clone(), estimate.clone()))
}

/// Pairs poses by nearest timestamp (see the module docs), returning the matched
/// (reference, estimate) in the order of the shorter trajectory. Fails when nothing
/// matches.
pub fn associate_by_timestamp(
    reference: &Trajectory,
    estimate: &Trajectory,
    max_diff: f64,
) -> Result<(Trajectory, Trajectory), EvalError> {
    if !(max_diff.is_finite() && max_diff >= 0.0) {
        return Err(EvalError::InvalidParameter(format!(
            "max_diff must be a finite number >= 0, got {max_diff}"
        )));
    }
    // evo iterates over the shorter trajectory; on equal length the estimate is "shorter".
    let estimate_is_short = estimate.len() <= reference.len();
    let (short, long) = if estimate_is_short {
        (estimate, reference)
    } else {
        (reference, estimate)
    };
    let (short_ids, long_ids) =
        matching_time_indices(short.timestamps(), long.timestamps(), max_diff);
    if short_ids.is_empty() {
        return Err(EvalError::NoMatches {
            reference: reference.len(),
            estimate: estimate.len(),
            max_diff,
        });
    }
    let (short, long) = (short.select(&short_ids), long.select(&long_ids));
    Ok(if estimate_is_short {
        (long, short)
    } else {
        (short, long)
    })
}

/// For each stamp of `stamps_1`, the index of the nearest stamp of `stamps_2` if it is at
/// most `max_diff` away: (matched indices into `stamps_1`, into `stamps_2`).
fn matching_time_indices(
    stamps_1: &[f64],
    stamps_2: &[f64],
    max_diff: f64,
) -> (Vec<usize>, Vec<usize>) {
    let sorted = stamps_2.windows(2).all(|w| w[0] <= w[1]);
    let mut ids_1 = Vec::new();
    let mut ids_2 = Vec::new();
    for (i, &t) in stamps_1.iter().enumerate() {
        let nearest = if sorted {
            nearest_sorted(stamps_2, t)
        } else {
            nearest_scan(stamps_2, t)
        };
        if let Some((j, diff)) = nearest {
            if diff <= max_diff {
                ids_1.push(i);
                ids_2.push(j);
            }
        }
    }
    (ids_1, ids_2)
}

/// `argmin_j |stamps[j] - t|` (first index on ties) and the difference, by linear scan.
fn nearest_scan(stamps: &[f64], t: f64) -> Option<(usize, f64)> {
    let mut best: Option<(usize, f64)> = None;
    for (j, &s) in stamps.iter().enumerate() {
        let diff = (s - t).abs();
        if best.is_none_or(|(_, d)| diff < d) {
            best = Some((j, diff));
        }
    }
    best
}

/// Same result as [`nearest_scan`] on non-decreasing `stamps`, by binary search.
fn nearest_sorted(stamps: &[f64], t: f64) -> Option<(usize, f64)> {
    let right = stamps.partition_point(|&s| s < t);
    // Right of t the differences grow with the index, so `right` is the best there.
    let right_best = stamps.get(right).map(|&s| (right, (s - t).abs()));
    // Left of t they shrink with the index; the first index with the smallest difference
    // is found by walking back over equal differences (duplicate stamps).
    let left_best = right.checked_sub(1).map(|mut j| {
        let diff = (stamps[j] - t).abs();
        while j > 0 && (stamps[j - 1] - t).abs() == diff {
            j -= 1;
        }
        (j, diff)
    });
    match (left_best, right_best) {
        // On a tie the left index is lower, and argmin takes the first.
        (Some(l), Some(r)) => Some(if r.1 < l.1 { r } else { l }),
        (l, r) => l.or(r),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_search_agrees_with_scan() {
        let stamps = [0.0, 0.1, 0.1, 0.2, 0.30, 0.30, 0.5];
        for k in 0..=60 {
            let t = -0.05 + 0.01 * k as f64;
            assert_eq!(
                nearest_sorted(&stamps, t),
                nearest_scan(&stamps, t),
                "t = {t}"
            );
        }
        assert_eq!(nearest_sorted(&[], 1.0), None);
    }

    #[test]
    fn tie_takes_lower_index() {
        // 0.25 is exactly halfway between 0.0 and 0.5: argmin picks index 0.
        assert_eq!(nearest_sorted(&[0.0, 0.5], 0.25), Some((0, 0.25)));
        assert_eq!(nearest_scan(&[0.0, 0.5], 0.25), Some((0, 0.25)));
    }
}
