//! Multi-robot pose-graph simulator: the DOOR-SLAM paper's ARGoS experiment (its
//! "Simulation Experiments") at the
//! pose-graph level.
//!
//! Drones fly smooth random walks in a shared 20 m × 20 m × 6 m arena, so their paths cross
//! many times ([`ARENA_HALF_M`], [`ARENA_HALF_HEIGHT_M`]). The front-end is simulated by
//! noisy measurements, all with the same Gaussian model (paper: σ_R = 0.01 rad,
//! σ_t = 0.1 m): a measurement of the relative pose `T` is `z = T · Exp(ξ)` with
//! `ξ ~ N(0, Σ)`, `Σ = diag(σr², σr², σr², σt², σt², σt²)` in the rotation-first tangent
//! of [`doorslam_geometry::lie`], and its information matrix is exactly `Σ⁻¹`, so the
//! whitened residual of a measurement at the true poses is χ²₆-distributed.
//!
//! - odometry `i → i+1` of every robot;
//! - inlier inter-robot closures: each pair of poses of two robots closer than the
//!   radius yields one with the configured probability;
//! - uniform outliers (the paper's): random pose pairs of two robots measuring a random
//!   pose (translation in [-10, 10]³ m, rotation uniform on SO(3)), as confident as inliers;
//! - correlated outlier groups (the paper's future work): mutually consistent wrong
//!   closures, as perceptual aliasing of a repeated place makes — see [`CorrelatedGroup`];
//! - optionally, inlier intra-robot closures where a robot revisits its own path.
//!
//! Outlier accounting: `outlier_fraction` f is outliers / (inliers + outliers) among the
//! inter-robot closures, so there are `round(f · I / (1 - f))` outliers for I inlier
//! closures. Correlated closures count toward that number and uniform outliers fill the
//! rest; if the groups alone exceed it there are no uniform outliers and the fraction is
//! above f ([`SimulatedTeam::outlier_fraction`] reports the real one).
//!
//! Everything is a pure function of [`SimConfig`]: the same seed gives the same bytes.
//! Each purpose draws from its own random stream, so e.g. changing `outlier_fraction`
//! keeps the trajectories, odometry and inlier closures of a seed.

mod closures;
mod config;
mod dataset;
mod random;
mod trajectory;

use doorslam_backend::{BetweenFactor, PoseGraph};
use doorslam_geometry::key;
use nalgebra::Isometry3;

pub use closures::measurement_chi2;
pub use config::{SimConfig, SimError, MAX_ROBOTS};
pub use dataset::{truth_file_name, write_dataset};
pub use trajectory::{in_arena, ARENA_HALF_HEIGHT_M, ARENA_HALF_M};

use random::{Rng, Stream};

/// A loop closure of the simulated graph and what it really is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LabelledClosure {
    /// Multi-robot keys (`doorslam_geometry::key::symbol`); for inter-robot closures the
    /// lower robot comes first.
    pub key_a: u64,
    pub key_b: u64,
    /// Whether the measurement is the true relative pose plus the nominal noise.
    pub inlier: bool,
    /// The correlated outlier group ([`SimulatedTeam::groups`]) it belongs to, if any.
    pub group: Option<usize>,
}

/// A group of mutually consistent wrong closures between `robot_a` and `robot_b`: each
/// measures `T_a⁻¹ · offset · T_b` (plus noise), the truth with robot b's pose displaced
/// by the world-frame `offset` W (translation 3-10 m, rotation 0.3-1 rad).
#[derive(Debug, Clone, PartialEq)]
pub struct CorrelatedGroup {
    pub robot_a: u8,
    pub robot_b: u8,
    pub offset: Isometry3<f64>,
}

/// Closure counts by kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ClosureCounts {
    pub inter_inliers: usize,
    pub uniform_outliers: usize,
    pub correlated_outliers: usize,
    pub intra_inliers: usize,
}

/// A simulated team: truth, the noisy multi-robot graph, and the label of every closure.
#[derive(Debug, Clone)]
pub struct SimulatedTeam {
    pub config: SimConfig,
    /// Ground truth, per robot, per pose index.
    pub truth: Vec<Vec<Isometry3<f64>>>,
    /// Poses robot-major (`symbol(robot, index)`), initialized by chaining each robot's
    /// odometry from its true first pose; edges: all odometry (robot-major), then the
    /// closures in the order of [`SimulatedTeam::closures`].
    pub graph: PoseGraph<Isometry3<f64>>,
    /// One per closure edge, in edge order (arrival order: by the later pose's index).
    pub closures: Vec<LabelledClosure>,
    pub groups: Vec<CorrelatedGroup>,
}

impl SimulatedTeam {
    /// The true pose of a multi-robot key.
    pub fn true_pose(&self, k: u64) -> Option<&Isometry3<f64>> {
        let robot = usize::from(key::robot(k)?);
        let index = usize::try_from(key::index(k)).ok()?;
        self.truth.get(robot)?.get(index)
    }

    /// The odometry edges (the graph's first edges).
    pub fn odometry_edges(&self) -> &[BetweenFactor<Isometry3<f64>>] {
        let n = self.graph.edges().len().saturating_sub(self.closures.len());
        &self.graph.edges()[..n]
    }

    /// The closure edges, aligned with [`SimulatedTeam::closures`].
    pub fn closure_edges(&self) -> &[BetweenFactor<Isometry3<f64>>] {
        let n = self.graph.edges().len().saturating_sub(self.closures.len());
        &self.graph.edges()[n..]
    }

    pub fn counts(&self) -> ClosureCounts {
        let mut c = ClosureCounts::default();
        for l in &self.closures {
            let inter = key::robot(l.key_a) != key::robot(l.key_b);
            match (inter, l.inlier, l.group) {
                (false, _, _) => c.intra_inliers += 1,
                (true, true, _) => c.inter_inliers += 1,
                (true, false, None) => c.uniform_outliers += 1,
                (true, false, Some(_)) => c.correlated_outliers += 1,
            }
        }
        c
    }

    /// Outliers / (inliers + outliers) among the inter-robot closures (0 if none).
    pub fn outlier_fraction(&self) -> f64 {
        let c = self.counts();
        let outliers = c.uniform_outliers + c.correlated_outliers;
        let total = outliers + c.inter_inliers;
        if total == 0 {
            0.0
        } else {
            outliers as f64 / total as f64
        }
    }

    /// The configuration as one `name=value` line, for dataset provenance.
    pub fn config_line(&self) -> String {
        let c = &self.config;
        format!(
            "robots={} poses_per_robot={} step_m={} sigma_t={} sigma_r={} closure_radius_m={} \
             closure_probability={} outlier_fraction={} correlated_groups={} \
             correlated_group_size={} intra_closures={} seed={}",
            c.robots,
            c.poses_per_robot,
            c.step_m,
            c.sigma_t,
            c.sigma_r,
            c.closure_radius_m,
            c.closure_probability,
            c.outlier_fraction,
            c.correlated_groups,
            c.correlated_group_size,
            c.intra_closures,
            c.seed
        )
    }
}

/// Simulates a team from `config` (validated first).
pub fn simulate(config: &SimConfig) -> Result<SimulatedTeam, SimError> {
    config.validate()?;
    let truth = trajectory::simulate_truth(config);
    let information = config.information();
    let mut noise = Rng::new(config.seed, Stream::MeasurementNoise);
    let n = config.poses_per_robot;
    let node = |(robot, index): closures::PoseId| robot * n + index;

    let mut graph = PoseGraph::new();
    let mut odometry = Vec::new();
    for (robot, poses) in truth.iter().enumerate() {
        let mut estimate = poses[0];
        graph.add_pose(key::symbol(robot as u8, 0)?, estimate);
        for (index, pair) in poses.windows(2).enumerate() {
            let z = noise.perturb(
                &(pair[0].inverse() * pair[1]),
                config.sigma_r,
                config.sigma_t,
            );
            estimate *= z;
            graph.add_pose(key::symbol(robot as u8, index as u64 + 1)?, estimate);
            odometry.push((node((robot, index)), node((robot, index + 1)), z));
        }
    }
    // The configuration was validated (positive sigmas: Σ⁻¹ is positive definite) and every
    // edge joins two distinct poses, so the graph refuses nothing; say so if it ever does.
    let refused =
        |e: doorslam_backend::EdgeError| SimError::Infeasible(format!("simulated edge: {e}"));
    for (i, j, z) in odometry {
        graph.add_edge(i, j, z, information).map_err(refused)?;
    }

    let sim = closures::simulate_closures(config, &truth, &mut noise)?;
    let mut labelled = Vec::with_capacity(sim.closures.len());
    for c in sim.closures {
        graph
            .add_edge(node(c.a), node(c.b), c.measured, information)
            .map_err(refused)?;
        labelled.push(LabelledClosure {
            key_a: key::symbol(c.a.0 as u8, c.a.1 as u64)?,
            key_b: key::symbol(c.b.0 as u8, c.b.1 as u64)?,
            inlier: c.inlier,
            group: c.group,
        });
    }
    Ok(SimulatedTeam {
        config: config.clone(),
        truth,
        graph,
        closures: labelled,
        groups: sim.groups,
    })
}
