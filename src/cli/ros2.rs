//! `doorslam ros2 record RUN_DIR [--out FILE]`: a finished run folder as ROS 2 messages in
//! an MCAP file (logic in `doorslam_ros2::record`); `doorslam ros2 replay RUN_DIR
//! [--listen EP] [--connect EP] [--rate R]`: the same messages over Zenoh as rmw_zenoh
//! publishes them (`doorslam_ros2::replay`).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use doorslam_ros2::replay::ReplayOptions;

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
    /// Publish a finished run over Zenoh as rmw_zenoh does (one node per robot,
    /// `/<robot>/doorslam`), for RViz / Foxglove with `RMW_IMPLEMENTATION=rmw_zenoh_cpp`.
    Replay(ReplayArgs),
}

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// The run folder.
    pub run_dir: PathBuf,
    /// Zenoh endpoint to listen on (repeatable), e.g. `tcp/0.0.0.0:7448`.
    #[arg(long)]
    pub listen: Vec<String>,
    /// Zenoh endpoint to connect to (repeatable): the laptop's `rmw_zenohd`,
    /// `tcp/<laptop>:7447`.
    #[arg(long)]
    pub connect: Vec<String>,
    /// Run time per wall-clock time (2: twice as fast).
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// `ROS_DOMAIN_ID`.
    #[arg(long, default_value_t = 0)]
    pub domain_id: u32,
    /// No multicast scouting (only the given endpoints).
    #[arg(long)]
    pub no_multicast: bool,
    /// Print what was published as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
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
            let s = doorslam_ros2::record::record(&a.run_dir, a.out.as_deref())
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
        Ros2Command::Replay(a) => {
            let stop = Arc::new(AtomicBool::new(false));
            let flag = stop.clone();
            ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))
                .context("installing the Ctrl-C handler")?;
            let options = ReplayOptions {
                domain_id: a.domain_id,
                listen: a.listen,
                connect: a.connect,
                multicast_scouting: !a.no_multicast,
                rate: a.rate,
                ..ReplayOptions::default()
            };
            let s = doorslam_ros2::replay::replay(&a.run_dir, &options, &stop)
                .with_context(|| format!("doorslam ros2 replay {}", a.run_dir.display()))?;
            if a.json {
                println!("{}", serde_json::to_string(&s)?);
            } else {
                println!(
                    "session {}: {} samples in {:.1} s{}",
                    s.session_id,
                    s.samples.values().sum::<u64>(),
                    s.seconds,
                    if s.stopped { " (stopped)" } else { "" }
                );
                for t in &s.tokens {
                    println!("  {t}");
                }
            }
            Ok(())
        }
    }
}
