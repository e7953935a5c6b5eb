//! The publisher side (`doorslam bench ipc`): for each resolution and transport, start a
//! peer process, warm up, then run three phases and combine both processes' findings.
//!
//! Phases of one case (each at most `seconds_per_case`):
//! 1. latency: pairs paced [`LATENCY_PACE`] apart, so the receiver is idle (spinning or
//!    asleep, depending on the transport) when each arrives;
//! 2. throughput: pairs as fast as the transport accepts them;
//! 3. 30 Hz: the camera rate, for the CPU time of both processes per pair.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use crate::child::PeerProcess;
use crate::error::{BenchError, Result};
use crate::measure::{cpu_ns, median, mono_ns, pin_to_cpu, test_image};
use crate::peer::{PeerReport, PeerSpec};
use crate::report::{check_targets, loadavg, IpcReport, Machine, ResultRow, Settings};
use crate::transports::{open_publisher, Phase, Publish, Transport};

/// Gap between latency pairs: long enough for the receiver to finish a 1280x720 pair
/// and go idle, short enough for a thousand samples in two seconds.
pub const LATENCY_PACE: Duration = Duration::from_millis(2);
/// The camera rate the CPU cost is quoted at.
pub const PACED_HZ: f64 = 30.0;
/// The stereo resolutions of the issue: EuRoC-like VGA-ish and 720p.
pub const RESOLUTIONS: [(u32, u32); 2] = [(752, 480), (1280, 720)];

const PEER_START: Duration = Duration::from_secs(30);
const WARMUP_LIMIT: Duration = Duration::from_secs(30);
const REPORT_LIMIT: Duration = Duration::from_secs(15);

/// How the benchmark starts its subscriber process: `program args...`, followed by the
/// peer's own arguments ([`PeerSpec::to_args`]). The program is expected to parse those
/// into a [`PeerSpec`] and call [`crate::run_peer`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PeerCommand {
    pub program: PathBuf,
    /// Arguments before the peer's, e.g. the hidden subcommand that runs the peer.
    pub args: Vec<String>,
}

impl PeerCommand {
    /// This process's own binary, re-executed with `args` (then the peer's arguments).
    pub fn current_exe<S: Into<String>>(args: impl IntoIterator<Item = S>) -> Result<Self> {
        let program =
            std::env::current_exe().map_err(BenchError::io("locate this process's binary"))?;
        Ok(Self {
            program,
            args: args.into_iter().map(Into::into).collect(),
        })
    }

    /// `the doorslam binary re-executed (`bench ipc-peer`)`, for the report's method.
    fn describe(&self) -> String {
        let name = self.program.file_name().map_or_else(
            || self.program.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        format!("the {name} binary re-executed (`{}`)", self.args.join(" "))
    }
}

/// Options of one run.
#[derive(Debug, Clone)]
pub struct IpcOptions {
    /// Length of each measured phase of each case, seconds (0.05 to 600).
    pub seconds_per_case: f64,
    /// Most latency samples per case (at least 1).
    pub frames: usize,
    /// Interleaved repetitions of every case (1 to 100); figures are medians over them.
    pub rounds: usize,
    /// CPUs to pin the publisher and the subscriber process to.
    pub pin_cpus: Option<(usize, usize)>,
    /// How to start the subscriber process.
    pub peer: PeerCommand,
}

impl IpcOptions {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        let invalid = |option, reason| Err(BenchError::InvalidOption { option, reason });
        if !(self.seconds_per_case.is_finite() && (0.05..=600.0).contains(&self.seconds_per_case)) {
            return invalid("seconds_per_case", "must be between 0.05 and 600");
        }
        if self.frames == 0 {
            return invalid("frames", "must be at least 1");
        }
        if !(1..=100).contains(&self.rounds) {
            return invalid("rounds", "must be between 1 and 100");
        }
        Ok(())
    }
}

fn method(peer: &PeerCommand) -> Vec<String> {
    let subscriber = format!("subscriber = a second process: {}", peer.describe());
    [
        subscriber.as_str(),
        "latency = CLOCK_MONOTONIC read in the subscriber once the whole pair is readable, minus the stamp the publisher took right before its send call (after its one copy into the shm sample/buffer; for the Unix socket the write() is the send)",
        "latency phase: pairs paced 2 ms apart; iceoryx2_poll spins on receive(), iceoryx2_event and the two floors sleep in the kernel between pairs",
        "pairs_per_s: pairs received / (last receive - start of sending), publisher sending as fast as accepted; drops = sent - received over all phases",
        "cpu_*_30hz: CPU time (CLOCK_PROCESS_CPUTIME_ID, all threads) of publisher + subscriber over the 30 Hz phase / pairs sent; the subscriber does not checksum in that phase; iceoryx2_poll spins by design",
        "copy_us_per_frame_30hz: the publisher's one copy into the shm sample/buffer (CLOCK_THREAD_CPUTIME_ID around it), which a camera writing into the loaned sample pays anyway; transport_cpu_percent_30hz = cpu_percent_30hz without it",
        "eventfd_floor and unix_dgram_floor have no throughput phase (pairs_per_s null): they carry no pairs",
        "unix_dgram_floor: no payload; a Unix datagram socket pair (the primitive iceoryx2's ipc events use), 9-byte datagram with the stamp, read after poll()",
        "zero_copy: both processes look up the payload address in /proc/self/maps; true iff the publisher's write target and every image the subscriber checksummed in place lie in a shared (s) mapping of the same memory object (device + inode)",
        "zenoh_shm: peer sessions over tcp/127.0.0.1 with Zenoh's SHM transport; the publisher puts a POSIX SHM buffer (ShmProvider), the subscriber reads ZBytes::as_shm() in place",
        "eventfd_floor: no payload; an eventfd inherited by the subscriber, written by the publisher (stamp in the counter), read after poll(); pairs_per_s = wake-ups/s",
        "rounds: every case runs `rounds` times, interleaved (each transport once per round, in the same order); each figure of a row is the median over its rounds, counts are sums; p99_us_rounds lists every round's p99_us, and the event/floor target is the median of the per-round ratios (the two ran seconds apart in each round)",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect()
}

/// Runs every case, calling `progress` with the name of each before it starts; a failing
/// case becomes a row with `error` set and the run goes on. Fails only on invalid options
/// or when the publisher cannot be pinned.
pub fn run(opts: &IpcOptions, progress: &dyn Fn(&str)) -> Result<IpcReport> {
    opts.validate()?;
    let mut machine = Machine::probe();
    if let Some((publisher, _)) = opts.pin_cpus {
        pin_to_cpu(publisher).map_err(|source| BenchError::PinCpu {
            process: "publisher",
            cpu: publisher,
            source,
        })?;
    }
    let mut results = Vec::new();
    let mut case = 0;
    let rounds = opts.rounds;
    for (w, h) in RESOLUTIONS {
        let resolution = format!("{w}x{h}");
        let left = test_image(w, h, 0);
        let right = test_image(w, h, 1);
        let mut by_transport: Vec<Vec<ResultRow>> = vec![Vec::new(); Transport::ALL.len()];
        for round in 1..=rounds {
            for (k, transport) in Transport::ALL.into_iter().enumerate() {
                case += 1;
                progress(&format!(
                    "{} {w}x{h} (round {round} of {rounds})",
                    transport.name()
                ));
                let row = match run_case(transport, w, h, case, opts, &left, &right) {
                    Ok(row) => row,
                    Err(e) => ResultRow {
                        error: Some(e.chain()),
                        ..ResultRow::new(transport, resolution.clone())
                    },
                };
                by_transport[k].push(row);
            }
        }
        for (transport, runs) in Transport::ALL.into_iter().zip(by_transport) {
            results.push(combine_rounds(transport, &resolution, runs));
        }
    }
    machine.loadavg_end = loadavg();
    let resolutions: Vec<String> = RESOLUTIONS
        .iter()
        .map(|(w, h)| format!("{w}x{h}"))
        .collect();
    let targets = check_targets(&results, &resolutions);
    Ok(IpcReport {
        machine,
        settings: Settings {
            seconds_per_case: opts.seconds_per_case,
            latency_frames_max: opts.frames,
            latency_pace_us: LATENCY_PACE.as_micros() as u64,
            paced_hz: PACED_HZ,
            rounds,
            pin_cpus: opts.pin_cpus.map(|(a, b)| [a, b]),
            method: method(&opts.peer),
        },
        results,
        targets,
    })
}

/// One row from a case's rounds: every figure is the median over the rounds that did not
/// fail, counts are summed, zero-copy must hold in every round; the per-round p99s are
/// kept (targets compare transports round by round). If every round failed, the first
/// failure is the row.
fn combine_rounds(transport: Transport, resolution: &str, runs: Vec<ResultRow>) -> ResultRow {
    let rounds = runs.len();
    let p99_us_rounds = runs.iter().map(|r| r.p99_us).collect();
    let p99_us_30hz_rounds = runs.iter().map(|r| r.p99_us_30hz).collect();
    let (ok, failed): (Vec<ResultRow>, Vec<ResultRow>) =
        runs.into_iter().partition(|r| r.error.is_none());
    let Some(first) = ok.first() else {
        let mut row = failed
            .into_iter()
            .next()
            .unwrap_or_else(|| ResultRow::new(transport, resolution.to_string()));
        row.rounds = rounds;
        return row;
    };
    let med = |f: fn(&ResultRow) -> Option<f64>| median(ok.iter().map(f));
    let sum = |f: fn(&ResultRow) -> u64| ok.iter().map(f).sum::<u64>();
    ResultRow {
        p50_us: med(|r| r.p50_us),
        p99_us: med(|r| r.p99_us),
        pairs_per_s: med(|r| r.pairs_per_s),
        zero_copy: ok
            .iter()
            .map(|r| r.zero_copy)
            .reduce(|a, b| a.zip(b).map(|(a, b)| a && b))
            .flatten(),
        samples: sum(|r| r.samples),
        drops: sum(|r| r.drops),
        cpu_us_per_frame_30hz: med(|r| r.cpu_us_per_frame_30hz),
        cpu_percent_30hz: med(|r| r.cpu_percent_30hz),
        copy_us_per_frame_30hz: med(|r| r.copy_us_per_frame_30hz),
        transport_cpu_percent_30hz: med(|r| r.transport_cpu_percent_30hz),
        p50_us_30hz: med(|r| r.p50_us_30hz),
        p99_us_30hz: med(|r| r.p99_us_30hz),
        sent: sum(|r| r.sent),
        received: sum(|r| r.received),
        checksum_errors: sum(|r| r.checksum_errors),
        payload_mapping: first.payload_mapping.clone(),
        rounds,
        p99_us_rounds,
        p99_us_30hz_rounds,
        error: None,
        ..ResultRow::new(transport, resolution.to_string())
    }
}

fn sleep_until(t: Instant) {
    let now = Instant::now();
    if t > now {
        std::thread::sleep(t - now);
    }
}

/// What the publisher counted while sending.
#[derive(Default)]
struct Sent {
    latency: u64,
    throughput: u64,
    throughput_start_ns: u64,
    paced: u64,
    paced_cpu_ns: u64,
    paced_copy_cpu_ns: u64,
    paced_wall_ns: u64,
}

fn run_case(
    transport: Transport,
    w: u32,
    h: u32,
    case: usize,
    opts: &IpcOptions,
    left: &[u8],
    right: &[u8],
) -> Result<ResultRow> {
    let tag = format!("bench{}c{case}", std::process::id());
    let phase = Duration::from_secs_f64(opts.seconds_per_case);
    let (mut publisher, endpoint) =
        open_publisher(transport, &tag, w, h).map_err(|e| BenchError::OpenPublisher {
            transport,
            source: Box::new(e),
        })?;
    let spec = PeerSpec {
        transport,
        width: w,
        height: h,
        endpoint,
        deadline: Duration::from_secs_f64(3.0 * opts.seconds_per_case + 90.0),
        pin_cpu: opts.pin_cpus.map(|(_, cpu)| cpu),
    };
    let mut peer = PeerProcess::spawn(&opts.peer, &spec.to_args())?;
    peer.expect("ready", PEER_START)?;
    publisher.accept_peer(Instant::now() + PEER_START)?;

    let mut seq = 0u64;
    let warm_until = Instant::now() + WARMUP_LIMIT;
    while !peer.said("warm")? {
        if Instant::now() >= warm_until {
            return Err(BenchError::Peer(
                "no warm-up frame reached the peer".to_string(),
            ));
        }
        publisher.publish(Phase::Warmup, seq, left, right)?;
        seq += 1;
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(50));

    let flat_out = transport.carries_payload();
    let sent = send_phases(
        publisher.as_mut(),
        opts,
        phase,
        flat_out,
        &mut seq,
        left,
        right,
    )?;

    // Resend the end marker until the report comes: a lost marker must not cost the case.
    let until = Instant::now() + REPORT_LIMIT;
    let report = loop {
        if let Some(line) = peer.wait_for("report ", Duration::from_millis(200))? {
            break serde_json::from_str::<PeerReport>(&line)
                .map_err(|e| BenchError::PeerReport("parse", e))?;
        }
        if Instant::now() >= until {
            return Err(BenchError::Peer("the peer sent no report".to_string()));
        }
        publisher.publish(Phase::End, seq, left, right)?;
    };
    peer.finish(Duration::from_secs(10))?;
    Ok(combine(transport, w, h, publisher.as_ref(), &sent, &report))
}

/// Sends the three phases; `flat_out: false` skips the throughput phase (the wake-up
/// floor has no pairs to count, only merged counter writes).
fn send_phases(
    publisher: &mut dyn Publish,
    opts: &IpcOptions,
    phase: Duration,
    flat_out: bool,
    seq: &mut u64,
    left: &[u8],
    right: &[u8],
) -> Result<Sent> {
    let mut sent = Sent::default();
    let mut send = |p: Phase, seq: &mut u64| -> Result<bool> {
        let ok = publisher.publish(p, *seq, left, right)?;
        *seq += 1;
        Ok(ok)
    };

    let n = ((phase.as_secs_f64() / LATENCY_PACE.as_secs_f64()) as usize).clamp(1, opts.frames);
    let t0 = Instant::now();
    for k in 0..n as u32 {
        sleep_until(t0 + LATENCY_PACE * k);
        sent.latency += u64::from(send(Phase::Latency, seq)?);
    }
    std::thread::sleep(Duration::from_millis(50));

    sent.throughput_start_ns = mono_ns();
    let end = Instant::now() + if flat_out { phase } else { Duration::ZERO };
    while Instant::now() < end {
        if send(Phase::Throughput, seq)? {
            sent.throughput += 1;
        } else {
            std::thread::yield_now();
        }
    }
    // Let the subscriber drain, so the 30 Hz phase starts from idle.
    std::thread::sleep(Duration::from_millis(150));

    let period = Duration::from_secs_f64(1.0 / PACED_HZ);
    let n = ((phase.as_secs_f64() * PACED_HZ).round() as u32).max(3);
    let (cpu0, wall0, t0) = (cpu_ns(), mono_ns(), Instant::now());
    for k in 0..n {
        sleep_until(t0 + period * k);
        sent.paced += u64::from(send(Phase::Paced, seq)?);
    }
    sleep_until(t0 + period * n);
    send(Phase::End, seq)?;
    sent.paced_cpu_ns = cpu_ns().saturating_sub(cpu0);
    sent.paced_wall_ns = mono_ns().saturating_sub(wall0);
    sent.paced_copy_cpu_ns = publisher.paced_copy_cpu_ns();
    Ok(sent)
}

/// CPU of both processes over the 30 Hz phase.
#[derive(Clone, Copy)]
struct PacedCpu {
    us_per_frame: f64,
    percent: f64,
    copy_us_per_frame: f64,
    transport_percent: f64,
}

fn us(ns: Option<u64>) -> Option<f64> {
    ns.map(|v| v as f64 / 1e3)
}

fn combine(
    transport: Transport,
    w: u32,
    h: u32,
    publisher: &dyn Publish,
    sent: &Sent,
    r: &PeerReport,
) -> ResultRow {
    let received = r.latency.received + r.throughput.received + r.paced.received;
    let total_sent = sent.latency + sent.throughput + sent.paced;
    let pairs_per_s = r.throughput.last_recv_ns.and_then(|last| {
        let span = last.saturating_sub(sent.throughput_start_ns) as f64 / 1e9;
        (span > 0.0).then(|| r.throughput.received as f64 / span)
    });
    let paced = match r.paced_cpu_ns {
        Some(peer_cpu) if sent.paced > 0 && sent.paced_wall_ns > 0 => {
            let (frames, wall) = (sent.paced as f64, sent.paced_wall_ns as f64);
            let total = (sent.paced_cpu_ns + peer_cpu) as f64;
            let copy = sent.paced_copy_cpu_ns as f64;
            Some(PacedCpu {
                us_per_frame: total / 1e3 / frames,
                percent: 100.0 * total / wall,
                copy_us_per_frame: copy / 1e3 / frames,
                transport_percent: 100.0 * (total - copy).max(0.0) / wall,
            })
        }
        _ => None,
    };
    let zero_copy = transport.carries_payload().then(|| {
        let same = match (publisher.payload_mapping(), &r.mapping) {
            (Some(p), Some(s)) => p.same_shared_object(s),
            _ => false,
        };
        same && r.all_in_shared_object && r.shm_claim != Some(false)
    });
    ResultRow {
        p50_us: us(r.latency.latency.p50_ns),
        p99_us: us(r.latency.latency.p99_ns),
        pairs_per_s,
        zero_copy,
        samples: r.latency.latency.count,
        drops: total_sent.saturating_sub(received),
        cpu_us_per_frame_30hz: paced.map(|p| p.us_per_frame),
        cpu_percent_30hz: paced.map(|p| p.percent),
        copy_us_per_frame_30hz: paced.map(|p| p.copy_us_per_frame),
        transport_cpu_percent_30hz: paced.map(|p| p.transport_percent),
        p50_us_30hz: us(r.paced.latency.p50_ns),
        p99_us_30hz: us(r.paced.latency.p99_ns),
        sent: total_sent,
        received,
        checksum_errors: r.checksum_errors,
        payload_mapping: r.mapping.as_ref().map(|m| {
            let kind = if m.shared { "shared" } else { "private" };
            let path = if m.path.is_empty() {
                "[anonymous]"
            } else {
                &m.path
            };
            format!("{path} ({kind})")
        }),
        error: (!r.ended).then(|| "the peer never saw the end marker".to_string()),
        ..ResultRow::new(transport, format!("{w}x{h}"))
    }
}
