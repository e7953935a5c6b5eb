//! `doorslam bw [--json] RUN_DIR_OR_LEDGER`: the paper's Table II for a run, from its
//! ledger files (logic in `doorslam_team::bw`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

#[derive(Debug, Args)]
pub struct BwArgs {
    /// A run folder (its `ledger.json` and `*/ledger.json`, one per robot) or one ledger file.
    pub path: PathBuf,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: BwArgs) -> Result<()> {
    let ledgers = doorslam_team::bw::load(&args.path)
        .with_context(|| format!("doorslam bw {}", args.path.display()))?;
    let report = doorslam_team::bw::report(&ledgers);
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{}", report.table());
    }
    Ok(())
}
