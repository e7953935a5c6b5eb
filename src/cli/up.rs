//! `doorslam up --config robot.toml`: every service of one robot as child processes, logs
//! prefixed with the service name, stopped cleanly (SIGTERM, then SIGKILL after a grace
//! period) on Ctrl-C. A service that fails is restarted after a delay, like the systemd
//! units do (`Restart=on-failure`, `RestartSec=1`, at most 5 starts in 30 s); past that
//! limit, or with `--restart no`, the whole robot is stopped. On a drone systemd does this
//! job (`deploy/systemd/`); `up` is for the bench, HIL replay and simulation.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};

use crate::config::RobotConfig;

#[derive(Debug, Args)]
pub struct UpArgs {
    /// Robot configuration (TOML); `[up] services` lists what to start.
    #[arg(long)]
    pub config: PathBuf,
    /// Seconds a service gets to stop after SIGTERM before it is killed.
    #[arg(long, default_value_t = 5.0)]
    pub grace_s: f64,
    /// What to do when a service fails (exits non-zero or is killed by a signal).
    #[arg(long, value_enum, default_value_t = Restart::OnFailure)]
    pub restart: Restart,
    /// Seconds between a failure and the restart.
    #[arg(long, default_value_t = 1.0)]
    pub restart_delay_s: f64,
}

/// Restart policy of `doorslam up`, named after systemd's `Restart=`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Restart {
    /// Restart a failed service (at most [`START_LIMIT`] starts in [`START_INTERVAL`]).
    OnFailure,
    /// Stop the whole robot when a service fails.
    No,
}

/// systemd's `StartLimitBurst` and `StartLimitIntervalSec` as in the units.
const START_LIMIT: usize = 5;
const START_INTERVAL: Duration = Duration::from_secs(30);

/// One supervised service.
struct Service {
    name: String,
    child: Child,
    /// When it was started, within the last [`START_INTERVAL`].
    starts: VecDeque<Instant>,
    /// Set after a failure: when to start it again.
    restart_at: Option<Instant>,
    /// Exited successfully (e.g. a replay at the end of its dataset): left alone.
    finished: bool,
}

fn spawn(exe: &Path, name: &str, config: &Path) -> Result<Child> {
    use std::os::unix::process::CommandExt;
    let mut command = Command::new(exe);
    command
        .args(["service", name, "--config"])
        .arg(config)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    // SAFETY: runs in the forked child before exec and only calls prctl(2), which is
    // async-signal-safe. If `up` itself dies (even by SIGKILL) its services get SIGTERM
    // instead of running on, orphaned.
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = command
        .spawn()
        .with_context(|| format!("cannot start service {name}"))?;
    if let Some(out) = child.stdout.take() {
        forward(name.to_string(), out);
    }
    if let Some(err) = child.stderr.take() {
        forward(name.to_string(), err);
    }
    eprintln!("[up] started {name} (pid {})", child.id());
    Ok(child)
}

fn forward(name: String, stream: impl std::io::Read + Send + 'static) {
    std::thread::spawn(move || {
        for line in BufReader::new(stream).lines().map_while(Result::ok) {
            eprintln!("[{name}] {line}");
        }
    });
}

/// Stops the services in the reverse of their start order, as systemd does: producers
/// (camera, front-end) stop before the consumers they feed, so a consumer drains what was
/// sent before it stops and nothing in flight is lost. Each gets SIGTERM, then SIGKILL if
/// it is still running after `grace`.
fn terminate(services: &mut [Service], grace: Duration) {
    // Finished services and those waiting for a restart have already been reaped.
    let running = |s: &Service| !s.finished && s.restart_at.is_none();
    for Service { name, child, .. } in services.iter_mut().rev().filter(|s| running(s)) {
        // SAFETY: kill(2) on our own child's pid; no memory is involved.
        unsafe {
            libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
        }
        let deadline = Instant::now() + grace;
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
    let grace = super::seconds("--grace-s", args.grace_s, super::MAX_WAIT_S)?;
    let restart_delay =
        super::seconds("--restart-delay-s", args.restart_delay_s, super::MAX_WAIT_S)?;
    let exe = std::env::current_exe().context("locating the doorslam binary")?;
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst))
        .context("installing the Ctrl-C handler")?;

    let mut services: Vec<Service> = Vec::new();
    for name in &config.up_services() {
        match spawn(&exe, name, &args.config) {
            Ok(child) => services.push(Service {
                name: name.clone(),
                child,
                starts: VecDeque::from([Instant::now()]),
                restart_at: None,
                finished: false,
            }),
            Err(e) => {
                terminate(&mut services, grace);
                return Err(e);
            }
        }
    }

    let mut failed: Option<String> = None;
    while !stop.load(Ordering::SeqCst) && failed.is_none() {
        for s in services.iter_mut().filter(|s| !s.finished) {
            if let Some(at) = s.restart_at {
                if Instant::now() >= at {
                    match spawn(&exe, &s.name, &args.config) {
                        Ok(child) => {
                            s.child = child;
                            s.starts.push_back(Instant::now());
                            s.restart_at = None;
                        }
                        Err(e) => {
                            eprintln!("[up] {e:#}: stopping the robot");
                            failed = Some(format!("{e:#}"));
                            break;
                        }
                    }
                }
                continue;
            }
            let Ok(Some(status)) = s.child.try_wait() else {
                continue;
            };
            if status.success() {
                // E.g. a replay that reached the end of its dataset.
                eprintln!("[up] {} finished ({status})", s.name);
                s.finished = true;
                continue;
            }
            while s
                .starts
                .front()
                .is_some_and(|t| t.elapsed() > START_INTERVAL)
            {
                s.starts.pop_front();
            }
            if args.restart == Restart::No {
                eprintln!("[up] {} failed ({status}): stopping the robot", s.name);
                failed = Some(format!("service {} failed ({status})", s.name));
            } else if s.starts.len() >= START_LIMIT {
                eprintln!(
                    "[up] {} failed ({status}) after {} starts within {START_INTERVAL:?}: giving up, stopping the robot",
                    s.name,
                    s.starts.len()
                );
                failed = Some(format!(
                    "service {} failed {} times within {START_INTERVAL:?} ({status})",
                    s.name,
                    s.starts.len()
                ));
            } else {
                eprintln!(
                    "[up] {} failed ({status}): restarting in {restart_delay:?}",
                    s.name
                );
                s.restart_at = Some(Instant::now() + restart_delay);
            }
        }
        if services.iter().all(|s| s.finished) {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!("[up] stopping {} services", services.len());
    terminate(&mut services, grace);
    // After the services stopped: their files are final, and the record never runs
    // beside the team link.
    if let Some(path) = &config.record.mcap {
        let dir = &config.backend.state_dir;
        match doorslam_ros2::record::record(dir, Some(path)) {
            Ok(s) => eprintln!(
                "[up] recorded {} messages of {} into {}",
                s.messages.values().sum::<u64>(),
                dir.display(),
                path.display()
            ),
            Err(e) => {
                let e = format!("[record] mcap = {}: {e}", path.display());
                eprintln!("[up] {e}");
                failed.get_or_insert(e);
            }
        }
    }
    match failed {
        Some(why) => bail!(why),
        None => Ok(()),
    }
}
