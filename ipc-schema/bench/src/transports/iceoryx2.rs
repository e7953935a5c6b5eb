//! iceoryx2 through the services' own channel (`doorslam_ipc::{Sender, Receiver}` on the
//! frames topic: safe overflow, buffer 2, an event service beside it), so the benchmark
//! measures exactly the path the camera and its consumers use. The subscriber either
//! spins on `try_recv()` or sleeps in `recv_timeout()` until the publisher's notification.

use std::hint::spin_loop;
use std::time::{Duration, Instant};

use doorslam_ipc::iceoryx2::prelude::*;
use doorslam_ipc::{create_node, FrameHeader, IpcError, Receiver, Sender, StereoFrame, Topic};

use super::{Delivered, PeerEndpoint, Phase, Publish, Receive};
use crate::error::{BenchError, Result};
use crate::measure::{mapping_of_range, mono_ns, thread_cpu_ns, Mapping};

pub struct IceoryxPublisher {
    sender: Sender<StereoFrame>,
    mapping: Option<Mapping>,
    copy_cpu_ns: u64,
    width: u32,
    height: u32,
    // Dropped last: ports before the node.
    _node: Node<ipc::Service>,
}

impl IceoryxPublisher {
    /// The channel always notifies; with a spinning receiver that never consumes the
    /// notification, iceoryx2 skips the system call (the listener is still "notified").
    pub fn open(tag: &str, width: u32, height: u32) -> Result<(Box<dyn Publish>, PeerEndpoint)> {
        let (node, _) = create_node("doorslam-bench-publisher")?;
        let sender = Sender::<StereoFrame>::new(&node, tag, Topic::Frames)?;
        let endpoint = PeerEndpoint {
            name: tag.to_string(),
            ..PeerEndpoint::default()
        };
        let me = Self {
            sender,
            mapping: None,
            copy_cpu_ns: 0,
            width,
            height,
            _node: node,
        };
        Ok((Box::new(me), endpoint))
    }
}

impl Publish for IceoryxPublisher {
    fn publish(&mut self, phase: Phase, seq: u64, left: &[u8], right: &[u8]) -> Result<bool> {
        let (width, height, l, r) = if phase == Phase::End {
            (0, 0, &[][..], &[][..])
        } else {
            (self.width, self.height, left, right)
        };
        let header = FrameHeader {
            seq,
            stamp_ns: 0,
            robot: 0,
            // The bench stream is its own service, so the camera field carries the phase.
            camera: phase as u32,
            width,
            height,
            ..FrameHeader::default()
        };
        let (mapping, copy_cpu_ns) = (&mut self.mapping, &mut self.copy_cpu_ns);
        let sent = self.sender.send_with(|slot| {
            let copy_start = (phase == Phase::Paced).then(thread_cpu_ns);
            // The one copy: source images straight into the loaned shared-memory sample.
            StereoFrame::write(slot, header, l, r)?;
            if let Some(t0) = copy_start {
                *copy_cpu_ns += thread_cpu_ns().saturating_sub(t0);
            }
            if mapping.is_none() && phase == Phase::Warmup {
                let addr = slot.as_ptr() as usize;
                *mapping = mapping_of_range(&mut None, addr, std::mem::size_of::<StereoFrame>());
            }
            let header_ptr = slot.as_mut_ptr().cast::<FrameHeader>();
            // SAFETY: StereoFrame is #[repr(C)] with `header: FrameHeader` as its first
            // field (ipc-schema's cross-process layout contract), so the frame pointer is a
            // valid pointer to its initialized header. The stamp is written after the image
            // copy so the latency measures the transport, not the memcpy.
            unsafe { std::ptr::addr_of_mut!((*header_ptr).stamp_ns).write(mono_ns()) };
            Ok::<(), doorslam_ipc::FrameError>(())
        });
        match sent {
            Ok(()) => Ok(true),
            // Every sample is in flight: the transport has no room right now.
            Err(IpcError::NoRoom { .. }) => Ok(false),
            Err(e) => Err(BenchError::Ipc(e)),
        }
    }

    fn payload_mapping(&self) -> Option<Mapping> {
        self.mapping.clone()
    }

    fn paced_copy_cpu_ns(&self) -> u64 {
        self.copy_cpu_ns
    }
}

pub struct IceoryxReceiver {
    receiver: Receiver<StereoFrame>,
    sleep_on_event: bool,
    _node: Node<ipc::Service>,
}

impl IceoryxReceiver {
    pub fn open(endpoint: &PeerEndpoint, sleep_on_event: bool) -> Result<Self> {
        let robot = endpoint.name.as_str();
        let (node, _) = create_node("doorslam-bench-subscriber")?;
        let receiver = Receiver::<StereoFrame>::new(&node, robot, Topic::Frames)?;
        Ok(Self {
            receiver,
            sleep_on_event,
            _node: node,
        })
    }

    fn deliver(
        sample: &doorslam_ipc::iceoryx2::sample::Sample<ipc::Service, StereoFrame, ()>,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()> {
        let recv_ns = mono_ns();
        let frame = sample.payload();
        let h = *frame.header();
        let Some(phase) = Phase::from_u32(h.camera) else {
            return Ok(());
        };
        // The images are read where the publisher wrote them: slices into the sample.
        let left = frame.left_image().map_err(BenchError::Frame)?;
        let right = frame.right_image().map_err(BenchError::Frame)?;
        on_frame(&Delivered {
            phase,
            stamp_ns: Some(h.stamp_ns),
            recv_ns,
            left,
            right,
            shm_claim: None,
        });
        Ok(())
    }

    /// Hands every queued sample to `on_frame`; returns how many there were.
    fn drain(&self, on_frame: &mut dyn FnMut(&Delivered<'_>)) -> Result<usize> {
        let mut n = 0;
        while let Some(sample) = self.receiver.try_recv()? {
            n += 1;
            Self::deliver(&sample, on_frame)?;
        }
        Ok(n)
    }
}

impl Receive for IceoryxReceiver {
    fn receive(
        &mut self,
        timeout: Duration,
        on_frame: &mut dyn FnMut(&Delivered<'_>),
    ) -> Result<()> {
        if self.sleep_on_event {
            // What every service does: sleep in the kernel until notified, then drain.
            if let Some(sample) = self.receiver.recv_timeout(timeout)? {
                Self::deliver(&sample, on_frame)?;
                drop(sample);
                self.drain(on_frame)?;
            }
            return Ok(());
        }
        let deadline = Instant::now() + timeout;
        while self.drain(on_frame)? == 0 && Instant::now() < deadline {
            spin_loop();
        }
        Ok(())
    }
}
