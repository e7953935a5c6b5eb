//! `doorslam up --config robot.toml`: every service of one robot as child processes, logs
//! prefixed with the service name, stopped cleanly (SIGTERM, then SIGKILL after a grace
//! period) on Ctrl-C or when a service fails. On a drone systemd does this job
//! (`deploy/systemd/`); `up` is for the bench, HIL replay and simulation.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::config::RobotConfig;

#[derive(Debug, Args)]
pub struct UpArgs {
    /// Robot configuration (TOML); `[up] services` lists what to start.
    #[arg(long)]
    pub config: PathBuf,
    /// Seconds a service gets to stop after SIGTERM before it is killed.
    #[arg(long, default_value_t = 5.0)]
    pub grace_s: f64,
}

fn forward(name: String, stream: impl std::io::Read + Send + 'static) {
    std::thread::spawn(move || {
        for line in BufReader::new(stream).lines().map_while(Result::ok) {
            eprintln!("[{name}] {line}");
        }
    });
}

fn terminate(children: &mut [(String, Child)], grace: Duration) {
    for (_, child) in children.iter() {
        // SAFETY: kill(2) on our own child's pid; no memory is involved.
        unsafe {
            libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
        }
    }
    let deadline = Instant::now() + grace;
    for (name, child) in children.iter_mut() {
        loop {
            match child.try_wait() {
                Ok(Some(status)) => {
                    eprintln!("[up] {name} stopped ({status})");
                    break;
                }
                Ok(None) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(20))
                }
                _ => {
                    eprintln!("[up] {name} did not stop within {grace:?}: killing it");
                    let _ = child.kill();
                    let _ = child.wait();
                    break;
                }
            }
        }
    }
}

pub fn run(args: UpArgs) -> Result<()> {
    let config = RobotConfig::load(&args.config)?;
    anyhow::ensure!(
        args.grace_s.is_finite() && args.grace_s >= 0.0,
        "--grace-s must be >= 0"
    );
    let exe = std::env::current_exe().context("locating the doorslam binary")?;
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst))
        .context("installing the Ctrl-C handler")?;

    let mut children: Vec<(String, Child)> = Vec::new();
    for name in &config.up.services {
        let spawned = Command::new(&exe)
            .args(["service", name, "--config"])
            .arg(&args.config)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn();
        let mut child = match spawned {
            Ok(c) => c,
            Err(e) => {
                terminate(&mut children, Duration::from_secs_f64(args.grace_s));
                bail!("cannot start service {name}: {e}");
            }
        };
        if let Some(out) = child.stdout.take() {
            forward(name.clone(), out);
        }
        if let Some(err) = child.stderr.take() {
            forward(name.clone(), err);
        }
        eprintln!("[up] started {name} (pid {})", child.id());
        children.push((name.clone(), child));
    }

    let mut failed: Option<String> = None;
    let mut finished = vec![false; children.len()];
    while !stop.load(Ordering::SeqCst) && failed.is_none() {
        for (k, (name, child)) in children.iter_mut().enumerate() {
            if finished[k] {
                continue;
            }
            if let Ok(Some(status)) = child.try_wait() {
                finished[k] = true;
                if status.success() {
                    // E.g. a replay that reached the end of its dataset.
                    eprintln!("[up] {name} finished ({status})");
                } else {
                    eprintln!("[up] {name} failed ({status}): stopping the robot");
                    failed = Some(format!("service {name} failed ({status})"));
                }
            }
        }
        if finished.iter().all(|f| *f) {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!("[up] stopping {} services", children.len());
    terminate(&mut children, Duration::from_secs_f64(args.grace_s));
    match failed {
        Some(why) => bail!(why),
        None => Ok(()),
    }
}
