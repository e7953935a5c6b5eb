//! Experiments run on the simulators: each measures a member crate's algorithm on
//! simulated data and returns typed results (the CLI prints them).
//!
//! - [`pcm_sweep`]: the back-end's PCM outlier rejection swept over its threshold on
//!   simulated teams ([`crate::posegraph_sim`]), the paper's Fig. 5/6 (`doorslam sim
//!   pcm-sweep`).

pub mod pcm_sweep;
