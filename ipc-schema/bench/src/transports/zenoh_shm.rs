//! Zenoh with shared memory: two peer sessions (one per process) joined over
//! tcp/127.0.0.1 with Zenoh's SHM transport enabled (its default when built with the
//! `shared-memory` feature). The publisher allocates each pair in a POSIX SHM buffer of
//! its own provider and puts it; over the TCP link only a small descriptor travels, and
//! the subscriber maps the same buffer.

use std::time::Duration;

use doorslam_team::zenoh::handlers::FifoChannelHandler;
use doorslam_team::zenoh::pubsub::{Publisher, Subscriber};
use doorslam_team::zenoh::sample::Sample;
use doorslam_team::zenoh::shm::{
    cleanup_orphaned_shm_segments, GarbageCollect, PosixShmProviderBackend, ShmProvider,
    ShmProviderBuilder, ZAllocError, ZLayoutAllocError,
};
use doorslam_team::zenoh::{Session, Wait};
use doorslam_team::{open_peer, LinkConfig};

use super::{Delivered, PeerEndpoint, Phase, Publish, Receive, WireHeader, WIRE_HEADER_LEN};
use crate::error::{BenchError, Result};
use crate::measure::{mapping_of, mono_ns, thread_cpu_ns, Mapping};

fn failed(what: impl Into<String>) -> BenchError {
    BenchError::Transport(what.into())
}

/// Pairs the SHM pool holds: enough to keep a pipeline of in-flight frames, small
/// enough that a stalled subscriber makes the publisher wait rather than grow memory.
const POOL_PAIRS: usize = 6;

fn key(tag: &str) -> String {
    format!("doorslam/bench/{tag}/frames")
}

/// A free loopback port for the publisher's listener (tiny race until Zenoh binds it;
/// Zenoh does not report loopback locators, so port 0 could not be passed on).
fn free_port() -> Result<u16> {
    let probe = std::net::TcpListener::bind("127.0.0.1:0")
        .map_err(BenchError::io("probe a free tcp port"))?;
    let addr = probe
        .local_addr()
        .map_err(BenchError::io("probe a free tcp port"))?;
    Ok(addr.port())
}

pub struct ZenohPublisher {
    publisher: Publisher<'static>,
    provider: ShmProvider<PosixShmProviderBackend>,
    width: u32,
    height: u32,
    mapping: Option<Mapping>,
    copy_cpu_ns: u64,
    _session: Session,
}

impl ZenohPublisher {
    pub fn open(tag: &str, width: u32, height: u32) -> Result<(Box<dyn Publish>, PeerEndpoint)> {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port()?);
        let session = open_peer(&LinkConfig {
            listen: vec![endpoint.clone()],
            connect: vec![],
            multicast_scouting: false,
        })?;
        let key = key(tag);
        let publisher = session
            .declare_publisher(key.clone())
            .wait()
            .map_err(BenchError::zenoh(format!("zenoh publisher on {key}")))?;
        let pair = WIRE_HEADER_LEN + 2 * width as usize * height as usize;
        let backend = PosixShmProviderBackend::builder(POOL_PAIRS * pair)
            .wait()
            .map_err(BenchError::zenoh(format!(
                "zenoh shm pool of {} bytes",
                POOL_PAIRS * pair
            )))?;
        let provider = ShmProviderBuilder::backend(backend).wait();
        let me = Self {
            publisher,
            provider,
            width,
            height,
            mapping: None,
            copy_cpu_ns: 0,
            _session: session,
        };
        let peer = PeerEndpoint {
            name: key,
            connect: Some(endpoint),
            fd: None,
        };
        Ok((Box::new(me), peer))
    }
}

impl Publish for ZenohPublisher {
    fn publish(&mut self, phase: Phase, seq: u64, left: &[u8], right: &[u8]) -> Result<bool> {
        let mut header = WireHeader {
            seq,
            stamp_ns: 0,
            phase,
            width: self.width,
            height: self.height,
        };
        if phase == Phase::End {
            (header.width, header.height) = (0, 0);
            header.stamp_ns = mono_ns();
            let bytes = header.encode().to_vec();
            self.publisher
                .put(bytes)
                .wait()
                .map_err(BenchError::zenoh("zenoh put"))?;
            return Ok(true);
        }
        let n = left.len();
        let len = WIRE_HEADER_LEN + 2 * n;
        let mut buf = match self
            .provider
            .alloc(len)
            .with_policy::<GarbageCollect>()
            .wait()
        {
            Ok(buf) => buf,
            Err(ZLayoutAllocError::Alloc(ZAllocError::NeedDefragment)) => {
                self.provider.defragment();
                return Ok(false);
            }
            // Every buffer is still held by the subscriber: no room right now.
            Err(ZLayoutAllocError::Alloc(ZAllocError::OutOfMemory)) => return Ok(false),
            Err(e) => return Err(BenchError::zenoh(format!("zenoh shm alloc of {len} bytes"))(e)),
        };
        let copy_start = (phase == Phase::Paced).then(thread_cpu_ns);
        // The one copy: source images into the SHM buffer.
        buf[WIRE_HEADER_LEN..WIRE_HEADER_LEN + n].copy_from_slice(left);
        buf[WIRE_HEADER_LEN + n..len].copy_from_slice(right);
        if let Some(t0) = copy_start {
            self.copy_cpu_ns += thread_cpu_ns().saturating_sub(t0);
        }
        if self.mapping.is_none() && phase == Phase::Warmup {
            self.mapping = mapping_of(&mut None, &buf);
        }
        header.stamp_ns = mono_ns();
        buf[..WIRE_HEADER_LEN].copy_from_slice(&header.encode());
        self.publisher
            .put(buf)
            .wait()
            .map_err(BenchError::zenoh("zenoh put"))?;
        Ok(true)
    }

    fn payload_mapping(&self) -> Option<Mapping> {
        self.mapping.clone()
    }

    fn paced_copy_cpu_ns(&self) -> u64 {
        self.copy_cpu_ns
    }
}

impl Drop for ZenohPublisher {
    fn drop(&mut self) {
        // The peer process has exited by now (it is reaped before the publisher drops);
        // Zenoh can leave a segment of an exited process in /dev/shm until the next
        // Zenoh process starts, so remove the dangling ones (lock-checked: live ones stay).
        cleanup_orphaned_shm_segments();
    }
}

pub struct ZenohReceiver {
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    _session: Session,
}

impl ZenohReceiver {
    pub fn open(endpoint: &PeerEndpoint) -> Result<Self> {
        let Some(connect) = endpoint.connect.clone() else {
            return Err(failed("zenoh peer: no endpoint to connect to"));
        };
        let session = open_peer(&LinkConfig {
            listen: vec![],
            connect: vec![connect],
            multicast_scouting: false,
        })?;
        let subscriber = session
            .declare_subscriber(endpoint.name.clone())
            .wait()
            .map_err(BenchError::zenoh(format!(
                "zenoh subscriber on {}",
                endpoint.name
            )))?;
        Ok(Self {
            subscriber,
            _session: session,
        })
    }
}

fn deliver(sample: &Sample, on_frame: &mut dyn FnMut(&Delivered<'_>)) -> Result<()> {
    let recv_ns = mono_ns();
    let payload = sample.payload();
    // In place when the payload arrived as a SHM buffer; otherwise Zenoh hands over the
    // bytes it received from the socket (a copy by construction).
    let (bytes, shm_claim) = match payload.as_shm() {
        Some(shm) => (std::borrow::Cow::Borrowed(&shm[..]), true),
        None => (payload.to_bytes(), false),
    };
    let Some(header) = WireHeader::decode(&bytes) else {
        return Err(failed("zenoh: malformed frame header"));
    };
    let n = header.pixels();
    let Some(images) = bytes.get(WIRE_HEADER_LEN..WIRE_HEADER_LEN + 2 * n) else {
        return Err(failed("zenoh: frame shorter than its header says"));
    };
    on_frame(&Delivered {
        phase: header.phase,
        stamp_ns: Some(header.stamp_ns),
        recv_ns,
        left: &images[..n],
        right: &images[n..],
        shm_claim: Some(shm_claim),
    });
    Ok(())
}

impl Receive for ZenohReceiver {
    fn receive(
        &mut self,
        timeout: Duration,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()> {
        let first = self
            .subscriber
            .recv_timeout(timeout)
            .map_err(BenchError::zenoh("zenoh receive"))?;
        let Some(sample) = first else {
            return Ok(());
        };
        deliver(&sample, on_frame)?;
        while let Some(sample) = self
            .subscriber
            .try_recv()
            .map_err(BenchError::zenoh("zenoh receive"))?
        {
            deliver(&sample, on_frame)?;
        }
        Ok(())
    }
}
