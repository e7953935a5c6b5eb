//! # doorslam-backend
//!
//! The estimator of one robot: pose graphs, graph IO, sparse pose-graph optimization,
//! outlier rejection and trajectory evaluation, on the Lie groups of `doorslam-geometry`. A pure library: no threads,
//! no I/O besides the file readers; the `backend` service wraps it.
//!
//! - [`graph`], [`g2o`]: pose graphs with multi-robot keys, g2o reading/writing;
//! - [`solver`], [`init`], [`robust`], [`sparsity`], [`linear`]: Gauss-Newton /
//!   Levenberg-Marquardt on the sparse normal equations (faer Cholesky, symbolic
//!   factorization reused), chordal initialization, robust kernels and GNC;
//! - [`outliers`]: PCM (pairwise consistency + exact maximum clique, singleton closures
//!   checked through 3-robot cycles), closure labels, injected outliers;
//! - [`distributed`]: distributed PGO — one agent per robot (two-stage distributed
//!   Gauss-Seidel, then block-coordinate refinement) and an in-process team runner;
//! - [`eval`]: trajectory IO (KITTI/TUM/EuRoC), Umeyama alignment, ATE/RPE as evo.

pub mod distributed;
pub mod eval;
pub mod g2o;
pub mod graph;
pub mod init;
pub mod journal;
pub mod linear;
pub mod outliers;
pub mod rng;
pub mod robust;
pub mod service;
pub mod solver;
pub mod sparsity;

pub use doorslam_geometry::information::{check_information, InformationCheck, InformationError};
pub use doorslam_geometry::{key, LieGroup};
pub use g2o::{
    read_g2o, read_g2o_with, write_g2o, G2oFile, Graph, GraphError, InformationPolicy, ReadOptions,
    UnknownTags,
};
pub use graph::{BetweenFactor, EdgeClass, EdgeError, PoseGraph};
pub use linear::{LinearError, SparseCholesky};
pub use robust::Kernel;
pub use solver::{
    optimize, Criterion, Method, Optimizer, SolveError, SolverOptions, StopReason, Summary,
};
