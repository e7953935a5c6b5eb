//! Simulation tools of the distributed back-end: teams made of single-robot graphs
//! ([`split_into_team`]).

mod split;

pub use split::{split_into_team, SplitError};
