//! The subscriber process of the benchmark: a real second process (the caller's binary
//! re-executed, see [`crate::PeerCommand`]) that receives pairs, reads them in place, and
//! reports.
//!
//! It speaks to the publisher on its stdout, one line each: `ready` once subscribed,
//! `warm` once warm-up frames flow (over SHM, where the transport has it), and
//! `report <json>` after the end marker (or its deadline).

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::error::{BenchError, Result};
use crate::measure::{checksum, cpu_ns, mapping_of, test_image, LatencySummary, Mapping, Maps};
use crate::transports::{open_receiver, Delivered, PeerEndpoint, Phase, Transport};

/// What the peer needs to know, from its command line ([`PeerSpec::to_args`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PeerSpec {
    pub transport: Transport,
    pub width: u32,
    pub height: u32,
    pub endpoint: PeerEndpoint,
    /// The peer gives up and reports after this long, whatever happens.
    pub deadline: Duration,
    /// Pin this process to one CPU.
    pub pin_cpu: Option<usize>,
}

impl PeerSpec {
    /// The peer's command line, after [`crate::PeerCommand`]'s own arguments: `--transport
    /// NAME --width W --height H --name NAME --deadline-s SECONDS`, then `--connect
    /// ENDPOINT`, `--fd FD` and `--pin-cpu CPU` where set. The caller's subcommand parses
    /// these flags back into a [`PeerSpec`] and calls [`run_peer`].
    pub fn to_args(&self) -> Vec<String> {
        let mut args: Vec<String> = vec![
            "--transport".into(),
            self.transport.name().into(),
            "--width".into(),
            self.width.to_string(),
            "--height".into(),
            self.height.to_string(),
            "--name".into(),
            self.endpoint.name.clone(),
            "--deadline-s".into(),
            // Shortest round-trip spelling: parsed back, it is the same duration.
            self.deadline.as_secs_f64().to_string(),
        ];
        if let Some(connect) = &self.endpoint.connect {
            args.extend(["--connect".into(), connect.clone()]);
        }
        if let Some(fd) = self.endpoint.fd {
            args.extend(["--fd".into(), fd.to_string()]);
        }
        if let Some(cpu) = self.pin_cpu {
            args.extend(["--pin-cpu".into(), cpu.to_string()]);
        }
        args
    }
}

/// One phase as the peer saw it.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct PhaseReport {
    pub received: u64,
    pub latency: LatencySummary,
    pub first_recv_ns: Option<u64>,
    pub last_recv_ns: Option<u64>,
}

/// The peer's findings, sent back as one JSON line.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct PeerReport {
    pub latency: PhaseReport,
    pub throughput: PhaseReport,
    pub paced: PhaseReport,
    /// This process's CPU time from the first 30 Hz pair to the end marker.
    pub paced_cpu_ns: Option<u64>,
    /// Pairs whose checksum was computed in place (latency and throughput phases).
    pub checked: u64,
    pub checksum_errors: u64,
    /// The mapping the first checked pair was read from.
    pub mapping: Option<Mapping>,
    /// Every checked image lay in a shared mapping of that same memory object.
    pub all_in_shared_object: bool,
    /// The transport's own claim (Zenoh `as_shm`), true only if made for every pair.
    pub shm_claim: Option<bool>,
    /// The end marker arrived (false: the deadline ended the run).
    pub ended: bool,
}

#[derive(Default)]
struct PhaseStats {
    received: u64,
    latencies_ns: Vec<u64>,
    first_recv_ns: Option<u64>,
    last_recv_ns: Option<u64>,
}

impl PhaseStats {
    fn record(&mut self, d: &Delivered<'_>) {
        self.received += 1;
        if let Some(stamp) = d.stamp_ns {
            self.latencies_ns.push(d.recv_ns.saturating_sub(stamp));
        }
        self.first_recv_ns.get_or_insert(d.recv_ns);
        self.last_recv_ns = Some(d.recv_ns);
    }

    fn report(self) -> PhaseReport {
        PhaseReport {
            received: self.received,
            latency: LatencySummary::from_samples(self.latencies_ns),
            first_recv_ns: self.first_recv_ns,
            last_recv_ns: self.last_recv_ns,
        }
    }
}

struct Stats {
    carries_payload: bool,
    expected: (u64, u64),
    warm_frames: u64,
    warm_said: bool,
    phases: [PhaseStats; 3],
    paced_cpu_start: Option<u64>,
    paced_cpu_ns: Option<u64>,
    maps: Option<Maps>,
    report: PeerReport,
}

impl Stats {
    fn new(spec: &PeerSpec) -> Self {
        let (w, h) = (spec.width, spec.height);
        Self {
            carries_payload: spec.transport.carries_payload(),
            expected: (
                checksum(&test_image(w, h, 0)),
                checksum(&test_image(w, h, 1)),
            ),
            warm_frames: 0,
            warm_said: false,
            phases: Default::default(),
            paced_cpu_start: None,
            paced_cpu_ns: None,
            maps: None,
            report: PeerReport {
                all_in_shared_object: true,
                ..PeerReport::default()
            },
        }
    }

    fn on_frame(&mut self, d: &Delivered<'_>) {
        let slot = match d.phase {
            Phase::Warmup => return self.on_warmup(d),
            Phase::End => {
                if !self.report.ended {
                    self.report.ended = true;
                    self.paced_cpu_ns = self.paced_cpu_start.map(|s| cpu_ns().saturating_sub(s));
                }
                return;
            }
            Phase::Latency => 0,
            Phase::Throughput => 1,
            Phase::Paced => {
                self.paced_cpu_start.get_or_insert_with(cpu_ns);
                2
            }
        };
        self.phases[slot].record(d);
        if let Some(claim) = d.shm_claim {
            self.report.shm_claim = Some(self.report.shm_claim.unwrap_or(true) && claim);
        }
        // The 30 Hz phase measures the transport's CPU cost, so it does not read images.
        if self.carries_payload && d.phase != Phase::Paced {
            self.check_in_place(d);
        }
    }

    fn on_warmup(&mut self, d: &Delivered<'_>) {
        self.warm_frames += 1;
        if self.carries_payload {
            // Primes the /proc/self/maps cache outside the measured phases.
            let _ = mapping_of(&mut self.maps, d.left);
        }
        // Zenoh starts on the network path and switches to SHM once probed: wait for a
        // SHM frame (or give up after 50 and let the report say it never came).
        let steady = d.shm_claim != Some(false) || self.warm_frames >= 50;
        if !self.warm_said && self.warm_frames >= 3 && steady {
            self.warm_said = true;
            println!("warm");
        }
    }

    /// Reads both images where they lie (a checksum over every byte, no copy) and notes
    /// which memory object they lie in.
    fn check_in_place(&mut self, d: &Delivered<'_>) {
        self.report.checked += 1;
        if (checksum(d.left), checksum(d.right)) != self.expected {
            self.report.checksum_errors += 1;
        }
        let left = mapping_of(&mut self.maps, d.left);
        let right = mapping_of(&mut self.maps, d.right);
        if self.report.mapping.is_none() {
            self.report.mapping = left.clone();
        }
        let in_object = |m: &Option<Mapping>, first: &Option<Mapping>| match (m, first) {
            (Some(m), Some(first)) => m.same_shared_object(first),
            _ => false,
        };
        let first = &self.report.mapping;
        if !(in_object(&left, first) && in_object(&right, first)) {
            self.report.all_in_shared_object = false;
        }
    }

    fn finish(mut self) -> PeerReport {
        let [latency, throughput, paced] = std::mem::take(&mut self.phases);
        self.report.latency = latency.report();
        self.report.throughput = throughput.report();
        self.report.paced = paced.report();
        self.report.paced_cpu_ns = self.paced_cpu_ns;
        if self.report.checked == 0 {
            self.report.all_in_shared_object = false;
        }
        self.report
    }
}

/// Runs the peer until the end marker or the deadline, then prints its report. Its
/// stdout is the protocol with the publisher (`ready`, `warm`, `report <json>`), so
/// nothing else may print there.
pub fn run_peer(spec: &PeerSpec) -> Result<(), BenchError> {
    if spec.deadline.is_zero() {
        return Err(BenchError::InvalidOption {
            option: "deadline",
            reason: "must be a positive duration",
        });
    }
    if let Some(cpu) = spec.pin_cpu {
        crate::measure::pin_to_cpu(cpu).map_err(|source| BenchError::PinCpu {
            process: "subscriber",
            cpu,
            source,
        })?;
    }
    let mut receiver = open_receiver(spec.transport, &spec.endpoint)?;
    let mut stats = Stats::new(spec);
    println!("ready");
    let deadline = Instant::now() + spec.deadline;
    while !stats.report.ended && Instant::now() < deadline {
        receiver.receive(Duration::from_millis(50), &mut |d| stats.on_frame(d))?;
    }
    let report = stats.finish();
    let json =
        serde_json::to_string(&report).map_err(|e| BenchError::PeerReport("serialize", e))?;
    println!("report {json}");
    Ok(())
}
