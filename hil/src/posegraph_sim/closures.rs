//! Loop closures: inliers where paths meet, uniform outliers, correlated outlier groups.

use std::collections::BTreeSet;

use doorslam_geometry::{LieGroup, Tangent};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use super::random::{Rng, Stream};
use super::{CorrelatedGroup, SimConfig, SimError};

/// A pose of the team: (robot, index).
pub(super) type PoseId = (usize, usize);

/// Uniform outliers' translations are uniform in [-h, h]³ (m).
const OUTLIER_TRANSLATION_HALF_M: f64 = 10.0;
/// A correlated group's wrong offset: translation norm and rotation angle ranges.
const GROUP_OFFSET_M: (f64, f64) = (3.0, 10.0);
const GROUP_OFFSET_RAD: (f64, f64) = (0.3, 1.0);
/// Random draws per requested outlier before giving up on finding an unused pose pair.
const ATTEMPTS_PER_OUTLIER: usize = 1000;

/// A simulated closure before it enters the graph.
#[derive(Debug, Clone)]
pub(super) struct SimClosure {
    pub a: PoseId,
    pub b: PoseId,
    pub measured: Isometry3<f64>,
    pub inlier: bool,
    pub group: Option<usize>,
}

/// All closures, in arrival order, and the correlated groups' offsets.
pub(super) struct Closures {
    pub closures: Vec<SimClosure>,
    pub groups: Vec<CorrelatedGroup>,
}

/// Index pairs (i, j), sorted, with |pa[i] - pb[j]| < r: a sweep over pb sorted by x.
fn pairs_within(pa: &[Isometry3<f64>], pb: &[Isometry3<f64>], r: f64) -> Vec<(usize, usize)> {
    let mut by_x: Vec<(f64, usize)> = pb
        .iter()
        .enumerate()
        .map(|(j, t)| (t.translation.x, j))
        .collect();
    by_x.sort_by(|u, v| u.0.total_cmp(&v.0).then(u.1.cmp(&v.1)));
    let mut pairs = Vec::new();
    for (i, ta) in pa.iter().enumerate() {
        let x = ta.translation.x;
        let start = by_x.partition_point(|&(bx, _)| bx <= x - r);
        for &(bx, j) in &by_x[start..] {
            if bx >= x + r {
                break;
            }
            if (ta.translation.vector - pb[j].translation.vector).norm() < r {
                pairs.push((i, j));
            }
        }
    }
    pairs.sort_unstable();
    pairs
}

/// `T_a⁻¹ T_b`, the relative pose a closure from a to b measures.
fn relative(truth: &[Vec<Isometry3<f64>>], a: PoseId, b: PoseId) -> Isometry3<f64> {
    truth[a.0][a.1].inverse() * truth[b.0][b.1]
}

/// Inlier closures (inter-robot, then intra-robot if enabled): each pair of poses within
/// the radius is kept with the configured probability and measured with noise.
fn inliers(config: &SimConfig, truth: &[Vec<Isometry3<f64>>], noise: &mut Rng) -> Vec<SimClosure> {
    let (r, p) = (config.closure_radius_m, config.closure_probability);
    let mut candidates: Vec<(PoseId, PoseId)> = Vec::new();
    let mut select = Rng::new(config.seed, Stream::InlierSelection);
    for ra in 0..truth.len() {
        for rb in ra + 1..truth.len() {
            for (i, j) in pairs_within(&truth[ra], &truth[rb], r) {
                if select.bernoulli(p) {
                    candidates.push(((ra, i), (rb, j)));
                }
            }
        }
    }
    if config.intra_closures {
        // A revisit, not the same stretch of flight: the poses must be further apart
        // along the path than across the radius.
        let min_gap = ((2.0 * r / config.step_m).ceil() as usize).max(2);
        let mut select = Rng::new(config.seed, Stream::IntraSelection);
        for (ra, poses) in truth.iter().enumerate() {
            for (i, j) in pairs_within(poses, poses, r) {
                if j >= i + min_gap && select.bernoulli(p) {
                    candidates.push(((ra, i), (ra, j)));
                }
            }
        }
    }
    candidates
        .into_iter()
        .map(|(a, b)| SimClosure {
            a,
            b,
            measured: noise.perturb(&relative(truth, a, b), config.sigma_r, config.sigma_t),
            inlier: true,
            group: None,
        })
        .collect()
}

/// Two different robots, lower first.
fn robot_pair(rng: &mut Rng, robots: usize) -> (usize, usize) {
    let a = rng.below(robots);
    let b = (a + 1 + rng.below(robots - 1)) % robots;
    (a.min(b), a.max(b))
}

/// `count` uniform outliers between random poses of two different robots; the
/// measurement is a random pose, with the inliers' information (so it looks confident).
fn uniform_outliers(
    config: &SimConfig,
    count: usize,
    used: &mut BTreeSet<(PoseId, PoseId)>,
) -> Result<Vec<SimClosure>, SimError> {
    let mut rng = Rng::new(config.seed, Stream::UniformOutliers);
    let n = config.poses_per_robot;
    let mut out = Vec::with_capacity(count);
    let mut attempts = 0;
    while out.len() < count {
        attempts += 1;
        if attempts > ATTEMPTS_PER_OUTLIER * count {
            return Err(SimError::Infeasible(format!(
                "found only {} unused pose pairs for {count} uniform outliers",
                out.len()
            )));
        }
        let (ra, rb) = robot_pair(&mut rng, config.robots);
        let (a, b) = ((ra, rng.below(n)), (rb, rng.below(n)));
        let measured = rng.pose_in_cube(OUTLIER_TRANSLATION_HALF_M);
        if used.insert((a, b)) {
            out.push(SimClosure {
                a,
                b,
                measured,
                inlier: false,
                group: None,
            });
        }
    }
    Ok(out)
}

/// A wrong rigid offset: translation of norm in [3, 10] m, rotation of angle in
/// [0.3, 1] rad, both in random directions.
fn wrong_offset(rng: &mut Rng) -> Isometry3<f64> {
    let t = rng.direction() * rng.uniform(GROUP_OFFSET_M.0, GROUP_OFFSET_M.1);
    let axis = rng.direction();
    let angle = rng.uniform(GROUP_OFFSET_RAD.0, GROUP_OFFSET_RAD.1);
    Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_scaled_axis(axis * angle),
    )
}

/// Correlated outlier groups (perceptual aliasing of a repeated place): group g picks two
/// robots and a wrong offset W, then closes `size` consecutive poses of the first robot
/// with as many consecutive poses of the second, each measuring `T_a⁻¹ · W · T_b · Exp(ξ)`:
/// the truth with the second robot's pose displaced by W. Every cycle through two closures
/// of a group is the identity, so PCM finds them mutually consistent; a cycle with an
/// inlier is the conjugate of W, off by at least 0.3 rad.
fn correlated_groups(
    config: &SimConfig,
    truth: &[Vec<Isometry3<f64>>],
    used: &mut BTreeSet<(PoseId, PoseId)>,
) -> Result<(Vec<SimClosure>, Vec<CorrelatedGroup>), SimError> {
    let mut rng = Rng::new(config.seed, Stream::CorrelatedGroups);
    let (n, size) = (config.poses_per_robot, config.correlated_group_size);
    let (mut out, mut groups) = (Vec::new(), Vec::new());
    for g in 0..config.correlated_groups {
        let (ra, rb) = robot_pair(&mut rng, config.robots);
        let offset = wrong_offset(&mut rng);
        let mut placed = None;
        for _ in 0..ATTEMPTS_PER_OUTLIER {
            let (i0, j0) = (rng.below(n - size + 1), rng.below(n - size + 1));
            let pairs: Vec<(PoseId, PoseId)> =
                (0..size).map(|k| ((ra, i0 + k), (rb, j0 + k))).collect();
            if pairs.iter().all(|p| !used.contains(p)) {
                placed = Some(pairs);
                break;
            }
        }
        let pairs = placed.ok_or_else(|| {
            SimError::Infeasible(format!("no free stretch of poses for correlated group {g}"))
        })?;
        for (a, b) in pairs {
            used.insert((a, b));
            let displaced = truth[a.0][a.1].inverse() * offset * truth[b.0][b.1];
            out.push(SimClosure {
                a,
                b,
                measured: rng.perturb(&displaced, config.sigma_r, config.sigma_t),
                inlier: false,
                group: Some(g),
            });
        }
        groups.push(CorrelatedGroup {
            robot_a: ra as u8,
            robot_b: rb as u8,
            offset,
        });
    }
    Ok((out, groups))
}

/// Outliers needed so that outliers / (inliers + outliers) = f: round(f · I / (1 - f)).
pub(super) fn outlier_count(inter_inliers: usize, fraction: f64) -> usize {
    (fraction * inter_inliers as f64 / (1.0 - fraction)).round() as usize
}

/// Every closure of the team. Outlier accounting: the outlier count is
/// `round(f · I / (1 - f))` for I inter-robot inliers; correlated closures count toward it
/// and uniform outliers fill the rest (none if the groups alone exceed it, then the
/// fraction is above f). Intra-robot closures are all inliers and outside the fraction.
/// The result is in arrival order: a closure exists once its later pose is created.
pub(super) fn simulate_closures(
    config: &SimConfig,
    truth: &[Vec<Isometry3<f64>>],
    noise: &mut Rng,
) -> Result<Closures, SimError> {
    let mut closures = inliers(config, truth, noise);
    let mut used: BTreeSet<(PoseId, PoseId)> = closures.iter().map(|c| (c.a, c.b)).collect();
    let inter_inliers = closures.iter().filter(|c| c.a.0 != c.b.0).count();
    let (correlated, groups) = correlated_groups(config, truth, &mut used)?;
    let wanted = outlier_count(inter_inliers, config.outlier_fraction);
    let uniform = if config.robots >= 2 {
        uniform_outliers(config, wanted.saturating_sub(correlated.len()), &mut used)?
    } else {
        Vec::new()
    };
    closures.extend(uniform);
    closures.extend(correlated);
    // Pairs are unique, so this order is total.
    closures.sort_by_key(|c| (c.a.1.max(c.b.1), c.a, c.b));
    Ok(Closures { closures, groups })
}

/// Whitened χ² of a measurement against a relative pose: rᵀΩr, r = Log(z⁻¹ · t).
pub fn measurement_chi2(
    z: &Isometry3<f64>,
    t: &Isometry3<f64>,
    information: &nalgebra::Matrix6<f64>,
) -> f64 {
    let r: Tangent = (z.inverse() * t).log();
    r.dot(&(information * r))
}
