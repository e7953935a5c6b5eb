//! # doorslam-backend
//!
//! The estimator of one robot: pose graphs, SE(3) math, graph IO, sparse pose-graph
//! optimization, outlier rejection and trajectory evaluation. A pure library: no threads,
//! no I/O besides the file readers; the `backend` service wraps it.
//!
//! Landed so far: [`linear`], the sparse Cholesky solver of the normal equations
//! (faer), which keeps its symbolic factorization between iterations.

pub mod linear;

pub use linear::{LinearError, SparseCholesky};
