//! Subcommands whose implementation arrives with a later issue: they say which, and fail.

use anyhow::{bail, Result};
use clap::Args;

/// Accepts any arguments, so that `doorslam pgo file.g2o --json` gets the clear
/// "not built yet" message rather than an argument error.
#[derive(Debug, Args)]
pub struct PendingArgs {
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, hide = true)]
    pub args: Vec<String>,
}

pub fn fail(name: &str, issue: &str, _args: &PendingArgs) -> Result<()> {
    bail!("`doorslam {name}` is not built yet: it arrives with {issue}")
}
