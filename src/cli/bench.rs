//! `doorslam bench ipc [--json]`: the on-robot transports measured side by side, with
//! the subscriber in a second process (this binary again, as the hidden `ipc-peer`).

use std::time::Duration;

use anyhow::{bail, Result};
use clap::{Args, Subcommand};

use crate::bench::{self, IpcOptions, PeerEndpoint, PeerSpec, Transport};

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
}

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
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.command {
        BenchCommand::Ipc(args) => run_ipc(args),
        BenchCommand::IpcPeer(args) => {
            if !(args.deadline_s.is_finite() && args.deadline_s > 0.0) {
                bail!("--deadline-s must be a positive number of seconds");
            }
            bench::run_peer(&PeerSpec {
                transport: args.transport,
                width: args.width,
                height: args.height,
                endpoint: PeerEndpoint {
                    name: args.name,
                    connect: args.connect,
                    fd: args.fd,
                },
                deadline: Duration::from_secs_f64(args.deadline_s),
            })
        }
    }
}

fn run_ipc(args: IpcArgs) -> Result<()> {
    if !(args.seconds_per_case.is_finite() && (0.05..=600.0).contains(&args.seconds_per_case)) {
        bail!("--seconds-per-case must be between 0.05 and 600");
    }
    if args.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let opts = IpcOptions {
        seconds_per_case: args.seconds_per_case,
        frames: args.frames,
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
