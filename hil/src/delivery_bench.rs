//! The delivery contract weighed against Zenoh's own: the team link's hand-written
//! acknowledgements and resends ([`doorslam_team::delivery::Delivery`], what robots run)
//! and zenoh-ext's `AdvancedPublisher` (cache + sample-miss detection by heartbeat) /
//! `AdvancedSubscriber` (recovery), carrying the same stream of wire messages from robot
//! a to robot b over two real Zenoh peer sessions in this process, through a TCP relay
//! that counts every byte both ways (Zenoh framing, keep-alives, declarations, queries and
//! replies included) and cuts the link for a while, as a robot flying out of range does.
//!
//! The relay is the radio: b dials a's listening port through it, so everything between
//! the two sessions crosses it. A cut closes every connection and refuses new ones until
//! it ends; Zenoh then reconnects by itself (b's connect endpoint is retried). Loss
//! inside a connection is TCP's business and costs both layers alike, so the relay does
//! not emulate it: what differs between the two layers is what they do about messages
//! published while the peers are apart, and what that costs in bytes.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use doorslam_ipc::wire::{
    Body, Descriptor, Descriptors, Header, Kind, Message, RobotId, DESCRIPTOR_DIM,
};
use doorslam_team::delivery::{Arrived, Delivery};
use doorslam_team::protocol::ProtocolConfig;
use zenoh::{Session, Wait};
use zenoh_ext::{
    AdvancedPublisherBuilderExt, AdvancedSubscriberBuilderExt, CacheConfig, HistoryConfig,
    MissDetectionConfig, RecoveryConfig,
};

/// Which delivery layer carries the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Layer {
    /// The team link's: per-kind sequences, acknowledgements, resends after
    /// `retransmit_ms` (doubling), everything in flight resent when the peer reappears
    /// (its liveliness token), over plain declared publishers.
    Acks,
    /// zenoh-ext: the publisher keeps its last `cache` samples and sends a heartbeat
    /// every `heartbeat`; the subscriber asks for what it missed.
    ZenohExt,
}

/// The stream and the cut.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchOptions {
    /// Messages a sends b.
    pub messages: u64,
    /// Descriptors per message (one is 4 + 8 + 128 B on the wire).
    pub descriptors: usize,
    /// Messages per second.
    pub rate_hz: f64,
    /// The link is cut this long after the first message...
    pub cut_at: Duration,
    /// ... for this long (zero: no cut).
    pub cut_for: Duration,
    /// zenoh-ext: samples the publisher keeps for recovery.
    pub cache: usize,
    /// zenoh-ext: heartbeat period of the publisher's sample-miss detection.
    pub heartbeat: Duration,
    /// zenoh-ext: the subscriber also asks a publisher it detects (again) for its history
    /// (`HistoryConfig::detect_late_publishers`, as zenoh-ext's example does).
    pub history: bool,
    /// Acks: resend after this long (doubling per resend up to 16 times).
    pub retransmit_ms: u64,
    /// Zenoh's link lease (both layers).
    pub lease: Duration,
    /// Give up this long after the last message was published.
    pub settle: Duration,
}

impl Default for BenchOptions {
    fn default() -> Self {
        Self {
            messages: 300,
            descriptors: 2,
            rate_hz: 10.0,
            cut_at: Duration::from_secs(10),
            cut_for: Duration::from_secs(8),
            cache: 128,
            heartbeat: Duration::from_millis(500),
            history: true,
            // The team link's default (`[team] retransmit_ms`).
            retransmit_ms: 1000,
            lease: Duration::from_secs(2),
            settle: Duration::from_secs(30),
        }
    }
}

/// What one run delivered and what it cost.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BenchReport {
    pub layer: Layer,
    pub messages: u64,
    /// Distinct messages b received.
    pub delivered: u64,
    /// The first (at most 20) messages b never received.
    pub missing: Vec<u64>,
    /// Messages b received again.
    pub duplicates: u64,
    /// Deliveries that came after a later message of the stream.
    pub out_of_order: u64,
    /// zenoh-ext: samples its subscriber reported as missed for good.
    pub reported_missed: u64,
    /// Acks: messages a sent again.
    pub resends: u64,
    /// Bytes of the messages themselves (encoded wire messages, each once).
    pub payload_bytes: u64,
    /// Bytes through the relay, a → b and b → a.
    pub bytes_a_to_b: u64,
    pub bytes_b_to_a: u64,
    /// Both ways over the payload.
    pub overhead_ratio: f64,
    /// From the end of the cut until b had every message published before it (s; null
    /// without a cut, or when that never happened).
    pub recovered_after_s: Option<f64>,
    pub time_s: f64,
}

/// Why a run could not be made.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("relay: {0}")]
    Io(#[from] std::io::Error),
    #[error("zenoh ({what}): {reason}")]
    Zenoh { what: &'static str, reason: String },
    #[error("wire: {0}")]
    Wire(String),
    #[error("bad option: {0}")]
    Options(String),
}

fn zerr(what: &'static str) -> impl Fn(zenoh::Error) -> BenchError {
    move |e| BenchError::Zenoh {
        what,
        reason: e.to_string(),
    }
}

/// A TCP relay that counts bytes both ways and can cut every connection.
struct Relay {
    addr: SocketAddr,
    /// [a → b, b → a]: the listener side is a (upstream), the dialling side b.
    counts: Arc<[AtomicU64; 2]>,
    cut: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    streams: Arc<Mutex<Vec<TcpStream>>>,
    accept: Option<JoinHandle<()>>,
}

impl Relay {
    fn start(upstream: SocketAddr) -> Result<Self, BenchError> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let counts: Arc<[AtomicU64; 2]> = Arc::new([AtomicU64::new(0), AtomicU64::new(0)]);
        let cut = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let streams = Arc::new(Mutex::new(Vec::new()));
        let accept = {
            let (counts, cut, stop, streams) =
                (counts.clone(), cut.clone(), stop.clone(), streams.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Acquire) {
                    let down = match listener.accept() {
                        Ok((s, _)) => s,
                        Err(_) => {
                            std::thread::sleep(Duration::from_millis(5));
                            continue;
                        }
                    };
                    // Out of range: the connection is refused (closed at once).
                    if cut.load(Ordering::Acquire) {
                        drop(down);
                        continue;
                    }
                    let Ok(up) = TcpStream::connect(upstream) else {
                        continue;
                    };
                    let _ = down.set_nonblocking(false);
                    let _ = down.set_nodelay(true);
                    let _ = up.set_nodelay(true);
                    // b → a: what b sends (down) goes up; a → b the other way.
                    let pairs = [(&down, &up, 1), (&up, &down, 0)].map(|(from, to, slot)| {
                        Some((from.try_clone().ok()?, to.try_clone().ok()?, slot))
                    });
                    if let Ok(mut all) = streams.lock() {
                        all.push(down);
                        all.push(up);
                    }
                    for (mut from, mut to, slot) in pairs.into_iter().flatten() {
                        let (counts, cut) = (counts.clone(), cut.clone());
                        std::thread::spawn(move || {
                            let mut buf = vec![0u8; 64 * 1024];
                            loop {
                                let n = match from.read(&mut buf) {
                                    Ok(0) | Err(_) => break,
                                    Ok(n) => n,
                                };
                                if cut.load(Ordering::Acquire) || to.write_all(&buf[..n]).is_err() {
                                    break;
                                }
                                counts[slot].fetch_add(n as u64, Ordering::Relaxed);
                            }
                            let _ = from.shutdown(Shutdown::Both);
                            let _ = to.shutdown(Shutdown::Both);
                        });
                    }
                }
            })
        };
        Ok(Self {
            addr,
            counts,
            cut,
            stop,
            streams,
            accept: Some(accept),
        })
    }

    fn set_cut(&self, cut: bool) {
        self.cut.store(cut, Ordering::Release);
        if cut {
            if let Ok(mut all) = self.streams.lock() {
                for s in all.drain(..) {
                    let _ = s.shutdown(Shutdown::Both);
                }
            }
        }
    }

    fn bytes(&self) -> (u64, u64) {
        (
            self.counts[0].load(Ordering::Relaxed),
            self.counts[1].load(Ordering::Relaxed),
        )
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.set_cut(true);
        self.stop.store(true, Ordering::Release);
        if let Some(h) = self.accept.take() {
            let _ = h.join();
        }
    }
}

fn free_port() -> Result<u16, BenchError> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// A peer session as the team link opens one (no multicast scouting, no shared memory,
/// the lease given), listening or dialling over TCP on loopback.
fn open(
    listen: Option<u16>,
    connect: Option<SocketAddr>,
    lease: Duration,
    timestamps: bool,
) -> Result<Session, BenchError> {
    let mut config = zenoh::Config::default();
    let mut set = |key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| BenchError::Zenoh {
                what: "config",
                reason: format!("{key}: {e}"),
            })
    };
    set("mode", "\"peer\"".into())?;
    set(
        "listen/endpoints",
        match listen {
            Some(p) => format!("[\"tcp/127.0.0.1:{p}\"]"),
            None => "[]".into(),
        },
    )?;
    set(
        "connect/endpoints",
        match connect {
            Some(a) => format!("[\"tcp/{a}\"]"),
            None => "[]".into(),
        },
    )?;
    set("scouting/multicast/enabled", "false".into())?;
    set("transport/shared_memory/enabled", "false".into())?;
    set("transport/link/tx/lease", lease.as_millis().to_string())?;
    // Zenoh's own redial after a cut (1 s, doubling to 4 s), as the team link has it.
    if timestamps {
        // zenoh-ext's cache orders samples by timestamp.
        set("timestamping/enabled", "true".into())?;
    }
    zenoh::open(config).wait().map_err(zerr("open"))
}

/// Message `i` of the stream: robot a's descriptors of keyframes `i n .. (i + 1) n`.
fn message(i: u64, descriptors: usize) -> Message {
    let n = descriptors.max(1) as u64;
    Message {
        header: Header {
            sender: RobotId::new("a").expect("a is a robot id"),
            epoch: 1,
            sequence: i,
        },
        body: Body::Descriptors(Descriptors {
            robot: 0,
            keyframes: i * n..(i + 1) * n,
            descriptors: (i * n..(i + 1) * n)
                .map(|k| Descriptor {
                    key: doorslam_geometry::key::symbol(0, k).expect("robot a's keys"),
                    scale: 0.01,
                    values: [(k % 100) as i8; DESCRIPTOR_DIM],
                })
                .collect(),
        }),
    }
}

/// A message's wire bytes (what both layers publish).
fn encoded(m: &Message) -> Result<Vec<u8>, BenchError> {
    m.encode().map_err(|e| BenchError::Wire(e.to_string()))
}

fn id_of(body: &Body) -> Option<u64> {
    match body {
        Body::Descriptors(d) => Some(d.keyframes.start / d.descriptors.len().max(1) as u64),
        _ => None,
    }
}

/// What b received, in arrival order.
#[derive(Default)]
struct Received {
    seen: std::collections::BTreeSet<u64>,
    duplicates: u64,
    out_of_order: u64,
    highest: Option<u64>,
    /// Messages published before the link came back, and when b had them all.
    backlog: Option<u64>,
    backlog_done: Option<Instant>,
}

impl Received {
    fn take(&mut self, id: u64) {
        if !self.seen.insert(id) {
            self.duplicates += 1;
            return;
        }
        if self.highest.is_some_and(|h| id < h) {
            self.out_of_order += 1;
        }
        self.highest = Some(self.highest.map_or(id, |h| h.max(id)));
        self.check_backlog();
    }

    /// Whether b has every message of the stream.
    fn has_all(&self, options: &BenchOptions) -> bool {
        self.seen.len() as u64 == options.messages
    }

    /// The link just came back: what was published until now is the backlog.
    fn note_cut_end(&mut self, clock: &Clock) {
        if clock.cut_end.is_some() && self.backlog.is_none() {
            self.backlog = Some(clock.next);
            self.check_backlog();
        }
    }

    /// Whether b now has every message published before the link came back.
    fn check_backlog(&mut self) {
        if let (Some(n), None) = (self.backlog, self.backlog_done) {
            if self.seen.range(..n).count() as u64 == n {
                self.backlog_done = Some(Instant::now());
            }
        }
    }
}

/// One run of `layer` with `options`.
pub fn run(layer: Layer, options: &BenchOptions) -> Result<BenchReport, BenchError> {
    let sane = (1..=1_000_000).contains(&options.messages)
        && (1..=256).contains(&options.descriptors)
        && options.rate_hz > 0.0
        && options.rate_hz <= 1000.0;
    if !sane {
        return Err(BenchError::Options(format!(
            "{} messages of {} descriptors at {} Hz: 1 to 10⁶ messages of 1 to 256, 0 < rate ≤ 1000 Hz",
            options.messages, options.descriptors, options.rate_hz
        )));
    }
    let port = free_port()?;
    let relay = Relay::start(SocketAddr::from(([127, 0, 0, 1], port)))?;
    let timestamps = layer == Layer::ZenohExt;
    let a = open(Some(port), None, options.lease, timestamps)?;
    let b = open(None, Some(relay.addr), options.lease, timestamps)?;
    // Unique per run so parallel runs on one machine never cross.
    static RUN: AtomicU64 = AtomicU64::new(0);
    let prefix = format!(
        "doorslam/bench-delivery/{}-{}",
        std::process::id(),
        RUN.fetch_add(1, Ordering::Relaxed)
    );
    let result = match layer {
        Layer::Acks => run_acks(&a, &b, &relay, &prefix, options),
        Layer::ZenohExt => run_zenoh_ext(&a, &b, &relay, &prefix, options),
    };
    let _ = b.close().wait();
    let _ = a.close().wait();
    result
}

/// Where the run is with respect to the cut.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Cut {
    Before,
    During,
    After,
}

/// Paces the stream (which messages are due) and switches the cut.
struct Clock {
    start: Instant,
    period: Duration,
    /// The first message not yet due.
    next: u64,
    cut: Cut,
    cut_end: Option<Instant>,
    /// When the last message was published (and the cut was over).
    sent_at: Option<Instant>,
}

impl Clock {
    fn new(rate_hz: f64) -> Self {
        Self {
            start: Instant::now(),
            period: Duration::from_secs_f64(1.0 / rate_hz),
            next: 0,
            cut: Cut::Before,
            cut_end: None,
            sent_at: None,
        }
    }

    /// The messages due now, and the cut switched as its time comes.
    fn tick(&mut self, relay: &Relay, options: &BenchOptions) -> std::ops::Range<u64> {
        let t = self.start.elapsed();
        if !options.cut_for.is_zero() {
            if self.cut == Cut::Before && t >= options.cut_at {
                relay.set_cut(true);
                self.cut = Cut::During;
            } else if self.cut == Cut::During && t >= options.cut_at + options.cut_for {
                relay.set_cut(false);
                self.cut = Cut::After;
                self.cut_end = Some(Instant::now());
            }
        }
        let due = ((t.as_secs_f64() / self.period.as_secs_f64()) as u64 + 1).min(options.messages);
        let range = self.next..due.max(self.next);
        self.next = range.end;
        range
    }

    /// Whether the run is over: everything sent (and the cut over) and `delivered`, or
    /// `settle` passed since.
    fn finished(&mut self, delivered: bool, options: &BenchOptions) -> bool {
        let sent =
            self.next >= options.messages && (options.cut_for.is_zero() || self.cut == Cut::After);
        if !sent {
            return false;
        }
        let at = *self.sent_at.get_or_insert_with(Instant::now);
        delivered || at.elapsed() > options.settle
    }
}

fn report(
    layer: Layer,
    options: &BenchOptions,
    received: &Received,
    relay: &Relay,
    clock: &Clock,
    resends: u64,
    reported_missed: u64,
) -> Result<BenchReport, BenchError> {
    let payload_bytes = (0..options.messages)
        .map(|i| encoded(&message(i, options.descriptors)).map(|b| b.len() as u64))
        .sum::<Result<u64, _>>()?;
    let (ab, ba) = relay.bytes();
    Ok(BenchReport {
        layer,
        messages: options.messages,
        delivered: received.seen.len() as u64,
        missing: (0..options.messages)
            .filter(|i| !received.seen.contains(i))
            .take(20)
            .collect(),
        duplicates: received.duplicates,
        out_of_order: received.out_of_order,
        reported_missed,
        resends,
        payload_bytes,
        bytes_a_to_b: ab,
        bytes_b_to_a: ba,
        overhead_ratio: (ab + ba) as f64 / payload_bytes.max(1) as f64,
        recovered_after_s: match (clock.cut_end, received.backlog_done) {
            (Some(end), Some(done)) => Some(done.saturating_duration_since(end).as_secs_f64()),
            _ => None,
        },
        time_s: clock.start.elapsed().as_secs_f64(),
    })
}

/// Everything waiting at one end of the acknowledged stream: Hellos and acknowledgements
/// to its `Delivery`, the messages it delivers (in order, each once) to `deliver`.
fn take_in(
    delivery: &mut Delivery,
    inbox: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    mut deliver: impl FnMut(Body),
) {
    while let Ok(Some(s)) = inbox.try_recv() {
        let Ok(m) = Message::decode(&s.payload().to_bytes()) else {
            continue;
        };
        match m.body {
            Body::Hello(h) => {
                delivery.hello(m.header.sequence, &h);
            }
            Body::Ack(ack) => {
                let _ = delivery.acknowledged(&ack);
            }
            body => {
                if let Arrived::Deliver(run) = delivery.arrive(m.header, body) {
                    run.into_iter().for_each(|(_, body)| deliver(body));
                }
            }
        }
    }
}

fn run_acks(
    a: &Session,
    b: &Session,
    relay: &Relay,
    prefix: &str,
    options: &BenchOptions,
) -> Result<BenchReport, BenchError> {
    // The team link's own settings (`ProtocolConfig::default`), the resend time given.
    let config = ProtocolConfig {
        retransmit_ms: options.retransmit_ms,
        ..ProtocolConfig::default()
    }
    .delivery();
    let id = |s: &str| RobotId::new(s).expect("a and b are robot ids");
    let (mut da, mut db) = (
        Delivery::new(id("a"), 0, 1, config),
        Delivery::new(id("b"), 1, 1, config),
    );
    da.start_session(Some(1), false);
    db.start_session(Some(1), false);
    let to_b = a
        .declare_publisher(format!("{prefix}/b"))
        .wait()
        .map_err(zerr("publisher a"))?;
    let to_a = b
        .declare_publisher(format!("{prefix}/a"))
        .wait()
        .map_err(zerr("publisher b"))?;
    let at_a = a
        .declare_subscriber(format!("{prefix}/a"))
        .wait()
        .map_err(zerr("subscriber a"))?;
    let at_b = b
        .declare_subscriber(format!("{prefix}/b"))
        .wait()
        .map_err(zerr("subscriber b"))?;
    // The team link resends everything in flight when the peer's token appears again.
    let _token = b
        .liveliness()
        .declare_token(format!("{prefix}/alive/b"))
        .wait()
        .map_err(zerr("token"))?;
    let alive = a
        .liveliness()
        .declare_subscriber(format!("{prefix}/alive/**"))
        .history(true)
        .wait()
        .map_err(zerr("liveliness"))?;
    let mut received = Received::default();
    let mut clock = Clock::new(options.rate_hz);
    let send = |p: &zenoh::pubsub::Publisher<'_>, m: &Message| -> Result<(), BenchError> {
        p.put(encoded(m)?).wait().map_err(zerr("put"))
    };
    loop {
        let due = clock.tick(relay, options);
        received.note_cut_end(&clock);
        for i in due {
            da.queue(message(i, options.descriptors).body)
                .map_err(|e| BenchError::Wire(e.to_string()))?;
        }
        while let Ok(Some(s)) = alive.try_recv() {
            if s.kind() == zenoh::sample::SampleKind::Put {
                da.resend_all();
            }
        }
        let now_ms = clock.start.elapsed().as_millis() as u64;
        for o in da.poll(now_ms, Some(1)) {
            send(&to_b, &o.message)?;
        }
        for o in db.poll(now_ms, Some(1)) {
            send(&to_a, &o.message)?;
        }
        take_in(&mut db, &at_b, |body| {
            if let Some(id) = id_of(&body) {
                received.take(id);
            }
        });
        // a gets only Hellos and acknowledgements.
        take_in(&mut da, &at_a, |_| {});
        // Done when b has everything and a knows it (nothing left in flight).
        let all = received.has_all(options);
        if clock.finished(all && da.unsettled(Kind::Descriptors) == 0, options) {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    // What the ledger would add up: the last acknowledgements crossing back.
    std::thread::sleep(Duration::from_millis(200));
    report(
        Layer::Acks,
        options,
        &received,
        relay,
        &clock,
        da.retransmissions,
        0,
    )
}

fn run_zenoh_ext(
    a: &Session,
    b: &Session,
    relay: &Relay,
    prefix: &str,
    options: &BenchOptions,
) -> Result<BenchReport, BenchError> {
    let key = format!("{prefix}/b");
    let publisher = a
        .declare_publisher(key.clone())
        .cache(CacheConfig::default().max_samples(options.cache))
        .sample_miss_detection(MissDetectionConfig::default().heartbeat(options.heartbeat))
        .publisher_detection()
        .wait()
        .map_err(zerr("advanced publisher"))?;
    let mut builder = b
        .declare_subscriber(key)
        .recovery(RecoveryConfig::default().heartbeat())
        .subscriber_detection();
    if options.history {
        builder = builder.history(HistoryConfig::default().detect_late_publishers());
    }
    let subscriber = builder.wait().map_err(zerr("advanced subscriber"))?;
    let misses = subscriber
        .sample_miss_listener()
        .wait()
        .map_err(zerr("miss listener"))?;
    let mut received = Received::default();
    let mut clock = Clock::new(options.rate_hz);
    let mut missed = 0u64;
    loop {
        let due = clock.tick(relay, options);
        received.note_cut_end(&clock);
        for i in due {
            let bytes = encoded(&message(i, options.descriptors))?;
            publisher.put(bytes).wait().map_err(zerr("put"))?;
        }
        while let Ok(Some(s)) = subscriber.try_recv() {
            if let Ok(m) = Message::decode(&s.payload().to_bytes()) {
                if let Some(id) = id_of(&m.body) {
                    received.take(id);
                }
            }
        }
        while let Ok(Some(m)) = misses.try_recv() {
            missed += u64::from(m.nb());
        }
        if clock.finished(received.has_all(options), options) {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(200));
    report(
        Layer::ZenohExt,
        options,
        &received,
        relay,
        &clock,
        0,
        missed,
    )
}
