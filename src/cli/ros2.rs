//! `doorslam ros2 record RUN_DIR [--out FILE]`: a finished run folder as ROS 2 messages in
//! an MCAP file (logic in `doorslam_hil::ros2_record`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

#[derive(Debug, Args)]
pub struct Ros2Args {
    #[command(subcommand)]
    pub command: Ros2Command,
}

#[derive(Debug, Subcommand)]
pub enum Ros2Command {
    /// Write a finished `doorslam demo` run folder as `run.mcap` (ros2msg schemas, CDR
    /// payloads: what `ros2 bag` writes; opens in Foxglove, Lichtblick, `ros2 bag play`).
    Record(RecordArgs),
}

#[derive(Debug, Args)]
pub struct RecordArgs {
    /// The run folder (`<robot>/keyframes.csv`, `odometry.tum`, `team_estimate.tum`, ...).
    pub run_dir: PathBuf,
    /// Where to write (default `<RUN_DIR>/run.mcap`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print what was written as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Ros2Args) -> Result<()> {
    match args.command {
        Ros2Command::Record(a) => {
            let s = doorslam_hil::ros2_record::record(&a.run_dir, a.out.as_deref())
                .with_context(|| format!("doorslam ros2 record {}", a.run_dir.display()))?;
            if a.json {
                println!("{}", serde_json::to_string(&s)?);
            } else {
                println!(
                    "{}: {} robots ({}), {} messages, {} bytes",
                    s.path.display(),
                    s.robots.len(),
                    s.robots.join(", "),
                    s.messages.values().sum::<u64>(),
                    s.bytes
                );
                for (topic, n) in &s.messages {
                    println!("  {topic}: {n}");
                }
            }
            Ok(())
        }
    }
}
