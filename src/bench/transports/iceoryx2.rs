//! iceoryx2: the real frame service (`open_frames`: safe overflow, buffer 2), with the
//! subscriber either spinning on `receive()` or blocked on an iceoryx2 event listener
//! that the publisher notifies after each send.

use std::hint::spin_loop;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use doorslam_ipc::iceoryx2::port::listener::Listener;
use doorslam_ipc::iceoryx2::port::notifier::Notifier;
use doorslam_ipc::iceoryx2::port::LoanError;
use doorslam_ipc::iceoryx2::prelude::*;
use doorslam_ipc::iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use doorslam_ipc::iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use doorslam_ipc::{
    create_node, open_frames, service_name, FrameHeader, FramePublisher, FrameSubscriber,
    StereoFrame, Topic,
};

use super::{Delivered, PeerEndpoint, Phase, Publish, Receive};
use crate::bench::measure::{mapping_of_range, mono_ns, thread_cpu_ns, Mapping};

type FrameFactory = PortFactory<ipc::Service, StereoFrame, ()>;

/// The wake-up service beside the frames: `doorslam/<robot>/frames/ready`.
fn open_ready(node: &Node<ipc::Service>, robot: &str) -> Result<EventFactory<ipc::Service>> {
    let name = format!("{}/ready", service_name(robot, Topic::Frames));
    let service_name: ServiceName = name
        .as_str()
        .try_into()
        .map_err(|e| anyhow!("event service name {name:?}: {e:?}"))?;
    node.service_builder(&service_name)
        .event()
        .open_or_create()
        .map_err(|e| anyhow!("iceoryx2 event service {name:?}: {e:?}"))
}

pub struct IceoryxPublisher {
    publisher: FramePublisher,
    notifier: Option<Notifier<ipc::Service>>,
    mapping: Option<Mapping>,
    copy_cpu_ns: u64,
    width: u32,
    height: u32,
    // Dropped last: ports before their services, services before the node.
    _event: Option<EventFactory<ipc::Service>>,
    _frames: FrameFactory,
    _node: Node<ipc::Service>,
}

impl IceoryxPublisher {
    pub fn open(
        tag: &str,
        notify: bool,
        width: u32,
        height: u32,
    ) -> Result<(Box<dyn Publish>, PeerEndpoint)> {
        let (node, _) = create_node("doorslam-bench-publisher")?;
        let frames = open_frames(&node, tag)?;
        let publisher = frames
            .publisher_builder()
            .create()
            .map_err(|e| anyhow!("iceoryx2 publisher on {tag}: {e:?}"))?;
        let (event, notifier) = if notify {
            let event = open_ready(&node, tag)?;
            let notifier = event
                .notifier_builder()
                .create()
                .map_err(|e| anyhow!("iceoryx2 notifier on {tag}: {e:?}"))?;
            (Some(event), Some(notifier))
        } else {
            (None, None)
        };
        let endpoint = PeerEndpoint {
            name: tag.to_string(),
            ..PeerEndpoint::default()
        };
        let me = Self {
            publisher,
            notifier,
            mapping: None,
            copy_cpu_ns: 0,
            width,
            height,
            _event: event,
            _frames: frames,
            _node: node,
        };
        Ok((Box::new(me), endpoint))
    }
}

impl Publish for IceoryxPublisher {
    fn publish(&mut self, phase: Phase, seq: u64, left: &[u8], right: &[u8]) -> Result<bool> {
        let (width, height) = if phase == Phase::End {
            (0, 0)
        } else {
            (self.width, self.height)
        };
        let mut sample = match self.publisher.loan_uninit() {
            Ok(sample) => sample,
            // Every sample is in flight: the transport has no room right now.
            Err(LoanError::OutOfMemory | LoanError::ExceedsMaxLoans) => return Ok(false),
            Err(e) => return Err(anyhow!("iceoryx2 loan: {e:?}")),
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
        let (l, r) = if phase == Phase::End {
            (&[][..], &[][..])
        } else {
            (left, right)
        };
        let slot = sample.payload_mut();
        let copy_start = (phase == Phase::Paced).then(thread_cpu_ns);
        // The one copy: source images straight into the loaned shared-memory sample.
        StereoFrame::write(slot, header, l, r)?;
        if let Some(t0) = copy_start {
            self.copy_cpu_ns += thread_cpu_ns().saturating_sub(t0);
        }
        if self.mapping.is_none() && phase == Phase::Warmup {
            let addr = slot.as_ptr() as usize;
            self.mapping = mapping_of_range(&mut None, addr, std::mem::size_of::<StereoFrame>());
        }
        let header_ptr = slot.as_mut_ptr().cast::<FrameHeader>();
        // SAFETY: StereoFrame is #[repr(C)] with `header: FrameHeader` as its first field
        // (ipc-schema's cross-process layout contract), so the frame pointer is a valid
        // pointer to its initialized header. The stamp is written after the image copy
        // so the latency measures the transport, not the memcpy.
        unsafe { std::ptr::addr_of_mut!((*header_ptr).stamp_ns).write(mono_ns()) };
        // SAFETY: `StereoFrame::write` initialized the sample.
        let sample = unsafe { sample.assume_init() };
        sample.send().map_err(|e| anyhow!("iceoryx2 send: {e:?}"))?;
        if let Some(notifier) = &self.notifier {
            notifier
                .notify()
                .map_err(|e| anyhow!("iceoryx2 notify: {e:?}"))?;
        }
        Ok(true)
    }

    fn payload_mapping(&self) -> Option<Mapping> {
        self.mapping.clone()
    }

    fn paced_copy_cpu_ns(&self) -> u64 {
        self.copy_cpu_ns
    }
}

pub struct IceoryxReceiver {
    subscriber: FrameSubscriber,
    listener: Option<Listener<ipc::Service>>,
    _event: Option<EventFactory<ipc::Service>>,
    _frames: FrameFactory,
    _node: Node<ipc::Service>,
}

impl IceoryxReceiver {
    pub fn open(endpoint: &PeerEndpoint, wait_on_event: bool) -> Result<Self> {
        let robot = endpoint.name.as_str();
        let (node, _) = create_node("doorslam-bench-subscriber")?;
        let frames = open_frames(&node, robot)?;
        let subscriber = frames
            .subscriber_builder()
            .create()
            .map_err(|e| anyhow!("iceoryx2 subscriber on {robot}: {e:?}"))?;
        let (event, listener) = if wait_on_event {
            let event = open_ready(&node, robot)?;
            let listener = event
                .listener_builder()
                .create()
                .map_err(|e| anyhow!("iceoryx2 listener on {robot}: {e:?}"))?;
            (Some(event), Some(listener))
        } else {
            (None, None)
        };
        Ok(Self {
            subscriber,
            listener,
            _event: event,
            _frames: frames,
            _node: node,
        })
    }

    /// Hands every queued sample to `on_frame`; returns how many there were.
    fn drain(&self, on_frame: &mut dyn FnMut(&Delivered<'_>)) -> Result<usize> {
        let mut n = 0;
        while let Some(sample) = self
            .subscriber
            .receive()
            .map_err(|e| anyhow!("iceoryx2 receive: {e:?}"))?
        {
            let recv_ns = mono_ns();
            n += 1;
            let frame = sample.payload();
            let h = *frame.header();
            let Some(phase) = Phase::from_u32(h.camera) else {
                continue;
            };
            // The images are read where the publisher wrote them: slices into the sample.
            let left = frame.left_image().context("received frame")?;
            let right = frame.right_image().context("received frame")?;
            on_frame(&Delivered {
                phase,
                stamp_ns: Some(h.stamp_ns),
                recv_ns,
                left,
                right,
                shm_claim: None,
            });
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
        if let Some(listener) = &self.listener {
            // Sleeps in the kernel until notified; the samples are then drained.
            listener
                .timed_wait(|_| {}, timeout)
                .map_err(|e| anyhow!("iceoryx2 listener wait: {e:?}"))?;
            self.drain(on_frame)?;
            return Ok(());
        }
        let deadline = Instant::now() + timeout;
        while self.drain(on_frame)? == 0 && Instant::now() < deadline {
            spin_loop();
        }
        Ok(())
    }
}
