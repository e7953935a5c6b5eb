//! Simulation tools of the distributed back-end: teams made of single-robot graphs
//! ([`split_into_team`]), and the team link robots run as the `dpgo` runner's transport
//! ([`SessionLink`]).

mod link;
mod split;

pub use link::{Faults, LinkOptions, SessionLink};
pub use split::{split_into_team, SplitError};
