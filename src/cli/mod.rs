//! Subcommands, one file each.

mod bench;
mod bw;
mod demo;
mod dpgo;
mod eval;
mod pcm;
mod pgo;
mod place;
mod replay;
mod ros2;
mod router;
mod service;
pub(crate) mod sim;
mod team;
mod up;
mod verify;
mod vo;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// doorslam: distributed, online, outlier-resilient SLAM for drone teams.
#[derive(Debug, Parser)]
#[command(name = "doorslam", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run one on-robot service process (what a systemd unit starts).
    Service(service::ServiceArgs),
    /// Start all services of one robot as child processes.
    Up(up::UpArgs),
    /// Optimize a pose graph (g2o): Gauss-Newton / Levenberg-Marquardt.
    Pgo(pgo::PgoArgs),
    /// Reject outlier loop closures with PCM (pairwise consistency + maximum clique).
    Pcm(pcm::PcmArgs),
    /// Distributed pose-graph optimization (two-stage distributed Gauss-Seidel, then
    /// refinement), played in-process and compared with the centralized optimum.
    Dpgo(dpgo::DpgoArgs),
    /// Evaluate trajectories: ATE / RPE against ground truth.
    Eval(eval::EvalArgs),
    /// Place recognition offline: describe keyframes, evaluate matching, train the BoW vocabulary.
    Place(place::PlaceArgs),
    /// Simulate worlds, flights and multi-robot pose graphs.
    Sim(sim::SimArgs),
    /// Stereo visual odometry over a KITTI or EuRoC folder: every frame's pose, timing, drift.
    Vo(vo::VoArgs),
    /// Geometric verification of two keyframe packets (debugging), or the verification
    /// benchmark on pairs with ground truth (--bench).
    Verify(verify::VerifyArgs),
    /// Replay a dataset (KITTI / EuRoC layout) into the on-robot pipeline.
    Replay(replay::ReplayArgs),
    /// Measure what each inter-robot message kind costs in bytes.
    Bw(bw::BwArgs),
    /// The team link's security: certificates for TLS with mutual authentication.
    Team(team::TeamArgs),
    /// Run a Zenoh router for large fleets (robots connect to it instead of to each other).
    Router(router::RouterArgs),
    /// Run the demo: a team of drones, each a host of its own, building one map; a report.
    Demo(demo::DemoArgs),
    /// Measure the on-robot transports (iceoryx2, Zenoh shared memory, Unix socket).
    Bench(bench::BenchArgs),
    /// ROS 2 forms of a run: `record` writes a run folder as MCAP.
    Ros2(ros2::Ros2Args),
}

/// Names of the on-robot services, as `doorslam service NAME` spells them.
pub fn service_names() -> Vec<String> {
    use clap::ValueEnum;
    service::ServiceName::value_variants()
        .iter()
        .filter_map(|v| v.to_possible_value().map(|p| p.get_name().to_string()))
        .collect()
}

/// Parses the command line, runs the subcommand, prints the whole error chain on failure.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logging();
    let result = match cli.command {
        Command::Service(args) => service::run(args),
        Command::Up(args) => up::run(args),
        Command::Pgo(args) => pgo::run(args),
        Command::Pcm(args) => pcm::run(args),
        Command::Dpgo(args) => dpgo::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Place(args) => place::run(args),
        Command::Sim(args) => sim::run(args),
        Command::Vo(args) => vo::run(args),
        Command::Verify(args) => verify::run(args),
        Command::Replay(args) => replay::run(args),
        Command::Bw(args) => bw::run(args),
        Command::Team(args) => team::run(args),
        Command::Router(args) => router::run(args),
        Command::Demo(args) => demo::run(args),
        Command::Bench(args) => bench::run(args),
        Command::Ros2(args) => ros2::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

/// Logs go to stderr (stdout is reserved for `--json` output); `RUST_LOG` overrides.
fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,zenoh=warn"));
    // Colours only on a terminal: `up` and systemd read these lines from pipes.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(ansi)
        .try_init();
}

/// A duration given in seconds on the command line: finite, `0 ..= max_s` (an unbounded
/// value would overflow `Duration` and panic), with an error naming the flag.
pub fn seconds(flag: &str, value: f64, max_s: f64) -> anyhow::Result<std::time::Duration> {
    anyhow::ensure!(
        value.is_finite() && (0.0..=max_s).contains(&value),
        "{flag} {value}: must be a number of seconds from 0 to {max_s}"
    );
    Ok(std::time::Duration::from_secs_f64(value))
}

/// The longest wait a flag may ask for: a day.
pub const MAX_WAIT_S: f64 = 86_400.0;

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    #[test]
    fn command_tree_is_consistent() {
        super::Cli::command().debug_assert();
    }
}
