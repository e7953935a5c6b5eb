//! Outlier rejection of loop closures by Pairwise Consistency Maximization (PCM, Mangelson
//! et al. 2018): the largest set of pairwise-consistent closures is a maximum clique.

pub mod cycles;
pub mod inject;
pub mod labels;
pub mod max_clique;
pub mod pcm;
pub mod readmit;

pub use cycles::{confirm_through_cycles, cycle_mahalanobis2, triple_mahalanobis2};
pub use inject::inject_outliers;
pub use labels::{read_labels, Labels, LabelsError, Quality};
pub use max_clique::{
    core_decomposition, heuristic_clique, maximum_clique, CliqueOptions, CliqueResult,
    ConsistencyGraph, CoreDecomposition, VertexOutOfRange,
};
pub use pcm::{
    pairwise_mahalanobis2, Closure, Odometry, PairProblem, Pcm, PcmError, PcmSummary, Scope,
};
pub use readmit::readmit;
