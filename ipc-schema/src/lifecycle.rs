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
