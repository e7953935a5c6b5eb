//! The peer process as seen from the publisher: spawned from the caller's binary
//! ([`PeerCommand`]), read line by line with timeouts, and always killed and reaped, on
//! every path.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, TryRecvError};
use std::time::{Duration, Instant};

use crate::error::{BenchError, Result};
use crate::PeerCommand;

fn failed(what: impl Into<String>) -> BenchError {
    BenchError::Peer(what.into())
}

/// A running peer. Dropping it kills the process if it is still running and waits for
/// it, so no error path leaves a subscriber behind.
pub struct PeerProcess {
    child: Child,
    lines: Receiver<String>,
}

impl PeerProcess {
    /// Starts `<command> <args>` with stdout piped to us and stderr shared.
    pub fn spawn(command: &PeerCommand, args: &[String]) -> Result<Self> {
        let exe = &command.program;
        let mut child = Command::new(exe)
            .args(&command.args)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(BenchError::io(format!(
                "start the peer process {}",
                exe.display()
            )))?;
        let Some(stdout) = child.stdout.take() else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(failed("peer process has no stdout"));
        };
        let (tx, lines) = mpsc::channel();
        // A reader thread turns the blocking pipe into a channel we can wait on with a
        // timeout; it ends by itself when the peer closes its stdout.
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Ok(Self { child, lines })
    }

    fn exited(&mut self) -> String {
        match self.child.try_wait() {
            Ok(Some(status)) => format!("peer process exited ({status})"),
            _ => "peer process closed its output".to_string(),
        }
    }

    /// Waits up to `timeout` for a line starting with `prefix`; returns the rest of it.
    /// Other lines are skipped (only the protocol lines matter).
    pub fn expect(&mut self, prefix: &str, timeout: Duration) -> Result<String> {
        match self.wait_for(prefix, timeout)? {
            Some(rest) => Ok(rest),
            None => Err(failed(format!(
                "peer process did not say {prefix:?} within {timeout:?}"
            ))),
        }
    }

    /// As [`Self::expect`], with a timeout that is not an error (`None`); the peer
    /// having exited still is.
    pub fn wait_for(&mut self, prefix: &str, timeout: Duration) -> Result<Option<String>> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => {
                    if let Some(rest) = line.strip_prefix(prefix) {
                        return Ok(Some(rest.trim().to_string()));
                    }
                }
                Err(RecvTimeoutError::Timeout) => return Ok(None),
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(failed(format!(
                        "{} before saying {prefix:?}",
                        self.exited()
                    )))
                }
            }
        }
    }

    /// Whether a line starting with `prefix` has arrived (does not wait).
    pub fn said(&mut self, prefix: &str) -> Result<bool> {
        loop {
            match self.lines.try_recv() {
                Ok(line) if line.starts_with(prefix) => return Ok(true),
                Ok(_) => {}
                Err(TryRecvError::Empty) => return Ok(false),
                Err(TryRecvError::Disconnected) => {
                    return Err(failed(format!(
                        "{} before saying {prefix:?}",
                        self.exited()
                    )))
                }
            }
        }
    }

    /// Waits up to `timeout` for a clean exit, then kills.
    pub fn finish(mut self, timeout: Duration) -> Result<()> {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            let exited = self
                .child
                .try_wait()
                .map_err(BenchError::io("wait for the peer process"))?;
            if let Some(status) = exited {
                if status.success() {
                    return Ok(());
                }
                return Err(failed(format!("peer process failed ({status})")));
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        Err(failed(format!(
            "peer process did not exit within {timeout:?}; killed"
        )))
    }
}

impl Drop for PeerProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
        }
        let _ = self.child.wait();
    }
}
