//! Whether a run was real time on its machine, and what the CPU went to: so that a run on
//! a machine too small (or shared with other work) says so instead of reporting the
//! figures of a degraded run as the system's.
//!
//! - **Frames**: each robot's camera replay says how many frames it published and how many
//!   it skipped because their time had passed (`camera.json`); the front-end says how many
//!   it processed (`frontend.json`). Frames published but never processed were overwritten
//!   in the lossy frame service while the VO was busy. A robot keeps up when at most
//!   [`MAX_LOST_FRACTION`] of its frames are lost that way (for a restarted robot, the
//!   frames of the time it was dead are not counted), and the VO's 90th-percentile time
//!   per frame and the camera's 90th-percentile lateness are within a frame period.
//! - **CPU** ([`super::cpu`]): per robot and per process, the demo's own (rendering), and
//!   the whole machine's busy time over the flight: what the robots did not use was the
//!   demo or other work on the machine.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use super::{read_json, CpuLog};

/// Most frames a robot may lose (of those due while it ran) and still count as keeping up.
pub const MAX_LOST_FRACTION: f64 = 0.01;
/// Other work above this share of the machine during the flight makes it a shared run.
pub const SHARED_FRACTION: f64 = 0.1;

/// One robot's frames and latencies.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RobotRealtime {
    /// Frames of its flight.
    pub frames: u64,
    /// From its (last) camera replay: frames published, frames skipped because their time
    /// had passed, how late frames went out (ms).
    pub camera_published: Option<u64>,
    pub camera_skipped: Option<u64>,
    pub camera_late_ms_p90: Option<f64>,
    pub camera_late_ms_max: Option<f64>,
    /// Frames its (last) front-end processed.
    pub vo_frames: Option<u64>,
    /// Published but never processed (overwritten while the VO was busy).
    pub vo_missed: Option<u64>,
    /// The VO's time per frame (ms, wall and CPU of its thread).
    pub vo_ms_median: Option<f64>,
    pub vo_ms_p90: Option<f64>,
    pub vo_cpu_ms_median: Option<f64>,
    /// Frames lost while it ran (skipped by the camera unless it was restarted, and
    /// missed by the VO), as a fraction of its frames.
    pub lost_fraction: Option<f64>,
    pub kept_up: bool,
}

/// The real-time check of a run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Realtime {
    pub period_ms: f64,
    pub kept_up: bool,
    pub per_robot: BTreeMap<String, RobotRealtime>,
    /// One sentence: kept up, or what was lost.
    pub verdict: String,
}

/// The check from every robot's `camera.json` and `frontend.json`; `starts[r]` is how
/// many times robot r's processes were started.
pub fn check(
    out: &Path,
    letters: &[String],
    frames: &[usize],
    rate_hz: f64,
    starts: &[u32],
) -> Realtime {
    let period_ms = 1e3 / rate_hz;
    let mut per_robot = BTreeMap::new();
    let mut problems = Vec::new();
    let (mut all_frames, mut all_lost) = (0u64, 0u64);
    let mut worst_vo: f64 = 0.0;
    for (r, name) in letters.iter().enumerate() {
        let camera = read_json(&out.join(name).join("camera.json"));
        let frontend = read_json(&out.join(name).join("frontend.json"));
        let u = |v: &Option<serde_json::Value>, k: &str| v.as_ref()?.get(k)?.as_u64();
        let f = |v: &Option<serde_json::Value>, k: &str| v.as_ref()?.get(k)?.as_f64();
        let total = frames.get(r).copied().unwrap_or(0) as u64;
        let mut x = RobotRealtime {
            frames: total,
            camera_published: u(&camera, "published"),
            camera_skipped: u(&camera, "skipped"),
            camera_late_ms_p90: f(&camera, "late_ms_p90"),
            camera_late_ms_max: f(&camera, "late_ms_max"),
            vo_frames: u(&frontend, "frames"),
            vo_ms_median: f(&frontend, "ms_per_frame_median"),
            vo_ms_p90: f(&frontend, "ms_per_frame_p90"),
            vo_cpu_ms_median: f(&frontend, "cpu_ms_per_frame_median"),
            ..RobotRealtime::default()
        };
        x.vo_missed = x
            .camera_published
            .zip(x.vo_frames)
            .map(|(p, v)| p.saturating_sub(v));
        let restarted = starts.get(r).copied().unwrap_or(1) > 1;
        // A restarted replay skips the frames of the time the robot was dead: not lost
        // to a slow machine.
        let skipped = if restarted { Some(0) } else { x.camera_skipped };
        let lost = skipped.zip(x.vo_missed).map(|(s, m)| s + m);
        let due = if restarted {
            x.camera_published.unwrap_or(0)
        } else {
            total
        };
        x.lost_fraction = lost.map(|l| l as f64 / due.max(1) as f64);
        let mut why = Vec::new();
        match x.lost_fraction {
            None => why.push("no camera.json or frontend.json".to_string()),
            Some(l) if l > MAX_LOST_FRACTION => why.push(format!(
                "lost {:.1} % of its frames (camera skipped {}, VO missed {})",
                100.0 * l,
                skipped.unwrap_or(0),
                x.vo_missed.unwrap_or(0)
            )),
            _ => {}
        }
        if let Some(p90) = x.vo_ms_p90.filter(|p| *p > period_ms) {
            why.push(format!("VO p90 {p90:.0} ms per frame"));
        }
        if let Some(late) = x.camera_late_ms_p90.filter(|p| *p > period_ms) {
            why.push(format!("camera p90 {late:.0} ms late"));
        }
        x.kept_up = why.is_empty();
        if !why.is_empty() {
            problems.push(format!("{name}: {}", why.join(", ")));
        }
        all_frames += due;
        all_lost += lost.unwrap_or(0);
        worst_vo = worst_vo.max(x.vo_ms_p90.unwrap_or(0.0));
        per_robot.insert(name.clone(), x);
    }
    let kept_up = problems.is_empty() && !per_robot.is_empty();
    let verdict = if kept_up {
        format!(
            "real time: every robot kept up ({} of {all_frames} frames lost, VO p90 at most {worst_vo:.0} ms per frame, frame period {period_ms:.0} ms)",
            all_lost
        )
    } else {
        format!(
            "NOT real time on this machine ({}): the figures describe a degraded run",
            problems.join("; ")
        )
    };
    Realtime {
        period_ms,
        kept_up,
        per_robot,
        verdict,
    }
}

/// One robot's CPU.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RobotCpu {
    pub total_s: f64,
    /// Sampled, per process (`up` and each service).
    pub per_process: BTreeMap<String, f64>,
}

/// Where the CPU went.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CpuSummary {
    /// Every robot process together, the whole run (= `durations.robots_cpu_s`).
    pub robots_s: f64,
    pub per_robot: BTreeMap<String, RobotCpu>,
    /// The demo's own process while rendering (all its threads).
    pub render_s: f64,
    pub cores: usize,
    /// Over the flight: wall seconds, the machine's busy CPU seconds, the robots' and
    /// the demo's, and the rest (other work on the machine).
    pub flight_wall_s: f64,
    pub flight_machine_busy_s: Option<f64>,
    pub flight_robots_s: f64,
    pub flight_demo_s: f64,
    pub flight_others_s: Option<f64>,
    /// Other work used more than [`SHARED_FRACTION`] of the machine during the flight:
    /// timings of this run are not the system's.
    pub machine_shared: Option<bool>,
    /// `getrusage(RUSAGE_CHILDREN)` of the demo at the end (its robots' processes that were
    /// waited for, and the network commands): the former `robots_cpu_s`, to compare.
    pub waited_children_s: f64,
}

pub fn cpu_summary(log: &CpuLog, letters: &[String]) -> CpuSummary {
    let per_robot: BTreeMap<String, RobotCpu> = letters
        .iter()
        .enumerate()
        .map(|(r, name)| {
            (
                name.clone(),
                RobotCpu {
                    total_s: log.robots_s.get(r).copied().unwrap_or(0.0),
                    per_process: log.per_process.get(r).cloned().unwrap_or_default(),
                },
            )
        })
        .collect();
    let others = log
        .flight_machine_busy_s
        .map(|busy| (busy - log.flight_robots_s - log.flight_demo_s).max(0.0));
    let capacity = log.flight_wall_s * log.cores.max(1) as f64;
    CpuSummary {
        robots_s: log.robots_s.iter().sum(),
        per_robot,
        render_s: log.render_s,
        cores: log.cores,
        flight_wall_s: log.flight_wall_s,
        flight_machine_busy_s: log.flight_machine_busy_s,
        flight_robots_s: log.flight_robots_s,
        flight_demo_s: log.flight_demo_s,
        flight_others_s: others,
        machine_shared: others.map(|o| capacity > 0.0 && o > SHARED_FRACTION * capacity),
        waited_children_s: log.waited_children_s,
    }
}
