//! Typed channels of one robot: an iceoryx2 publish-subscribe service plus an event
//! service of the same name, so receivers sleep until something is sent (no busy polling).
//!
//! Back-pressure, per topic ([`Topic::lossy`]):
//! - **frames** are lossy: a subscriber keeps the 2 newest, a slow consumer loses the
//!   oldest (counted by the receiver from the sequence numbers); the camera never blocks;
//! - **everything else** (keyframes, odometry, descriptors, closures, estimates) is
//!   reliable: a subscriber buffers up to [`RELIABLE_BUFFER`] samples and a publisher facing
//!   a full buffer waits until the consumer catches up (`RetryUntilDelivered`); the wait
//!   shows up as latency upstream, not as loss. One exception, iceoryx2's guard against
//!   deadlocks: a sender only waits for a receiver that has connected its side of the
//!   connection, which a receiver does when it is created and at every receive; a full
//!   queue of a receiver that has not (a publisher that appeared while the consumer was
//!   busy) drops the sample. Senders count samples that reached fewer receivers than were
//!   connected ([`Sender::undelivered`]), and the back-end logs any gap in keyframe ids.
//!
//! The relay between the team link and the back-end (`team-in`, `team-out`) is reliable but
//! keeps no history ([`Topic::buffers`]): each end announces itself when it (re)starts.
//!
//! Crash recovery: reliable publishers keep their last [`RELIABLE_HISTORY`] samples, and a
//! subscriber that connects (a consumer restarted after a crash) is handed them first, in
//! order; consumers skip what they already have (the back-end by keyframe id). The history
//! is half the buffer, so a restarted consumer's queue still has room for new samples
//! before its first receive. A consumer down for up to 128 samples misses nothing; beyond
//! that the oldest are missing (a logged gap). A producer whose receiver's queue is full
//! waits; if that receiver's process is dead, it removes the dead ports within a second
//! and carries on (see [`remove_dead_receivers_while_blocked`]).
//!
//! Waking up: a receiver sleeps in one `ppoll(2)` on the event listener's socket and takes
//! the sample as soon as it wakes; notifications of samples already taken are consumed
//! later, when the queue is empty. (iceoryx2's own `timed_wait` toggles `O_NONBLOCK` and
//! `SO_RCVTIMEO` around every wait: four extra system calls on the wake-up path, which
//! doubled the wake-up latency on this machine kind.)

use core::fmt::Debug;
use core::mem::MaybeUninit;
use core::time::Duration;
use std::io;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::port::LoanError;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;

use crate::service::{service_name, IpcError, Topic};

/// Samples a reliable subscriber buffers before its publisher waits.
pub const RELIABLE_BUFFER: usize = 256;

/// Samples a reliable publisher keeps for consumers that (re)connect: the outage (in
/// samples) a restarted consumer recovers from without a gap. Half the buffer, so the
/// history cannot fill a new consumer's queue before it first receives.
pub const RELIABLE_HISTORY: usize = RELIABLE_BUFFER / 2;

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
    // Old frames are worthless to a consumer that connects late (lossy: safe overflow).
    let (buffer, history) = topic.buffers();
    let pubsub = node
        .service_builder(&sname)
        .publish_subscribe::<T>()
        .enable_safe_overflow(topic.lossy())
        .subscriber_max_buffer_size(buffer)
        .history_size(history)
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

/// Backpressure handler of reliable senders: waiting on a full receiver is normal while a
/// live consumer catches up, but a consumer that crashed never will, and until its
/// successor starts (which removes it) the sender would wait forever. So once per second of
/// waiting, the ports of dead processes are removed; the wait on a dead receiver then ends
/// (its samples stay in the history for its successor) and the producer carries on.
fn remove_dead_receivers_while_blocked(
) -> impl Fn(&iceoryx2::port::BackpressureInfo) -> iceoryx2::port::BackpressureAction + Send {
    let last_check_s = std::sync::atomic::AtomicU64::new(0);
    move |info| {
        use std::sync::atomic::Ordering::Relaxed;
        let waited_s = info.elapsed_time.as_secs();
        if info.retries == 0 {
            last_check_s.store(0, Relaxed);
        } else if waited_s > last_check_s.load(Relaxed) {
            last_check_s.store(waited_s, Relaxed);
            let _ = Node::<ipc::Service>::list(iceoryx2::config::Config::global_config(), |n| {
                if let NodeState::Dead(dead) = n {
                    let _ = dead.blocking_remove_stale_resources(Duration::ZERO);
                }
                CallbackProgression::Continue
            });
        }
        iceoryx2::port::BackpressureAction::Retry
    }
}

/// The sending end of a channel.
pub struct Sender<T: Debug + ZeroCopySend + 'static> {
    name: String,
    publisher: Publisher<ipc::Service, T, ()>,
    notifier: Notifier<ipc::Service>,
    pubsub: PubSub<T>,
    lossy: bool,
    undelivered: std::cell::Cell<u64>,
    /// Receivers as of the last [`Self::catch_up_receivers`].
    known_receivers: std::cell::RefCell<Vec<iceoryx2::identifiers::UniqueSubscriberId>>,
}

impl<T: Debug + ZeroCopySend + 'static> Sender<T> {
    pub fn new(node: &Node<ipc::Service>, robot: &str, topic: Topic) -> Result<Self, IpcError> {
        let (name, pubsub, event) = open::<T>(node, robot, topic)?;
        let strategy = if topic.lossy() {
            BackpressureStrategy::DiscardData
        } else {
            BackpressureStrategy::RetryUntilDelivered
        };
        let builder = pubsub.publisher_builder().backpressure_strategy(strategy);
        let builder = if topic.lossy() {
            builder
        } else {
            builder.set_backpressure_handler(remove_dead_receivers_while_blocked())
        };
        let publisher = builder.create().map_err(|e| service_error(&name, e))?;
        let notifier = event
            .notifier_builder()
            .create()
            .map_err(|e| service_error(&name, e))?;
        Ok(Self {
            name,
            publisher,
            notifier,
            pubsub,
            lossy: topic.lossy(),
            undelivered: Default::default(),
            known_receivers: Default::default(),
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
        let mut sample = self.publisher.loan_uninit().map_err(|e| match e {
            LoanError::OutOfMemory | LoanError::ExceedsMaxLoans => IpcError::NoRoom {
                service: self.name.clone(),
            },
            e => service_error(&self.name, e),
        })?;
        fill(sample.payload_mut()).map_err(|e| IpcError::Payload {
            service: self.name.clone(),
            reason: e.to_string(),
        })?;
        // SAFETY: `fill` returned Ok, which by contract means it initialized the value.
        let sample = unsafe { sample.assume_init() };
        // Frames are lossy by design: only reliable topics count (and pay for the count).
        let connected = (!self.lossy).then(|| self.receivers());
        let delivered = sample.send().map_err(|e| service_error(&self.name, e))?;
        if connected.is_some_and(|connected| delivered < connected) {
            // A receiver that has not connected its side yet had a full queue (see the
            // module docs), or one left during the send: counted, the caller may log it.
            self.undelivered.set(self.undelivered.get() + 1);
        }
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

    /// Reliable samples that reached fewer receivers than were connected when they were
    /// sent (always 0 for frames, which are lossy by design).
    pub fn undelivered(&self) -> u64 {
        self.undelivered.get()
    }

    /// Hands the history to receivers that connected since the last call (a consumer
    /// restarted after a crash) and wakes them. Sending does this by itself; a producer
    /// with nothing to send calls this from its idle loop (every ~100 ms), or a restarted
    /// consumer would wait for the next sample to get what it missed. Costs a read of the
    /// receiver list in shared memory; connections are updated and receivers woken only
    /// when that list changed.
    pub fn catch_up_receivers(&self) -> Result<(), IpcError> {
        let mut now = Vec::new();
        self.pubsub.dynamic_config().list_subscribers(|s| {
            now.push(s.subscriber_id);
            CallbackProgression::Continue
        });
        if now == *self.known_receivers.borrow() {
            return Ok(());
        }
        self.publisher
            .update_connections()
            .map_err(|e| service_error(&self.name, e))?;
        if !now.is_empty() {
            self.notifier
                .notify()
                .map_err(|e| service_error(&self.name, e))?;
        }
        *self.known_receivers.borrow_mut() = now;
        Ok(())
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
        // Connect to the publishers already there now, not at the first receive, so they
        // wait for this receiver (instead of dropping) from the start.
        subscriber
            .update_connections()
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
    /// `None` after the timeout, or when a signal (SIGTERM/SIGINT) interrupted the sleep:
    /// the caller's loop then checks its lifecycle.
    pub fn recv_timeout(
        &self,
        timeout: Duration,
    ) -> Result<Option<Sample<ipc::Service, T, ()>>, IpcError> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if let Some(s) = self.try_recv()? {
                return Ok(Some(s));
            }
            // The queue is empty: consume the notifications of samples already taken. A
            // sample is queued before its notification is sent, so a sample whose
            // notification is consumed here is seen by the second look (no lost wake-up).
            self.listener
                .try_wait(|_| {})
                .map_err(|e| service_error(&self.name, e))?;
            if let Some(s) = self.try_recv()? {
                return Ok(Some(s));
            }
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() || !self.sleep_until_notified(left)? {
                return Ok(None);
            }
            // Woken: usually the sample is there; a notification whose sample was taken
            // before we slept only costs another round.
        }
    }

    /// One `ppoll(2)` on the listener's socket; whether it became readable.
    fn sleep_until_notified(&self, timeout: Duration) -> Result<bool, IpcError> {
        // SAFETY: the descriptor belongs to the listener, which outlives this call; it is
        // only polled, never read or closed here.
        let fd = unsafe { self.listener.file_descriptor().native_handle() };
        let mut pfd = libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        };
        let ts = libc::timespec {
            tv_sec: timeout.as_secs().min(i32::MAX as u64) as libc::time_t,
            tv_nsec: libc::c_long::from(timeout.subsec_nanos() as i32),
        };
        // SAFETY: one valid pollfd and a valid timespec, both live for the call.
        let n = unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) };
        if n < 0 {
            let err = io::Error::last_os_error();
            if err.kind() == io::ErrorKind::Interrupted {
                return Ok(false);
            }
            return Err(IpcError::Service {
                service: self.name.clone(),
                reason: format!("waiting for a notification: {err}"),
            });
        }
        Ok(n > 0)
    }
}
