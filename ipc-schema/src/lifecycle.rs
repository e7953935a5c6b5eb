//! Process lifecycle of a service: systemd readiness and watchdog (`sd_notify`), and
//! termination requests (SIGTERM/SIGINT, caught by iceoryx2's node).

use core::time::Duration;
use std::os::unix::net::UnixDatagram;
use std::time::Instant;

use iceoryx2::prelude::*;

/// Sends a state string (`READY=1`, `WATCHDOG=1`, `STATUS=...`) to systemd if the process
/// runs under a `Type=notify` unit (`$NOTIFY_SOCKET` set). Returns whether it was sent.
pub fn sd_notify(state: &str) -> bool {
    let Some(socket) = std::env::var_os("NOTIFY_SOCKET") else {
        return false;
    };
    let Ok(sock) = UnixDatagram::unbound() else {
        return false;
    };
    let path = socket.to_string_lossy().into_owned();
    let sent = if let Some(abstract_name) = path.strip_prefix('@') {
        use std::os::linux::net::SocketAddrExt;
        std::os::unix::net::SocketAddr::from_abstract_name(abstract_name.as_bytes())
            .and_then(|addr| sock.send_to_addr(state.as_bytes(), &addr))
    } else {
        sock.send_to(state.as_bytes(), &path)
    };
    sent.is_ok()
}

/// Half the systemd watchdog period (`$WATCHDOG_USEC`), the interval to ping at.
pub fn watchdog_interval() -> Option<Duration> {
    let usec: u64 = std::env::var("WATCHDOG_USEC").ok()?.parse().ok()?;
    (usec > 0).then(|| Duration::from_micros(usec / 2))
}

/// Readiness, watchdog pings and shutdown detection for a service's main loop.
pub struct Lifecycle {
    watchdog: Option<Duration>,
    last_ping: Instant,
}

impl Default for Lifecycle {
    fn default() -> Self {
        Self::new()
    }
}

impl Lifecycle {
    pub fn new() -> Self {
        Self {
            watchdog: watchdog_interval(),
            last_ping: Instant::now(),
        }
    }

    /// Tells systemd the service is up (after its channels are open).
    pub fn ready(&self, status: &str) {
        sd_notify(&format!("READY=1\nSTATUS={status}"));
    }

    /// Call once per loop iteration: pings the watchdog when due and returns `false` once a
    /// termination was requested (the loop should then finish cleanly).
    pub fn keep_going(&mut self, node: &Node<ipc::Service>) -> bool {
        if let Some(period) = self.watchdog {
            if self.last_ping.elapsed() >= period {
                sd_notify("WATCHDOG=1");
                self.last_ping = Instant::now();
            }
        }
        node.wait(Duration::ZERO).is_ok()
    }

    /// Tells systemd the service is stopping.
    pub fn stopping(&self) {
        sd_notify("STOPPING=1");
    }
}

/// Why a start counter could not be read or written.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {reason}")]
pub struct EpochError {
    pub path: std::path::PathBuf,
    pub reason: String,
}

/// Reads the start counter `<dir>/<name>`, adds one and writes it back atomically
/// (temporary file + rename): a service's epoch, which every message it sends carries so
/// that peers can tell a restarted sender (with fresh sequences) from stale messages.
/// A missing file counts as 0; anything else than a number is an error naming the file.
pub fn next_epoch(dir: &std::path::Path, name: &str) -> Result<u64, EpochError> {
    let path = dir.join(name);
    let fail = |reason: String| EpochError {
        path: path.clone(),
        reason,
    };
    std::fs::create_dir_all(dir).map_err(|e| fail(format!("cannot create the folder: {e}")))?;
    let previous = match std::fs::read_to_string(&path) {
        Ok(text) => text
            .trim()
            .parse::<u64>()
            .map_err(|e| fail(format!("not an epoch number: {e}")))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => 0,
        Err(e) => return Err(fail(e.to_string())),
    };
    // A counter at the top of the range is a corrupted file, not a restart count: refused
    // (never wrapped to 0, which every peer would take for a stale replay). u64::MAX itself
    // is never an epoch: a team-link Hello names the peer's epoch as epoch + 1.
    let epoch = previous
        .checked_add(1)
        .filter(|e| *e < u64::MAX)
        .ok_or_else(|| {
            fail(format!(
                "epoch {previous} cannot be incremented: remove the file to start at 1"
            ))
        })?;
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, format!("{epoch}\n")).map_err(|e| fail(e.to_string()))?;
    std::fs::rename(&tmp, &path).map_err(|e| fail(e.to_string()))?;
    Ok(epoch)
}
