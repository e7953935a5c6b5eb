//! What the benchmark reports: the machine, the method, one row per transport and
//! resolution, and the targets checked against the rows.

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use crate::Transport;

/// The machine the figures come from (they mean little without it).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Machine {
    pub cpu_model: String,
    pub logical_cpus: usize,
    pub kernel: String,
    /// 1-minute load average before and after the run: other work skews the figures.
    pub loadavg_start: Option<f64>,
    pub loadavg_end: Option<f64>,
}

fn read_trimmed(path: &str) -> String {
    std::fs::read_to_string(path)
        .map(|s| s.trim().to_string())
        .unwrap_or_default()
}

pub(crate) fn loadavg() -> Option<f64> {
    read_trimmed("/proc/loadavg")
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

impl Machine {
    /// This machine, now: CPU model and count, kernel, load average.
    pub fn probe() -> Self {
        let cpuinfo = read_trimmed("/proc/cpuinfo");
        let cpu_model = cpuinfo
            .lines()
            .find_map(|l| {
                let (key, value) = l.split_once(':')?;
                (key.trim() == "model name").then(|| value.trim().to_string())
            })
            .unwrap_or_default();
        Self {
            cpu_model,
            logical_cpus: std::thread::available_parallelism().map_or(0, |n| n.get()),
            kernel: read_trimmed("/proc/sys/kernel/osrelease"),
            loadavg_start: loadavg(),
            loadavg_end: None,
        }
    }
}

/// How the figures were taken.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Settings {
    pub seconds_per_case: f64,
    pub latency_frames_max: usize,
    pub latency_pace_us: u64,
    pub paced_hz: f64,
    pub rounds: usize,
    /// Publisher and subscriber CPUs, when pinned (`--pin-cpus`).
    pub pin_cpus: Option<[usize; 2]>,
    pub method: Vec<String>,
}

/// One transport at one resolution.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ResultRow {
    pub transport: Transport,
    /// `WIDTHxHEIGHT` of each image of the pair.
    pub resolution: String,
    /// Publish -> receive latency, paced sends, receiver idle in between.
    pub p50_us: Option<f64>,
    pub p99_us: Option<f64>,
    /// Pairs the subscriber received per second with the publisher sending flat out.
    pub pairs_per_s: Option<f64>,
    /// Established by address lookup in both processes; null where there is no payload.
    pub zero_copy: Option<bool>,
    /// Latency samples behind p50/p99.
    pub samples: u64,
    /// Sent but never received (safe overflow, coalesced wake-ups), all phases.
    pub drops: u64,
    pub cpu_us_per_frame_30hz: Option<f64>,
    pub cpu_percent_30hz: Option<f64>,
    /// Part of `cpu_us_per_frame_30hz` that is the publisher's one copy into the sample.
    pub copy_us_per_frame_30hz: Option<f64>,
    /// `cpu_percent_30hz` without that copy: what the transport itself costs.
    pub transport_cpu_percent_30hz: Option<f64>,
    pub p50_us_30hz: Option<f64>,
    pub p99_us_30hz: Option<f64>,
    pub sent: u64,
    pub received: u64,
    pub checksum_errors: u64,
    /// The mapping the subscriber read the images from.
    pub payload_mapping: Option<String>,
    /// Rounds the case ran; figures are medians over them, counts sums.
    pub rounds: usize,
    /// `p99_us` of every round, in the order they ran.
    pub p99_us_rounds: Vec<Option<f64>>,
    /// `p99_us_30hz` of every round.
    pub p99_us_30hz_rounds: Vec<Option<f64>>,
    /// Why the case failed (every round failed: the first failure); figures are then
    /// empty.
    pub error: Option<String>,
}

impl ResultRow {
    /// A row with no figures yet.
    pub fn new(transport: Transport, resolution: String) -> Self {
        Self {
            transport,
            resolution,
            p50_us: None,
            p99_us: None,
            pairs_per_s: None,
            zero_copy: None,
            samples: 0,
            drops: 0,
            cpu_us_per_frame_30hz: None,
            cpu_percent_30hz: None,
            copy_us_per_frame_30hz: None,
            transport_cpu_percent_30hz: None,
            p50_us_30hz: None,
            p99_us_30hz: None,
            sent: 0,
            received: 0,
            checksum_errors: 0,
            payload_mapping: None,
            rounds: 0,
            p99_us_rounds: Vec::new(),
            p99_us_30hz_rounds: Vec::new(),
            error: None,
        }
    }
}

/// One of the targets, checked (reported, never asserted).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TargetCheck {
    pub target: String,
    pub resolution: String,
    pub value: Option<f64>,
    pub limit: f64,
    pub met: Option<bool>,
}

/// Everything one run found; serialized, the `--json` form.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IpcReport {
    pub machine: Machine,
    pub settings: Settings,
    pub results: Vec<ResultRow>,
    pub targets: Vec<TargetCheck>,
}

fn row<'a>(rows: &'a [ResultRow], transport: Transport, res: &str) -> Option<&'a ResultRow> {
    rows.iter()
        .find(|r| r.transport == transport && r.resolution == res)
}

/// The targets: iceoryx2 p99 < 50 µs awake; event-driven p99 within 2x the
/// wake-up floor; >= 1,000 pairs/s; < 1 % of a core at 30 Hz (event-driven: the
/// polling subscriber spins by design).
pub(crate) fn check_targets(rows: &[ResultRow], resolutions: &[String]) -> Vec<TargetCheck> {
    let mut out = Vec::new();
    let mut push = |target: &str, res: &str, value: Option<f64>, limit: f64, below: bool| {
        let met = value.map(|v| if below { v < limit } else { v >= limit });
        out.push(TargetCheck {
            target: target.to_string(),
            resolution: res.to_string(),
            value,
            limit,
            met,
        });
    };
    for res in resolutions {
        let poll = row(rows, Transport::Iceoryx2Poll, res);
        let event = row(rows, Transport::Iceoryx2Event, res);
        let floor = row(rows, Transport::EventfdFloor, res);
        let dgram = row(rows, Transport::UnixDgramFloor, res);
        push(
            "iceoryx2_poll p99_us < 50 (subscriber awake)",
            res,
            poll.and_then(|r| r.p99_us),
            50.0,
            true,
        );
        // Round by round (event and floor ran seconds apart), then the median ratio: a
        // burst of load in one round cannot pass for a property of one transport.
        let ratio = |floor: Option<&ResultRow>, f: fn(&ResultRow) -> &Vec<Option<f64>>| {
            let (e, fl) = (f(event?), f(floor?));
            crate::measure::median(e.iter().zip(fl).map(|(e, fl)| match (e, fl) {
                (Some(e), Some(fl)) if *fl > 0.0 => Some(e / fl),
                _ => None,
            }))
        };
        // "within 2x" includes 2x itself: compare against a hair above it.
        push(
            "iceoryx2_event p99 / eventfd_floor p99 <= 2",
            res,
            ratio(floor, |r| &r.p99_us_rounds),
            2.0 + 1e-9,
            true,
        );
        push(
            "  same, at 30 Hz (p99_us_30hz)",
            res,
            ratio(floor, |r| &r.p99_us_30hz_rounds),
            2.0 + 1e-9,
            true,
        );
        // Not an issue target: the same against the primitive iceoryx2 wakes with, i.e.
        // what iceoryx2 itself adds.
        push(
            "  vs unix_dgram_floor (iceoryx2's primitive)",
            res,
            ratio(dgram, |r| &r.p99_us_rounds),
            2.0 + 1e-9,
            true,
        );
        for r in [poll, event].into_iter().flatten() {
            let name = format!("{} pairs_per_s >= 1000", r.transport);
            push(&name, res, r.pairs_per_s, 1000.0, false);
        }
        push(
            "iceoryx2_event transport_cpu_percent_30hz < 1",
            res,
            event.and_then(|r| r.transport_cpu_percent_30hz),
            1.0,
            true,
        );
        push(
            "  same, with the one copy (cpu_percent_30hz)",
            res,
            event.and_then(|r| r.cpu_percent_30hz),
            1.0,
            true,
        );
    }
    out
}

fn num(v: Option<f64>, decimals: usize) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.decimals$}"))
}

impl IpcReport {
    /// The human table (what `doorslam bench ipc` prints without `--json`).
    pub fn table(&self) -> String {
        let m = &self.machine;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "doorslam bench ipc: {} x {}, Linux {}, load {} -> {}; {} s per phase, {} round(s), {}",
            m.logical_cpus,
            m.cpu_model,
            m.kernel,
            num(m.loadavg_start, 2),
            num(m.loadavg_end, 2),
            self.settings.seconds_per_case,
            self.settings.rounds,
            match self.settings.pin_cpus {
                Some([a, b]) => format!("publisher pinned to CPU {a}, subscriber to CPU {b}"),
                None => "processes placed by the scheduler".to_string(),
            }
        );
        let _ = writeln!(
            s,
            "{:<16} {:>9} {:>7} {:>7} {:>8} {:>5} {:>7} {:>6} {:>9} {:>8} {:>7} {:>7} {:>8}",
            "transport",
            "pair",
            "p50 µs",
            "p99 µs",
            "pairs/s",
            "0copy",
            "samples",
            "drops",
            "µs/fr@30",
            "copy µs",
            "%CPU@30",
            "%xport",
            "p99@30"
        );
        for r in &self.results {
            let zc = match r.zero_copy {
                Some(true) => "yes",
                Some(false) => "no",
                None => "-",
            };
            let _ = writeln!(
                s,
                "{:<16} {:>9} {:>7} {:>7} {:>8} {:>5} {:>7} {:>6} {:>9} {:>8} {:>7} {:>7} {:>8}",
                r.transport,
                r.resolution,
                num(r.p50_us, 1),
                num(r.p99_us, 1),
                num(r.pairs_per_s, 0),
                zc,
                r.samples,
                r.drops,
                num(r.cpu_us_per_frame_30hz, 1),
                num(r.copy_us_per_frame_30hz, 1),
                num(r.cpu_percent_30hz, 2),
                num(r.transport_cpu_percent_30hz, 2),
                num(r.p99_us_30hz, 1),
            );
            if let Some(err) = &r.error {
                let _ = writeln!(s, "  error: {err}");
            }
        }
        let _ = writeln!(s, "p99 µs of each round (the table shows medians):");
        for r in self.results.iter().filter(|r| r.p99_us_rounds.len() > 1) {
            let rounds: Vec<String> = r.p99_us_rounds.iter().map(|v| num(*v, 1)).collect();
            let _ = writeln!(
                s,
                "  {:<16} {:>9}  {}",
                r.transport,
                r.resolution,
                rounds.join("  ")
            );
        }
        let _ = writeln!(
            s,
            "zero-copy evidence (mapping the subscriber read the images from):"
        );
        for r in &self.results {
            if let Some(m) = &r.payload_mapping {
                let _ = writeln!(s, "  {:<16} {:>9}  {m}", r.transport, r.resolution);
            }
        }
        let _ = writeln!(s, "targets (reported, not asserted):");
        for t in &self.targets {
            let verdict = match t.met {
                Some(true) => "met",
                Some(false) => "NOT met",
                None => "n/a",
            };
            let _ = writeln!(
                s,
                "  {:<46} {:>9}  value {:>9}  {verdict}",
                t.target,
                t.resolution,
                num(t.value, 2)
            );
        }
        s
    }
}
