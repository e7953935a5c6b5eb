//! The `doorslam` command line: argument parsing, dispatch, progress and JSON output.
//! All algorithms live in the member crates; this crate only wires them up.

pub mod cli;
pub mod config;
