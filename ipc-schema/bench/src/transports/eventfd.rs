//! The wake-up floor: one eventfd shared by the two processes, no payload. The publisher
//! adds `stamp << 3 | phase` to the counter; the peer sleeps in poll() and reads it back.
//! Nothing an event-driven transport does can wake a sleeping process faster than this.

use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::time::Duration;

use super::{
    inherited_fd, nonblocking_sent, wait_readable, Delivered, PeerEndpoint, Phase, Publish, Receive,
};
use crate::error::{BenchError, Result};
use crate::measure::{mono_ns, Mapping};

const PHASE_BITS: u32 = 3;

pub struct EventfdPublisher {
    fd: OwnedFd,
}

impl EventfdPublisher {
    pub fn open() -> Result<(Box<dyn Publish>, PeerEndpoint)> {
        // No EFD_CLOEXEC: the peer process inherits the descriptor across exec.
        // SAFETY: plain syscall; the result is checked before use.
        let raw = unsafe { libc::eventfd(0, libc::EFD_NONBLOCK) };
        if raw < 0 {
            return Err(BenchError::io("eventfd")(io::Error::last_os_error()));
        }
        // SAFETY: `raw` is a fresh descriptor that nothing else owns.
        let fd = unsafe { OwnedFd::from_raw_fd(raw) };
        let endpoint = PeerEndpoint {
            fd: Some(raw),
            ..PeerEndpoint::default()
        };
        Ok((Box::new(Self { fd }), endpoint))
    }
}

impl Publish for EventfdPublisher {
    fn publish(&mut self, phase: Phase, _seq: u64, _left: &[u8], _right: &[u8]) -> Result<bool> {
        let value = (mono_ns() << PHASE_BITS) | phase as u64;
        // SAFETY: writes 8 bytes from a live u64 to a descriptor we own.
        let n = unsafe {
            libc::write(
                self.fd.as_raw_fd(),
                (&value as *const u64).cast(),
                std::mem::size_of::<u64>(),
            )
        };
        // No room: the counter is saturated, the peer has not read for a while.
        nonblocking_sent(n, 8, "eventfd write")
    }

    fn payload_mapping(&self) -> Option<Mapping> {
        None
    }
}

pub struct EventfdReceiver {
    fd: OwnedFd,
    /// Phase of the last readable value: merged wake-ups are counted in it.
    last_phase: Phase,
}

impl EventfdReceiver {
    pub fn open(endpoint: &PeerEndpoint) -> Result<Self> {
        Ok(Self {
            fd: inherited_fd(endpoint, "eventfd floor")?,
            last_phase: Phase::Warmup,
        })
    }
}

impl Receive for EventfdReceiver {
    fn receive(
        &mut self,
        timeout: Duration,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()> {
        if !wait_readable(self.fd.as_raw_fd(), timeout) {
            return Ok(());
        }
        let mut value = 0u64;
        // SAFETY: reads 8 bytes into a live u64.
        let n = unsafe {
            libc::read(
                self.fd.as_raw_fd(),
                (&mut value as *mut u64).cast(),
                std::mem::size_of::<u64>(),
            )
        };
        let recv_ns = mono_ns();
        if n != 8 {
            return Ok(());
        }
        let stamp = value >> PHASE_BITS;
        let phase = Phase::from_u32((value & ((1 << PHASE_BITS) - 1)) as u32);
        // Several writes merged into one read sum their values: the sum decodes to a
        // stamp in the future (stamps are ~uptime), which is how a merge is recognized.
        let (phase, stamp_ns) = match phase {
            Some(p) if stamp <= recv_ns && recv_ns - stamp < 10_000_000_000 => (p, Some(stamp)),
            _ => (self.last_phase, None),
        };
        self.last_phase = phase;
        on_frame(&Delivered {
            phase,
            stamp_ns,
            recv_ns,
            left: &[],
            right: &[],
            shm_claim: None,
        });
        Ok(())
    }
}
