//! The wake-up primitive iceoryx2's `ipc` events are built on, bare: a Unix datagram
//! socket pair shared by the two processes, no payload. The publisher sends one 9-byte
//! datagram (stamp + phase); the peer sleeps in poll() and reads it. Next to the eventfd
//! floor it separates what the kernel primitive costs from what iceoryx2 adds on top.

use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::time::Duration;

use super::{
    inherited_fd, nonblocking_sent, wait_readable, Delivered, PeerEndpoint, Phase, Publish, Receive,
};
use crate::error::{BenchError, Result};
use crate::measure::{mono_ns, Mapping};

pub struct DgramPublisher {
    ours: OwnedFd,
    // The peer's end stays open here too: the child inherits it across exec.
    _theirs: OwnedFd,
}

impl DgramPublisher {
    pub fn open() -> Result<(Box<dyn Publish>, PeerEndpoint)> {
        let mut fds = [0; 2];
        // No SOCK_CLOEXEC: the peer process inherits its end across exec. Non-blocking
        // sends: a full socket means the peer has not read for a while.
        // SAFETY: socketpair writes two descriptors into `fds`; the result is checked.
        let rc = unsafe {
            libc::socketpair(
                libc::AF_UNIX,
                libc::SOCK_DGRAM | libc::SOCK_NONBLOCK,
                0,
                fds.as_mut_ptr(),
            )
        };
        if rc != 0 {
            return Err(BenchError::io("socketpair(AF_UNIX, SOCK_DGRAM)")(
                io::Error::last_os_error(),
            ));
        }
        // SAFETY: two fresh descriptors nothing else owns.
        let (ours, theirs) =
            unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) };
        let endpoint = PeerEndpoint {
            fd: Some(fds[1]),
            ..PeerEndpoint::default()
        };
        Ok((
            Box::new(Self {
                ours,
                _theirs: theirs,
            }),
            endpoint,
        ))
    }
}

impl Publish for DgramPublisher {
    fn publish(&mut self, phase: Phase, _seq: u64, _left: &[u8], _right: &[u8]) -> Result<bool> {
        let mut msg = [0u8; 9];
        msg[..8].copy_from_slice(&mono_ns().to_le_bytes());
        msg[8] = phase as u8;
        // SAFETY: sends 9 bytes from a live buffer on a descriptor we own.
        let n = unsafe { libc::send(self.ours.as_raw_fd(), msg.as_ptr().cast(), msg.len(), 0) };
        nonblocking_sent(n, msg.len(), "datagram send")
    }

    fn payload_mapping(&self) -> Option<Mapping> {
        None
    }
}

pub struct DgramReceiver {
    fd: OwnedFd,
}

impl DgramReceiver {
    pub fn open(endpoint: &PeerEndpoint) -> Result<Self> {
        Ok(Self {
            fd: inherited_fd(endpoint, "datagram floor")?,
        })
    }
}

impl Receive for DgramReceiver {
    fn receive(
        &mut self,
        timeout: Duration,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()> {
        if !wait_readable(self.fd.as_raw_fd(), timeout) {
            return Ok(());
        }
        let mut msg = [0u8; 9];
        loop {
            // SAFETY: receives at most 9 bytes into a live buffer.
            let n = unsafe {
                libc::recv(
                    self.fd.as_raw_fd(),
                    msg.as_mut_ptr().cast(),
                    msg.len(),
                    libc::MSG_DONTWAIT,
                )
            };
            let recv_ns = mono_ns();
            if n != msg.len() as isize {
                return Ok(());
            }
            let stamp = u64::from_le_bytes(msg[..8].try_into().expect("8 bytes"));
            let Some(phase) = Phase::from_u32(msg[8] as u32) else {
                continue;
            };
            on_frame(&Delivered {
                phase,
                stamp_ns: Some(stamp),
                recv_ns,
                left: &[],
                right: &[],
                shm_claim: None,
            });
        }
    }
}
