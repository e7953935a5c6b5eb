//! The transports under test, each as a publisher half (in the benchmarking process) and
//! a receiver half (in the re-executed peer process).
//!
//! Every transport stamps CLOCK_MONOTONIC right before its send call and the receiver
//! stamps it again as soon as the whole pair is readable; the difference is the latency.

mod dgram;
mod eventfd;
mod iceoryx2;
mod unix_socket;
mod zenoh_shm;

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::measure::Mapping;
use crate::BenchError;

/// What the peer should do with a frame. The publisher marks every frame with the
/// phase it belongs to, so the peer needs no side channel to know where a phase starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Connection set-up: discovery, shared-memory probing, first-touch page faults.
    Warmup = 0,
    /// Paced frames with the receiver idle in between: latency.
    Latency = 1,
    /// Frames as fast as the transport accepts: throughput.
    Throughput = 2,
    /// 30 Hz frames: CPU cost at the camera rate.
    Paced = 3,
    /// No payload: the peer reports and exits.
    End = 4,
}

impl Phase {
    pub fn from_u32(v: u32) -> Option<Self> {
        Some(match v {
            0 => Phase::Warmup,
            1 => Phase::Latency,
            2 => Phase::Throughput,
            3 => Phase::Paced,
            4 => Phase::End,
            _ => return None,
        })
    }
}

/// The transports, in the order a run measures them. Spelled by [`Transport::name`] in
/// reports, in JSON (serde) and on the peer's command line ([`std::str::FromStr`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Transport {
    /// iceoryx2 pub-sub, subscriber spinning on `receive()`.
    #[serde(rename = "iceoryx2_poll")]
    Iceoryx2Poll,
    /// iceoryx2 pub-sub plus an iceoryx2 event, subscriber blocked on the listener.
    #[serde(rename = "iceoryx2_event")]
    Iceoryx2Event,
    /// eventfd wake-up between the two processes, no payload: the floor for the above.
    #[serde(rename = "eventfd_floor")]
    EventfdFloor,
    /// Unix datagram wake-up, no payload: the primitive iceoryx2's ipc events use.
    #[serde(rename = "unix_dgram_floor")]
    UnixDgramFloor,
    /// Zenoh peer sessions over tcp/127.0.0.1 with the payload in a Zenoh SHM buffer.
    #[serde(rename = "zenoh_shm")]
    ZenohShm,
    /// A Unix domain stream socket carrying the same bytes.
    #[serde(rename = "unix_socket")]
    UnixSocket,
}

impl Transport {
    pub const ALL: [Transport; 6] = [
        Transport::Iceoryx2Poll,
        Transport::Iceoryx2Event,
        Transport::EventfdFloor,
        Transport::UnixDgramFloor,
        Transport::ZenohShm,
        Transport::UnixSocket,
    ];

    /// The name used in reports (and on the peer's command line).
    pub fn name(self) -> &'static str {
        match self {
            Transport::Iceoryx2Poll => "iceoryx2_poll",
            Transport::Iceoryx2Event => "iceoryx2_event",
            Transport::EventfdFloor => "eventfd_floor",
            Transport::UnixDgramFloor => "unix_dgram_floor",
            Transport::ZenohShm => "zenoh_shm",
            Transport::UnixSocket => "unix_socket",
        }
    }

    /// Whether the transport carries the images at all (the floors carry none).
    pub fn carries_payload(self) -> bool {
        !matches!(self, Transport::EventfdFloor | Transport::UnixDgramFloor)
    }
}

impl std::fmt::Display for Transport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // `pad`, not `write_str`: the report's table aligns transports with `{:<16}`.
        f.pad(self.name())
    }
}

/// A name that is none of [`Transport::ALL`]'s.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownTransport(pub String);

impl std::fmt::Display for UnknownTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names: Vec<&str> = Transport::ALL.iter().map(|t| t.name()).collect();
        write!(
            f,
            "unknown transport {:?} (one of {})",
            self.0,
            names.join(", ")
        )
    }
}

impl std::error::Error for UnknownTransport {}

impl std::str::FromStr for Transport {
    type Err = UnknownTransport;

    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        Transport::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| UnknownTransport(s.to_string()))
    }
}

/// How the peer finds the publisher's end; passed on the peer's command line.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PeerEndpoint {
    /// iceoryx2 robot namespace, Zenoh key expression, or abstract socket name.
    pub name: String,
    /// Zenoh endpoint to connect to.
    pub connect: Option<String>,
    /// Descriptor inherited from the publisher (eventfd, datagram socket).
    pub fd: Option<i32>,
}

/// The 32-byte header the byte-stream transports (Zenoh, Unix socket) put before the
/// images; iceoryx2 uses the schema's `FrameHeader` instead.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireHeader {
    pub seq: u64,
    pub stamp_ns: u64,
    pub phase: Phase,
    pub width: u32,
    pub height: u32,
}

pub const WIRE_HEADER_LEN: usize = 32;

impl WireHeader {
    pub fn encode(&self) -> [u8; WIRE_HEADER_LEN] {
        let mut b = [0u8; WIRE_HEADER_LEN];
        b[0..8].copy_from_slice(&self.seq.to_le_bytes());
        b[8..16].copy_from_slice(&self.stamp_ns.to_le_bytes());
        b[16..20].copy_from_slice(&(self.phase as u32).to_le_bytes());
        b[20..24].copy_from_slice(&self.width.to_le_bytes());
        b[24..28].copy_from_slice(&self.height.to_le_bytes());
        b
    }

    pub fn decode(b: &[u8]) -> Option<Self> {
        let b = b.get(..WIRE_HEADER_LEN)?;
        let u64_at = |i: usize| -> Option<u64> {
            Some(u64::from_le_bytes(b.get(i..i + 8)?.try_into().ok()?))
        };
        let u32_at = |i: usize| -> Option<u32> {
            Some(u32::from_le_bytes(b.get(i..i + 4)?.try_into().ok()?))
        };
        Some(Self {
            seq: u64_at(0)?,
            stamp_ns: u64_at(8)?,
            phase: Phase::from_u32(u32_at(16)?)?,
            width: u32_at(20)?,
            height: u32_at(24)?,
        })
    }

    /// Bytes of one image of this frame.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// One received pair, lent to the peer's bookkeeping where it lies (no copy is made
/// to hand it over).
#[derive(Debug)]
pub struct Delivered<'a> {
    pub phase: Phase,
    /// The publisher's CLOCK_MONOTONIC stamp; `None` when the transport merged several
    /// sends into one wake-up (eventfd) and the stamp is meaningless.
    pub stamp_ns: Option<u64>,
    /// CLOCK_MONOTONIC when the whole pair became readable here.
    pub recv_ns: u64,
    pub left: &'a [u8],
    pub right: &'a [u8],
    /// The transport's own claim that the payload is in shared memory (Zenoh's `as_shm`).
    pub shm_claim: Option<bool>,
}

/// Sleeps in poll(2) until `fd` is readable or `timeout` passes; whether it is readable.
pub(crate) fn wait_readable(fd: std::os::fd::RawFd, timeout: Duration) -> bool {
    let mut pfd = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    let ms = timeout.as_millis().clamp(1, i32::MAX as u128) as i32;
    // SAFETY: one valid pollfd, live for the call.
    unsafe { libc::poll(&mut pfd, 1, ms) > 0 }
}

/// Outcome of a non-blocking write(2)/send(2) of `len` bytes that returned `n`: sent,
/// `false` when there is no room (the peer has not read for a while), or the error.
pub(crate) fn nonblocking_sent(n: isize, len: usize, what: &str) -> Result<bool> {
    if n == len as isize {
        return Ok(true);
    }
    let err = std::io::Error::last_os_error();
    if n < 0 && err.kind() == std::io::ErrorKind::WouldBlock {
        return Ok(false);
    }
    Err(BenchError::Io {
        what: format!("{what}: {n} of {len} bytes sent"),
        source: err,
    })
}

/// The descriptor the publisher left open across exec for this peer (`--fd`), checked.
pub(crate) fn inherited_fd(endpoint: &PeerEndpoint, what: &str) -> Result<std::os::fd::OwnedFd> {
    use std::os::fd::FromRawFd;
    let Some(raw) = endpoint.fd else {
        return Err(BenchError::Transport(format!(
            "{what}: no inherited descriptor given"
        )));
    };
    // SAFETY: F_GETFD only queries the descriptor table.
    if raw < 0 || unsafe { libc::fcntl(raw, libc::F_GETFD) } < 0 {
        return Err(BenchError::Transport(format!(
            "{what}: descriptor {raw} was not inherited"
        )));
    }
    // SAFETY: the descriptor is open (checked above) and this process owns its copy.
    Ok(unsafe { std::os::fd::OwnedFd::from_raw_fd(raw) })
}

/// Publisher half.
pub trait Publish {
    /// Waits for the peer's connection, where the transport has one (Unix socket).
    fn accept_peer(&mut self, _deadline: Instant) -> Result<()> {
        Ok(())
    }

    /// Publishes one pair, stamping it right before the send call. `Ok(false)`: the
    /// transport has no room now (try again), which only a full shm pool or eventfd
    /// counter produces.
    fn publish(&mut self, phase: Phase, seq: u64, left: &[u8], right: &[u8]) -> Result<bool>;

    /// Where the publisher wrote its one copy of the payload (known after a publish).
    fn payload_mapping(&self) -> Option<Mapping>;

    /// CPU time the publisher spent in its one copy of 30 Hz pairs into the transport's
    /// buffer (0 where the send itself is the copy): the capture would pay it anyway.
    fn paced_copy_cpu_ns(&self) -> u64 {
        0
    }
}

/// Receiver half.
pub trait Receive {
    /// Waits up to `timeout` for pairs and hands each to `on_frame` in place.
    fn receive(
        &mut self,
        timeout: Duration,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()>;
}

/// Opens the publisher half of `transport` for `width x height` pairs, with names unique
/// to `tag` (pid + case), and says how the peer finds it.
pub fn open_publisher(
    transport: Transport,
    tag: &str,
    width: u32,
    height: u32,
) -> Result<(Box<dyn Publish>, PeerEndpoint)> {
    Ok(match transport {
        Transport::Iceoryx2Poll => iceoryx2::IceoryxPublisher::open(tag, width, height)?,
        Transport::Iceoryx2Event => iceoryx2::IceoryxPublisher::open(tag, width, height)?,
        Transport::EventfdFloor => eventfd::EventfdPublisher::open()?,
        Transport::UnixDgramFloor => dgram::DgramPublisher::open()?,
        Transport::ZenohShm => zenoh_shm::ZenohPublisher::open(tag, width, height)?,
        Transport::UnixSocket => unix_socket::SocketPublisher::open(tag, width, height)?,
    })
}

/// Opens the receiver half in the peer process.
pub fn open_receiver(transport: Transport, endpoint: &PeerEndpoint) -> Result<Box<dyn Receive>> {
    Ok(match transport {
        Transport::Iceoryx2Poll => Box::new(iceoryx2::IceoryxReceiver::open(endpoint, false)?),
        Transport::Iceoryx2Event => Box::new(iceoryx2::IceoryxReceiver::open(endpoint, true)?),
        Transport::EventfdFloor => Box::new(eventfd::EventfdReceiver::open(endpoint)?),
        Transport::UnixDgramFloor => Box::new(dgram::DgramReceiver::open(endpoint)?),
        Transport::ZenohShm => Box::new(zenoh_shm::ZenohReceiver::open(endpoint)?),
        Transport::UnixSocket => Box::new(unix_socket::SocketReceiver::open(endpoint)?),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_line_and_json_names_are_report_names() {
        for t in Transport::ALL {
            assert_eq!(t.name().parse::<Transport>(), Ok(t));
            assert_eq!(t.to_string(), t.name());
            assert_eq!(format!("{t:<17}|"), format!("{:<17}|", t.name()));
            let json = serde_json::to_string(&t).unwrap();
            assert_eq!(json, format!("\"{}\"", t.name()));
            assert_eq!(serde_json::from_str::<Transport>(&json).unwrap(), t);
        }
        let err = "iceoryx".parse::<Transport>().unwrap_err();
        assert!(err.to_string().contains("\"iceoryx\""), "{err}");
    }

    #[test]
    fn wire_header_round_trips() {
        let h = WireHeader {
            seq: 7,
            stamp_ns: 123_456_789,
            phase: Phase::Paced,
            width: 752,
            height: 480,
        };
        assert_eq!(WireHeader::decode(&h.encode()), Some(h));
        assert_eq!(WireHeader::decode(&[0u8; 31]), None);
        let mut bad = h.encode();
        bad[16] = 9;
        assert_eq!(WireHeader::decode(&bad), None);
    }
}
