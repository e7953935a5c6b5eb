//! Typed channels of one robot: an iceoryx2 publish-subscribe service plus an event
//! service of the same name, so receivers sleep until something is sent (no busy polling).
//!
//! Back-pressure, per topic ([`Topic::lossy`]):
//! - **frames** are lossy: a subscriber keeps the 2 newest, a slow consumer loses the
//!   oldest (counted by the receiver from the sequence numbers); the camera never blocks;
//! - **everything else** (keyframes, odometry, descriptors, closures, estimates) is
//!   reliable: a subscriber buffers up to [`RELIABLE_BUFFER`] samples and a publisher facing
//!   a full buffer waits until the consumer catches up (`RetryUntilDelivered`): nothing
//!   accepted is dropped; the wait shows up as latency upstream, never as loss.

use core::fmt::Debug;
use core::mem::MaybeUninit;
use core::time::Duration;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;

use crate::service::{service_name, IpcError, Topic};

/// Samples a reliable subscriber buffers before its publisher waits.
pub const RELIABLE_BUFFER: usize = 256;

fn service_error(service: &str, e: impl Debug) -> IpcError {
    let reason = format!("{e:?}");
    if reason.contains("IncompatibleTypes") {
        IpcError::SchemaMismatch {
            service: service.to_string(),
        }
    } else {
        IpcError::Service {
            service: service.to_string(),
            reason,
        }
    }
}

pub(crate) type PubSub<T> =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>;
pub(crate) type Event = iceoryx2::service::port_factory::event::PortFactory<ipc::Service>;

/// Opens (or creates) the pub-sub and event services of `topic` for `robot`.
pub(crate) fn open<T: Debug + ZeroCopySend + 'static>(
    node: &Node<ipc::Service>,
    robot: &str,
    topic: Topic,
) -> Result<(String, PubSub<T>, Event), IpcError> {
    let name = service_name(robot, topic);
    let sname: ServiceName = name.as_str().try_into().map_err(|e| IpcError::Name {
        name: name.clone(),
        reason: format!("{e:?}"),
    })?;
    let builder = node.service_builder(&sname).publish_subscribe::<T>();
    let builder = if topic.lossy() {
        builder
            .enable_safe_overflow(true)
            .subscriber_max_buffer_size(2)
    } else {
        builder
            .enable_safe_overflow(false)
            .subscriber_max_buffer_size(RELIABLE_BUFFER)
    };
    let pubsub = builder
        .history_size(0)
        .max_publishers(2)
        .max_subscribers(8)
        .open_or_create()
        .map_err(|e| service_error(&name, e))?;
    let event = node
        .service_builder(&sname)
        .event()
        .open_or_create()
        .map_err(|e| service_error(&name, e))?;
    Ok((name, pubsub, event))
}

/// The sending end of a channel.
pub struct Sender<T: Debug + ZeroCopySend + 'static> {
    name: String,
    publisher: Publisher<ipc::Service, T, ()>,
    notifier: Notifier<ipc::Service>,
    pubsub: PubSub<T>,
}

impl<T: Debug + ZeroCopySend + 'static> Sender<T> {
    pub fn new(node: &Node<ipc::Service>, robot: &str, topic: Topic) -> Result<Self, IpcError> {
        let (name, pubsub, event) = open::<T>(node, robot, topic)?;
        let strategy = if topic.lossy() {
            BackpressureStrategy::DiscardData
        } else {
            BackpressureStrategy::RetryUntilDelivered
        };
        let publisher = pubsub
            .publisher_builder()
            .backpressure_strategy(strategy)
            .create()
            .map_err(|e| service_error(&name, e))?;
        let notifier = event
            .notifier_builder()
            .create()
            .map_err(|e| service_error(&name, e))?;
        Ok(Self {
            name,
            publisher,
            notifier,
            pubsub,
        })
    }

    /// Fills a loaned shared-memory sample in place with `fill`, sends it, wakes receivers.
    /// `fill` must initialize the whole value (or return an error).
    pub fn send_with<E>(
        &self,
        fill: impl FnOnce(&mut MaybeUninit<T>) -> Result<(), E>,
    ) -> Result<(), IpcError>
    where
        E: std::fmt::Display,
    {
        let mut sample = self
            .publisher
            .loan_uninit()
            .map_err(|e| service_error(&self.name, e))?;
        fill(sample.payload_mut()).map_err(|e| IpcError::Payload {
            service: self.name.clone(),
            reason: e.to_string(),
        })?;
        // SAFETY: `fill` returned Ok, which by contract means it initialized the value.
        let sample = unsafe { sample.assume_init() };
        sample.send().map_err(|e| service_error(&self.name, e))?;
        self.notifier
            .notify()
            .map_err(|e| service_error(&self.name, e))?;
        Ok(())
    }

    /// Sends a copy of `value` (one memcpy into shared memory, no stack temporary).
    pub fn send_copy(&self, value: &T) -> Result<(), IpcError>
    where
        T: Copy,
    {
        self.send_with(|slot| {
            slot.write(*value);
            Ok::<(), std::convert::Infallible>(())
        })
    }

    /// Receivers currently connected.
    pub fn receivers(&self) -> usize {
        self.pubsub.dynamic_config().number_of_subscribers()
    }
}

/// The receiving end of a channel.
pub struct Receiver<T: Debug + ZeroCopySend + 'static> {
    name: String,
    subscriber: Subscriber<ipc::Service, T, ()>,
    listener: Listener<ipc::Service>,
}

impl<T: Debug + ZeroCopySend + 'static> Receiver<T> {
    pub fn new(node: &Node<ipc::Service>, robot: &str, topic: Topic) -> Result<Self, IpcError> {
        let (name, pubsub, event) = open::<T>(node, robot, topic)?;
        let subscriber = pubsub
            .subscriber_builder()
            .create()
            .map_err(|e| service_error(&name, e))?;
        let listener = event
            .listener_builder()
            .create()
            .map_err(|e| service_error(&name, e))?;
        Ok(Self {
            name,
            subscriber,
            listener,
        })
    }

    /// The next sample if one is waiting.
    pub fn try_recv(&self) -> Result<Option<Sample<ipc::Service, T, ()>>, IpcError> {
        self.subscriber
            .receive()
            .map_err(|e| service_error(&self.name, e))
    }

    /// The next sample, sleeping on the event service up to `timeout` if none is waiting.
    pub fn recv_timeout(
        &self,
        timeout: Duration,
    ) -> Result<Option<Sample<ipc::Service, T, ()>>, IpcError> {
        if let Some(s) = self.try_recv()? {
            return Ok(Some(s));
        }
        match self.listener.timed_wait(|_| {}, timeout) {
            Ok(_) => {}
            // SIGTERM/SIGINT interrupts the wait: not an error, the caller's loop checks
            // its lifecycle and finishes cleanly.
            Err(e) if format!("{e:?}").contains("Interrupt") => return Ok(None),
            Err(e) => return Err(service_error(&self.name, e)),
        }
        self.try_recv()
    }
}
