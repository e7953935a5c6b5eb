//! One robot of the demo: its `doorslam up` process (in its network namespace), its files,
//! and what its status files say.

use std::fs::OpenOptions;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::flights::robot_name;
use crate::netns::Net;

use super::cpu::CpuMeter;
use super::{io_err, read_json, DemoError};

/// Where a robot is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RobotState {
    Created,
    Running,
    Killed,
    Stopped,
}

/// What a robot's status files say now.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotSnapshot {
    pub name: char,
    pub state: RobotState,
    /// Frames the front-end processed and the frames it lost (its `frontend.json`).
    pub frames: Option<u64>,
    pub lost: Option<u64>,
    pub keyframes: u64,
    /// Meetings with any peer (the team link's sessions).
    pub rendezvous: u64,
    /// Meetings per peer.
    pub meetings: std::collections::BTreeMap<String, u64>,
    /// Peers the team link sees now.
    pub present: Vec<String>,
    /// Inter-robot closures the back-end took, and those PCM left out.
    pub closures: u64,
    pub rejected: u64,
    /// Distributed back-end steps that solved something.
    pub rounds: u64,
    pub converged: bool,
    /// The team solve (the solver's round) behind the back-end's estimate, and per robot
    /// it hands estimates down to, the round it handed to the team link for that robot
    /// (`backend.json` `team.round`, `team.rounds_handed_down`).
    pub round: Option<u64>,
    pub rounds_handed_down: std::collections::BTreeMap<String, u64>,
    /// Messages the team link sent to a present peer and the peer has not acknowledged
    /// yet (`status.json`, summed over the peers present): what is still on the radio.
    pub unacknowledged: u64,
    /// The robot whose frame the distributed back-end puts this robot in (its own until
    /// it merges with a team; empty before the back-end reports).
    pub anchor: String,
    /// Bytes this robot's team link sent (its ledger, payload).
    pub bytes_sent: u64,
}

/// A robot's process and files.
pub struct Robot {
    index: usize,
    pub dir: PathBuf,
    pub config: PathBuf,
    pub log: PathBuf,
    child: Option<Child>,
    pub state: RobotState,
    pub starts: u32,
}

impl Robot {
    /// Writes the robot's folder and configuration.
    pub fn create(out: &Path, index: usize, robot_toml: &str) -> Result<Robot, DemoError> {
        let dir = out.join(robot_name(index).to_string());
        std::fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        let config = dir.join("robot.toml");
        std::fs::write(&config, robot_toml).map_err(io_err(&config))?;
        Ok(Robot {
            index,
            log: dir.join("robot.log"),
            dir,
            config,
            child: None,
            state: RobotState::Created,
            starts: 0,
        })
    }

    pub fn name(&self) -> char {
        robot_name(self.index)
    }

    /// The process group of the running incarnation (`up`'s pid: it leads its group).
    pub fn pgid(&self) -> Option<i32> {
        self.child.as_ref().map(|c| c.id() as i32)
    }

    /// Starts `doorslam up` (in the robot's namespace when there is a network), in a
    /// process group of its own so that a kill reaches every service.
    pub fn start(&mut self, exe: &Path, net: Option<&Net>) -> Result<(), DemoError> {
        let log = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .map_err(io_err(&self.log))?;
        let err = log.try_clone().map_err(io_err(&self.log))?;
        let mut command = match net {
            Some(net) => net.command(self.index, exe)?,
            None => Command::new(exe),
        };
        command
            .args(["up", "--config"])
            .arg(&self.config)
            .args(["--restart", "on-failure"])
            .env(
                "RUST_LOG",
                std::env::var("RUST_LOG").unwrap_or_else(|_| "info,zenoh=warn".into()),
            )
            // An iceoryx2 domain of this demo's own: robots `a`, `b`... of two demos (or
            // of a demo and a `doorslam up` on the same machine) never share a service.
            .env(
                doorslam_ipc::service::DOMAIN_ENV,
                format!("demo{}", std::process::id()),
            )
            .stdin(Stdio::null())
            .stdout(log)
            .stderr(err)
            .process_group(0);
        let child = command.spawn().map_err(|e| DemoError::Robot {
            robot: self.name(),
            reason: format!("cannot start {}: {e}", exe.display()),
            log: self.log.clone(),
        })?;
        self.child = Some(child);
        self.state = RobotState::Running;
        self.starts += 1;
        Ok(())
    }

    /// SIGKILL to every process of the robot (its process group): a crash of the whole
    /// computer, no service gets to write anything.
    pub fn kill(&mut self) -> Result<(), DemoError> {
        if let Some(mut child) = self.child.take() {
            let pgid = child.id() as i32;
            // SAFETY: signals a process group we created; no memory is involved.
            unsafe { libc::kill(-pgid, libc::SIGKILL) };
            let _ = child.wait();
        }
        self.state = RobotState::Killed;
        Ok(())
    }

    /// A robot whose `up` exited while it should run: `up` stops only when a service
    /// keeps failing (or cannot start at all), so the demo stops and names it.
    pub fn check_alive(&mut self) -> Result<(), DemoError> {
        if self.state != RobotState::Running {
            return Ok(());
        }
        if let Some(child) = self.child.as_mut() {
            if let Ok(Some(status)) = child.try_wait() {
                self.state = RobotState::Stopped;
                let tail = std::fs::read_to_string(&self.log)
                    .map(|t| {
                        let lines: Vec<&str> = t.lines().rev().take(12).collect();
                        lines.into_iter().rev().collect::<Vec<_>>().join("\n")
                    })
                    .unwrap_or_default();
                return Err(DemoError::Robot {
                    robot: self.name(),
                    reason: format!(
                        "its services stopped ({status}); the last lines of its log:\n{tail}"
                    ),
                    log: self.log.clone(),
                });
            }
        }
        Ok(())
    }

    /// SIGTERM to `up`, which stops the services in reverse start order (each drains its
    /// queues and writes its files); SIGKILL to the group after `grace`. Once `up` has
    /// exited, and before it is reaped, `meter` reads its exact CPU total.
    pub fn stop(&mut self, meter: &mut CpuMeter) -> Result<(), DemoError> {
        let grace = Duration::from_secs(20);
        if let Some(mut child) = self.child.take() {
            let pid = child.id() as i32;
            // SAFETY: signals our own child process.
            unsafe { libc::kill(pid, libc::SIGTERM) };
            let deadline = Instant::now() + grace;
            loop {
                if exited_unreaped(pid) {
                    meter.exited(self.index, pid);
                    let _ = child.wait();
                    break;
                }
                match child.try_wait() {
                    Ok(Some(_)) | Err(_) => break,
                    Ok(None) if Instant::now() >= deadline => {
                        // SAFETY: as in `kill`.
                        unsafe { libc::kill(-pid, libc::SIGKILL) };
                        let _ = child.wait();
                        break;
                    }
                    Ok(None) => std::thread::sleep(Duration::from_millis(100)),
                }
            }
        }
        self.state = RobotState::Stopped;
        Ok(())
    }

    /// Reads the robot's status files (absent or half-written ones count as nothing yet).
    pub fn snapshot(&self) -> RobotSnapshot {
        let backend = read_json(&self.dir.join("backend.json"));
        let team = read_json(&self.dir.join("status.json"));
        let frontend = read_json(&self.dir.join("frontend.json"));
        let u = |v: Option<&serde_json::Value>| v.and_then(|x| x.as_u64()).unwrap_or(0);
        let b = backend.as_ref();
        let meetings: std::collections::BTreeMap<String, u64> = team
            .as_ref()
            .and_then(|t| t.get("peers"))
            .and_then(|p| p.as_object())
            .map(|peers| {
                peers
                    .iter()
                    .map(|(name, p)| (name.clone(), u(p.pointer("/stats/meetings"))))
                    .collect()
            })
            .unwrap_or_default();
        let rendezvous = meetings.values().sum();
        let present: Vec<String> = team
            .as_ref()
            .and_then(|t| t.get("present"))
            .and_then(|p| p.as_array())
            .map(|p| {
                p.iter()
                    .filter_map(|x| x.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default();
        let unacknowledged = team
            .as_ref()
            .and_then(|t| t.get("peers"))
            .and_then(|p| p.as_object())
            .map_or(0, |peers| {
                peers
                    .iter()
                    .filter(|(name, _)| present.contains(name))
                    .map(|(_, p)| u(p.get("unacknowledged_messages")))
                    .sum()
            });
        RobotSnapshot {
            name: self.name(),
            state: self.state,
            frames: frontend
                .as_ref()
                .and_then(|f| f.get("frames"))
                .and_then(|x| x.as_u64()),
            lost: frontend
                .as_ref()
                .and_then(|f| f.get("lost"))
                .and_then(|x| x.as_u64()),
            keyframes: u(b.and_then(|b| b.get("keyframes"))),
            rendezvous,
            meetings,
            present,
            closures: u(b.and_then(|b| b.get("closures"))),
            rejected: b
                .and_then(|b| b.pointer("/team/rejected_closures"))
                .and_then(|r| r.as_array())
                .map_or(0, |r| r.len() as u64),
            rounds: u(b.and_then(|b| b.pointer("/team/updates"))),
            converged: b
                .and_then(|b| b.pointer("/team/converged"))
                .and_then(|c| c.as_bool())
                .unwrap_or(false),
            round: b
                .and_then(|b| b.pointer("/team/round"))
                .and_then(|r| r.as_u64()),
            rounds_handed_down: b
                .and_then(|b| b.pointer("/team/rounds_handed_down"))
                .and_then(|r| r.as_object())
                .map(|m| {
                    m.iter()
                        .filter_map(|(r, n)| Some((r.clone(), n.as_u64()?)))
                        .collect()
                })
                .unwrap_or_default(),
            unacknowledged,
            anchor: b
                .and_then(|b| b.pointer("/team/anchor"))
                .and_then(|a| a.as_str())
                .unwrap_or_default()
                .to_string(),
            bytes_sent: ledger_bytes_sent(&self.dir.join("ledger.json")),
        }
    }
}

/// Payload bytes a ledger counts as sent (first sends and resends).
pub fn ledger_bytes_sent(path: &Path) -> u64 {
    doorslam_team::ledger::LedgerFile::read(path).map_or(0, |l| {
        l.traffic
            .iter()
            .filter(|t| t.direction == doorslam_team::ledger::Direction::Sent)
            .map(|t| t.counts.payload_bytes)
            .sum()
    })
}

/// Whether our child `pid` has exited, leaving it unreaped (its zombie's `/proc` entry
/// still holds its CPU times and its waited-for children's).
fn exited_unreaped(pid: i32) -> bool {
    // SAFETY: zeroed is a valid siginfo_t; waitid only writes into it.
    let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
    // SAFETY: waits for our own child without reaping it (WNOWAIT) and without blocking.
    let rc = unsafe {
        libc::waitid(
            libc::P_PID,
            pid as libc::id_t,
            &mut info,
            libc::WEXITED | libc::WNOWAIT | libc::WNOHANG,
        )
    };
    // SAFETY: si_pid is valid to read for a filled WEXITED siginfo; 0 when none exited.
    rc == 0 && unsafe { info.si_pid() } == pid
}
