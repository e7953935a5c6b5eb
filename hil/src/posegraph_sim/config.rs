//! The simulator's configuration and its one error type.

use std::path::PathBuf;

use doorslam_backend::GraphError;

/// How to simulate a team; every field is checked by [`SimConfig::validate`].
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Number of robots (keys `a`, `b`, ...; at most 52, the multi-robot key alphabet 'a'..'z', 'A'..'Z').
    pub robots: usize,
    /// Poses per robot trajectory (at least 2, so there is odometry).
    pub poses_per_robot: usize,
    /// Distance flown between consecutive poses, m.
    pub step_m: f64,
    /// Standard deviation of each translation component of a measurement, m.
    pub sigma_t: f64,
    /// Standard deviation of each rotation component of a measurement, rad.
    pub sigma_r: f64,
    /// Two poses closer than this may yield a loop closure, m.
    pub closure_radius_m: f64,
    /// Chance that a pair of poses within the radius yields a closure.
    pub closure_probability: f64,
    /// Outliers / (inliers + outliers) among the inter-robot closures, uniform and
    /// correlated outliers together.
    pub outlier_fraction: f64,
    /// Number of groups of mutually consistent wrong closures (perceptual aliasing).
    pub correlated_groups: usize,
    /// Closures per correlated group.
    pub correlated_group_size: usize,
    /// Also simulate (inlier) loop closures of a robot with its own earlier poses.
    pub intra_closures: bool,
    /// Everything random derives from this.
    pub seed: u64,
}

impl Default for SimConfig {
    /// The paper's ARGoS setting (5 drones, σ_R = 0.01 rad, σ_t = 0.1 m) with 30 % uniform
    /// outliers; the closure probability gives roughly 30-75 inter-robot inliers with 100
    /// poses per robot (~6400 pose pairs of different robots lie within 3 m).
    fn default() -> Self {
        Self {
            robots: 5,
            poses_per_robot: 100,
            step_m: 1.0,
            sigma_t: 0.1,
            sigma_r: 0.01,
            closure_radius_m: 3.0,
            closure_probability: 0.007,
            outlier_fraction: 0.3,
            correlated_groups: 0,
            correlated_group_size: 5,
            intra_closures: false,
            seed: 1,
        }
    }
}

/// Failures of simulating or writing a team.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A configuration field is out of range; names the field.
    #[error("invalid simulation config: {field} = {value} ({reason})")]
    InvalidConfig {
        field: &'static str,
        value: String,
        reason: &'static str,
    },
    /// The configuration is valid but cannot be realized (e.g. more outliers than there
    /// are unused pose pairs).
    #[error("cannot simulate: {0}")]
    Infeasible(String),
    #[error("cannot simulate: {0}")]
    Key(#[from] doorslam_geometry::KeyError),
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Graph {
        path: PathBuf,
        #[source]
        source: GraphError,
    },
}

/// Largest robot count: keys use one lowercase letter per robot.
pub const MAX_ROBOTS: usize = doorslam_geometry::key::MAX_ROBOTS as usize;

fn invalid(field: &'static str, value: impl ToString, reason: &'static str) -> SimError {
    SimError::InvalidConfig {
        field,
        value: value.to_string(),
        reason,
    }
}

fn positive(field: &'static str, v: f64) -> Result<(), SimError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(field, v, "must be finite and > 0"))
    }
}

impl SimConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), SimError> {
        if !(1..=MAX_ROBOTS).contains(&self.robots) {
            return Err(invalid("robots", self.robots, "must be in 1..=52"));
        }
        if self.poses_per_robot < 2 {
            return Err(invalid(
                "poses_per_robot",
                self.poses_per_robot,
                "must be >= 2",
            ));
        }
        positive("step_m", self.step_m)?;
        // Longer steps would jump across the arena instead of flying in it.
        if self.step_m > super::ARENA_HALF_M {
            return Err(invalid(
                "step_m",
                self.step_m,
                "must be <= 10 m (half the arena)",
            ));
        }
        positive("sigma_t", self.sigma_t)?;
        positive("sigma_r", self.sigma_r)?;
        // Beyond ~1 rad the rotation noise wraps around and is no longer Gaussian.
        if self.sigma_r > 0.5 {
            return Err(invalid("sigma_r", self.sigma_r, "must be <= 0.5 rad"));
        }
        positive("closure_radius_m", self.closure_radius_m)?;
        if !(0.0..=1.0).contains(&self.closure_probability) {
            return Err(invalid(
                "closure_probability",
                self.closure_probability,
                "must be in [0, 1]",
            ));
        }
        if !(0.0..1.0).contains(&self.outlier_fraction) {
            return Err(invalid(
                "outlier_fraction",
                self.outlier_fraction,
                "must be in [0, 1)",
            ));
        }
        if self.correlated_groups > 0 {
            if self.robots < 2 {
                return Err(invalid(
                    "correlated_groups",
                    self.correlated_groups,
                    "needs robots >= 2",
                ));
            }
            if !(1..=self.poses_per_robot).contains(&self.correlated_group_size) {
                return Err(invalid(
                    "correlated_group_size",
                    self.correlated_group_size,
                    "must be in 1..=poses_per_robot",
                ));
            }
        }
        Ok(())
    }

    /// Information matrix of every measurement: the inverse of
    /// diag(σr², σr², σr², σt², σt², σt²) (rotation-first tangent order).
    pub fn information(&self) -> nalgebra::Matrix6<f64> {
        let (wr, wt) = (self.sigma_r.powi(-2), self.sigma_t.powi(-2));
        nalgebra::Matrix6::from_diagonal(&nalgebra::Vector6::new(wr, wr, wr, wt, wt, wt))
    }
}
