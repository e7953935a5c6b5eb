//! A Unix domain stream socket (abstract name, so nothing is left on disk) carrying the
//! wire header and both images. The kernel copies the bytes twice (write, read): this
//! is the copying baseline the shared-memory transports are measured against.

use std::io::{self, IoSlice, Read, Write};
use std::os::fd::AsRawFd;
use std::os::linux::net::SocketAddrExt;
use std::os::unix::net::{SocketAddr, UnixListener, UnixStream};
use std::time::{Duration, Instant};

use doorslam_ipc::MAX_FRAME_PIXELS;

use super::{Delivered, PeerEndpoint, Phase, Publish, Receive, WireHeader, WIRE_HEADER_LEN};
use crate::error::{BenchError, Result};
use crate::measure::{mapping_of, mono_ns, Mapping};

fn failed(what: impl Into<String>) -> BenchError {
    BenchError::Transport(what.into())
}

fn socket_name(tag: &str) -> String {
    format!("doorslam-bench-{tag}")
}

fn abstract_addr(name: &str) -> Result<SocketAddr> {
    SocketAddr::from_abstract_name(name.as_bytes())
        .map_err(BenchError::io(format!("abstract socket name {name:?}")))
}

pub struct SocketPublisher {
    listener: UnixListener,
    stream: Option<UnixStream>,
    width: u32,
    height: u32,
    mapping: Option<Mapping>,
}

impl SocketPublisher {
    pub fn open(tag: &str, width: u32, height: u32) -> Result<(Box<dyn Publish>, PeerEndpoint)> {
        let name = socket_name(tag);
        let listener = UnixListener::bind_addr(&abstract_addr(&name)?).map_err(BenchError::io(
            format!("listen on abstract socket {name:?}"),
        ))?;
        // Non-blocking accept so a peer that never connects cannot hang the run.
        listener
            .set_nonblocking(true)
            .map_err(BenchError::io("unix socket: non-blocking accept"))?;
        let me = Self {
            listener,
            stream: None,
            width,
            height,
            mapping: None,
        };
        let endpoint = PeerEndpoint {
            name,
            ..PeerEndpoint::default()
        };
        Ok((Box::new(me), endpoint))
    }
}

/// `write_vectored` until every byte is gone (std's `write_all_vectored` is unstable).
fn write_all_vectored(stream: &mut UnixStream, mut bufs: &mut [IoSlice<'_>]) -> io::Result<()> {
    while !bufs.is_empty() {
        match stream.write_vectored(bufs) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => IoSlice::advance_slices(&mut bufs, n),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

impl Publish for SocketPublisher {
    fn accept_peer(&mut self, deadline: Instant) -> Result<()> {
        loop {
            match self.listener.accept() {
                Ok((stream, _)) => {
                    stream
                        .set_nonblocking(false)
                        .map_err(BenchError::io("unix socket: blocking stream"))?;
                    self.stream = Some(stream);
                    return Ok(());
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if Instant::now() > deadline {
                        return Err(failed("unix socket: the peer did not connect in time"));
                    }
                    std::thread::sleep(Duration::from_millis(2));
                }
                Err(e) => return Err(BenchError::io("unix socket accept")(e)),
            }
        }
    }

    fn publish(&mut self, phase: Phase, seq: u64, left: &[u8], right: &[u8]) -> Result<bool> {
        let Some(stream) = self.stream.as_mut() else {
            return Err(failed("unix socket: publish before the peer connected"));
        };
        let (width, height, l, r) = if phase == Phase::End {
            (0, 0, &[][..], &[][..])
        } else {
            (self.width, self.height, left, right)
        };
        if self.mapping.is_none() && !l.is_empty() {
            self.mapping = mapping_of(&mut None, l);
        }
        let header = WireHeader {
            seq,
            stamp_ns: mono_ns(),
            phase,
            width,
            height,
        }
        .encode();
        // The write is the send: the kernel copies the bytes into the socket buffer.
        let mut bufs = [IoSlice::new(&header), IoSlice::new(l), IoSlice::new(r)];
        write_all_vectored(stream, &mut bufs).map_err(BenchError::io("unix socket write"))?;
        Ok(true)
    }

    fn payload_mapping(&self) -> Option<Mapping> {
        self.mapping.clone()
    }
}

pub struct SocketReceiver {
    stream: UnixStream,
    buf: Vec<u8>,
}

impl SocketReceiver {
    pub fn open(endpoint: &PeerEndpoint) -> Result<Self> {
        let stream = UnixStream::connect_addr(&abstract_addr(&endpoint.name)?).map_err(
            BenchError::io(format!("connect to abstract socket {:?}", endpoint.name)),
        )?;
        // A publisher that dies mid-frame must not hang the peer forever.
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .map_err(BenchError::io("unix socket: read timeout"))?;
        Ok(Self {
            stream,
            buf: vec![0; 2 * MAX_FRAME_PIXELS],
        })
    }
}

impl Receive for SocketReceiver {
    fn receive(
        &mut self,
        timeout: Duration,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()> {
        if !super::wait_readable(self.stream.as_raw_fd(), timeout) {
            return Ok(());
        }
        let mut raw = [0u8; WIRE_HEADER_LEN];
        self.stream
            .read_exact(&mut raw)
            .map_err(BenchError::io("unix socket read"))?;
        let Some(header) = WireHeader::decode(&raw) else {
            return Err(failed("unix socket: malformed frame header"));
        };
        let n = header.pixels();
        if 2 * n > self.buf.len() {
            return Err(failed(format!(
                "unix socket: frame of {n} pixels exceeds the maximum"
            )));
        }
        // The copy out of the kernel: the payload lands in this process's private buffer.
        self.stream
            .read_exact(&mut self.buf[..2 * n])
            .map_err(BenchError::io("unix socket read"))?;
        let recv_ns = mono_ns();
        on_frame(&Delivered {
            phase: header.phase,
            stamp_ns: Some(header.stamp_ns),
            recv_ns,
            left: &self.buf[..n],
            right: &self.buf[n..2 * n],
            shm_claim: None,
        });
        Ok(())
    }
}
