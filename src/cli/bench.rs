//! `doorslam bench ipc [--json]`: the on-robot transports measured side by side, with
//! the subscriber in a second process (this binary again, as the hidden `ipc-peer`).

use std::time::Duration;

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use doorslam_ipc_bench::{
    self as bench, IpcOptions, PeerCommand, PeerEndpoint, PeerSpec, Transport,
};

/// The hidden subcommand the benchmark re-executes this binary with.
const PEER_SUBCOMMAND: [&str; 2] = ["bench", "ipc-peer"];

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub command: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Latency, throughput, zero-copy and 30 Hz CPU of iceoryx2 (polling, event-driven),
    /// an eventfd wake-up floor, Zenoh SHM and a Unix socket, for 752x480 and 1280x720 pairs.
    Ipc(IpcArgs),
    /// The subscriber process of `bench ipc` (started by it).
    #[command(hide = true)]
    IpcPeer(PeerArgs),
}

#[derive(Debug, Args)]
pub struct IpcArgs {
    /// Print exactly one JSON object on stdout instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Length of each measured phase (latency, throughput, 30 Hz) of each case, seconds.
    #[arg(long, default_value_t = 2.0)]
    pub seconds_per_case: f64,
    /// Most latency samples per case (pairs paced 2 ms apart).
    #[arg(long, default_value_t = 1000)]
    pub frames: usize,
    /// Times each case is run, interleaved (all transports once, then again, ...); each
    /// row is the round with the median p99, so a burst of load on the 2 cores hits the
    /// transports alike instead of one of them.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// Pin the publisher and the subscriber process to these two CPUs ("0,1"), instead of
    /// letting the scheduler place them (it often wakes the subscriber on the publisher's
    /// core, which favours some wake-up mechanisms over others).
    #[arg(long, value_parser = parse_cpu_pair)]
    pub pin_cpus: Option<(usize, usize)>,
}

fn parse_cpu_pair(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected two CPU numbers, e.g. 0,1"))?;
    let cpu = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|e| format!("{v:?} is not a CPU number: {e}"))
    };
    Ok((cpu(a)?, cpu(b)?))
}

/// The peer's arguments, as [`PeerSpec::to_args`] spells them.
#[derive(Debug, Args)]
pub struct PeerArgs {
    #[arg(long)]
    pub transport: Transport,
    #[arg(long)]
    pub width: u32,
    #[arg(long)]
    pub height: u32,
    /// iceoryx2 robot namespace, Zenoh key expression or abstract socket name.
    #[arg(long)]
    pub name: String,
    /// Zenoh endpoint of the publisher.
    #[arg(long)]
    pub connect: Option<String>,
    /// eventfd inherited from the publisher.
    #[arg(long)]
    pub fd: Option<i32>,
    /// Give up and report after this many seconds.
    #[arg(long)]
    pub deadline_s: f64,
    /// Pin this process to one CPU.
    #[arg(long)]
    pub pin_cpu: Option<usize>,
}

impl PeerArgs {
    fn spec(self) -> Result<PeerSpec> {
        if !(self.deadline_s.is_finite() && self.deadline_s > 0.0) {
            bail!("--deadline-s must be a positive number of seconds");
        }
        Ok(PeerSpec {
            transport: self.transport,
            width: self.width,
            height: self.height,
            endpoint: PeerEndpoint {
                name: self.name,
                connect: self.connect,
                fd: self.fd,
            },
            deadline: Duration::from_secs_f64(self.deadline_s),
            pin_cpu: self.pin_cpu,
        })
    }
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.command {
        BenchCommand::Ipc(args) => run_ipc(args),
        BenchCommand::IpcPeer(args) => Ok(bench::run_peer(&args.spec()?)?),
    }
}

fn run_ipc(args: IpcArgs) -> Result<()> {
    if !(args.seconds_per_case.is_finite() && (0.05..=600.0).contains(&args.seconds_per_case)) {
        bail!("--seconds-per-case must be between 0.05 and 600");
    }
    if args.frames == 0 {
        bail!("--frames must be at least 1");
    }
    if !(1..=100).contains(&args.rounds) {
        bail!("--rounds must be between 1 and 100");
    }
    let opts = IpcOptions {
        seconds_per_case: args.seconds_per_case,
        frames: args.frames,
        rounds: args.rounds,
        pin_cpus: args.pin_cpus,
        peer: PeerCommand::current_exe(PEER_SUBCOMMAND)?,
    };
    let report = bench::run_ipc(&opts, &|case| eprintln!("bench ipc: {case}"))?;
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{}", report.table());
    }
    let failed: Vec<String> = report
        .results
        .iter()
        .filter_map(|r| {
            let err = r.error.as_ref()?;
            Some(format!("{} {}: {err}", r.transport, r.resolution))
        })
        .collect();
    if !failed.is_empty() {
        bail!("{} case(s) failed: {}", failed.len(), failed.join("; "));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(subcommand)]
        command: BenchCommand,
    }

    /// What the library writes on the peer's command line is what this subcommand reads.
    #[test]
    fn peer_arguments_round_trip_through_the_hidden_subcommand() {
        let specs = [
            PeerSpec {
                transport: Transport::ZenohShm,
                width: 752,
                height: 480,
                endpoint: PeerEndpoint {
                    name: "doorslam/bench/bench1c2/frames".into(),
                    connect: Some("tcp/127.0.0.1:7447".into()),
                    fd: None,
                },
                deadline: Duration::from_secs_f64(3.0 * 0.3 + 90.0),
                pin_cpu: Some(1),
            },
            PeerSpec {
                transport: Transport::EventfdFloor,
                width: 1280,
                height: 720,
                endpoint: PeerEndpoint {
                    name: String::new(),
                    connect: None,
                    fd: Some(5),
                },
                deadline: Duration::from_secs(96),
                pin_cpu: None,
            },
        ];
        for spec in specs {
            let argv = std::iter::once("doorslam".to_string())
                .chain(PEER_SUBCOMMAND[1..].iter().map(|s| s.to_string()))
                .chain(spec.to_args());
            let BenchCommand::IpcPeer(args) = Cli::try_parse_from(argv).unwrap().command else {
                panic!("not the peer subcommand");
            };
            assert_eq!(args.spec().unwrap(), spec);
        }
    }
}
