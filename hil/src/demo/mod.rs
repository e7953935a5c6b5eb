//! `doorslam demo`: a team of robots flying through the synthetic town (or a dataset split
//! into robots), each robot a host of its own running its full set of services, and a
//! report people can look at.
//!
//! What happens, in order:
//! 1. **World**: the team's flights are planned and rendered into `<out>/world/` (one
//!    KITTI-layout sequence per robot, `events.csv` of who is in radio range when,
//!    `closures.csv` of true overlaps and aliased look-alikes); with `dataset`, the
//!    dataset is split into consecutive parts instead (its images are not copied).
//! 2. **Network**: as root, every robot gets a network namespace with its own address on
//!    a shared bridge ([`crate::netns`]); radio range follows `events.csv` (a pair out of
//!    range drops each other's packets). Not root: every robot on the loopback with
//!    explicit peer lists and no range changes (said in the log and the report).
//! 3. **Robots**: `doorslam up` per robot (camera replay → frontend → place-recognition →
//!    backend, and team), its configuration in `<out>/<robot>/robot.toml`, its logs in
//!    `<out>/<robot>/robot.log`. All replays share one clock (`start_unix_ms`), so a robot
//!    restarted after `kill` resumes where the flight is.
//! 4. **Flight**: range events and the kill/restart are applied on time; every robot's
//!    status is sampled for the progress lines and the bytes-over-time plot.
//! 5. **Back at base**: after the flight every pair is put in range (the drones landed
//!    together) until every robot's distributed back-end has converged on the solver's
//!    latest solve, with nothing left unacknowledged on the radio (or `settle_s`).
//! 6. **Report** ([`report`]): `report.md`, `summary.json`, plots as PNG and SVG; then the
//!    run as ROS 2 messages, `run.mcap` (`doorslam_ros2::record`).
//!
//! Nothing here stands in for a service: if one is missing, its process fails, `up`
//! gives up on it and the demo stops naming it.

pub mod config;
pub mod cpu;
mod markdown;
pub mod plots;
pub mod realtime;
pub mod report;
pub mod robot;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::flights::{FlightError, RangeEventKind};
use crate::netns::{Net, NetError};

pub use config::{DemoConfig, Kill};
pub use robot::{RobotSnapshot, RobotState};

/// A JSON file a robot's service wrote, or `None` while it is absent or half written
/// (services rewrite their files as they run; the demo reads what is there).
fn read_json(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Failures of the demo; each says which piece or file.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error("demo config: {0}")]
    Config(String),
    #[error("{path}: {reason}")]
    Io { path: PathBuf, reason: String },
    #[error(transparent)]
    Flight(#[from] FlightError),
    #[error(transparent)]
    Net(#[from] NetError),
    #[error("robot {robot}: {reason} (its log: {log})")]
    Robot {
        robot: char,
        reason: String,
        log: PathBuf,
    },
    #[error("report: {0}")]
    Report(String),
}

pub(crate) fn io_err(path: &Path) -> impl Fn(std::io::Error) -> DemoError + '_ {
    move |e| DemoError::Io {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

/// Where the run is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Rendering,
    Starting,
    Flying,
    AtBase,
    Stopping,
    Reporting,
}

/// What a person watching sees, a few times per second.
#[derive(Debug, Clone)]
pub struct Snapshot {
    pub phase: Phase,
    /// Seconds of flight time (simulation time), once flying.
    pub flight_s: f64,
    pub flight_total_s: f64,
    /// Rendered frames while rendering.
    pub rendered: (usize, usize),
    pub robots: Vec<RobotSnapshot>,
    /// Something worth a line of its own (a range change, a kill).
    pub note: Option<String>,
}

/// One entry of the rendezvous timeline.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TimelineEvent {
    /// Flight time in seconds.
    pub t_s: f64,
    pub event: String,
    pub robots: Vec<String>,
}

/// What the run measured while it ran (the report adds the rest from the files).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RunLog {
    pub mode: String,
    pub render_s: f64,
    pub flight_s: f64,
    pub settle_s: f64,
    pub converged_at_base: bool,
    /// Flight time, then bytes sent so far per robot (ledger), sampled once a second.
    pub bytes_over_time: Vec<(f64, Vec<u64>)>,
    pub timeline: Vec<TimelineEvent>,
    /// CPU of the robots' processes and of the machine ([`cpu`]).
    pub cpu: CpuLog,
    /// Random loss between robots, when asked for: (probability, packets from other
    /// robots received, of them dropped).
    pub drop: Option<(f64, u64, u64)>,
    /// Times each robot's processes were started.
    pub starts: Vec<u32>,
    /// How the robots' link was secured.
    pub security: SecuritySummary,
    /// `--ros2`: each robot's ROS 2 endpoint (plain TCP), in robot order.
    pub ros2_endpoints: Vec<String>,
}

/// Where one `--kill` is in the run.
#[derive(Debug, Clone, Copy)]
enum KillState {
    Pending,
    /// Killed at this instant, not yet restarted.
    Down(Instant),
    Restarted,
}

/// How the team link of the run was secured (`summary.json` `security`).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SecuritySummary {
    /// `mutual TLS + access control`, or `none (--insecure)`.
    pub mode: String,
    pub tls: bool,
    /// The team CA and the robots' certificates, relative to the run folder.
    pub certificates: Option<String>,
    /// Robot ids the access control lets in, each only as itself.
    pub roster: Vec<String>,
    /// Certificate validity policy: `clockless` (1970 to 9999, for robots without a
    /// synchronized clock), or none without TLS.
    pub validity: Option<String>,
}

impl SecuritySummary {
    fn insecure() -> Self {
        Self {
            mode: "none (--insecure): plain TCP, any host on the network may publish".into(),
            ..Self::default()
        }
    }

    fn secure(tls: &config::DemoTls) -> Self {
        Self {
            mode: "mutual TLS + access control".into(),
            tls: true,
            certificates: Some("certs/".into()),
            roster: tls.roster.clone(),
            validity: Some("clockless".into()),
        }
    }
}

/// CPU time, measured per process ([`cpu::CpuMeter`]) and for the machine.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct CpuLog {
    /// Per robot: CPU seconds of all its processes over the run.
    pub robots_s: Vec<f64>,
    /// Per robot: sampled CPU seconds per process (`up`, each service).
    pub per_process: Vec<std::collections::BTreeMap<String, f64>>,
    /// CPU seconds of the demo's own process while rendering.
    pub render_s: f64,
    /// Cores of the machine.
    pub cores: usize,
    /// Over the flight (wall seconds): busy CPU of the whole machine, and of the robots'
    /// processes (sampled); the rest is the demo itself and whatever else ran.
    pub flight_wall_s: f64,
    pub flight_machine_busy_s: Option<f64>,
    pub flight_robots_s: f64,
    pub flight_demo_s: f64,
    /// `getrusage(RUSAGE_CHILDREN)` at the end: every waited-for child and its waited-for
    /// children (the robots' `up` and services, the `ip`/`nft` commands), to compare.
    pub waited_children_s: f64,
}

/// At base, the team is settled once converged and quiet this long...
const QUIET: Duration = Duration::from_secs(4);
/// ... and not before the robots had this long to find each other again (scouting,
/// sessions re-opened after the flight's cuts).
const MEETING: Duration = Duration::from_secs(6);
/// A team still split into several frames (a restarted robot that has not merged again,
/// a lossy radio's sessions that did not get through yet) is settled only once quiet this
/// long: the meeting at base is its chance to merge.
const QUIET_SPLIT: Duration = Duration::from_secs(15);

fn letter(r: usize) -> char {
    crate::flights::robot_name(r)
}

/// Team link sessions opened since the last snapshot (a meeting counter that grew), as
/// timeline entries: the rendezvous the robots really had, next to the radio's ranges.
fn log_sessions(log: &mut RunLog, t_s: f64, before: &[RobotSnapshot], now: &[RobotSnapshot]) {
    for (old, new) in before.iter().zip(now) {
        for (peer, &count) in &new.meetings {
            let was = old.meetings.get(peer).copied().unwrap_or(0);
            // Each pair once, from its lower robot (a restarted robot's counters start
            // again: only growth counts).
            if count > was && new.name.to_string() < *peer {
                log.timeline.push(TimelineEvent {
                    t_s,
                    event: format!("rendezvous: team link session {count}"),
                    robots: vec![new.name.to_string(), peer.clone()],
                });
            }
        }
    }
}

/// Every robot's team link has every other robot present right now.
fn all_pairs_present(robots: &[RobotSnapshot]) -> bool {
    robots.iter().all(|x| {
        robots
            .iter()
            .filter(|y| y.name != x.name)
            .all(|y| x.present.contains(&y.name.to_string()))
    })
}

/// Every robot's back-end reports one and the same anchor: the team estimate is one frame.
fn in_one_frame(robots: &[RobotSnapshot]) -> bool {
    robots
        .iter()
        .all(|r| !r.anchor.is_empty() && r.anchor == robots[0].anchor)
}

/// Nothing the team's estimate depends on is still on the radio: every team link has
/// had each message it sent a present peer acknowledged, and every robot holds the team
/// solve its parent last handed down to it (its `round` is the one the parent reports
/// for it). Both back-ends say `converged` as soon as the solver has handed its estimates
/// to its team link, so without this the run could end while the newest estimates wait
/// for a resend (up to 16 × `retransmit_ms` apart on a lossy radio, longer than
/// [`QUIET`]) and the robot below keep an older solve: a team estimate whose robots come
/// from different solves, each right in shape, misplaced against each other.
fn estimates_delivered(robots: &[RobotSnapshot]) -> bool {
    robots.iter().all(|x| {
        x.unacknowledged == 0
            && x.rounds_handed_down.iter().all(|(name, round)| {
                robots
                    .iter()
                    .find(|r| r.name.to_string() == *name)
                    .is_some_and(|r| r.round == Some(*round))
            })
    })
}

/// What [`estimates_delivered`] still waits for, for the log.
fn undelivered(robots: &[RobotSnapshot]) -> String {
    let mut what = Vec::new();
    for x in robots {
        if x.unacknowledged > 0 {
            what.push(format!("{}: {} unacknowledged", x.name, x.unacknowledged));
        }
        for (name, round) in &x.rounds_handed_down {
            let held = robots
                .iter()
                .find(|r| r.name.to_string() == *name)
                .and_then(|r| r.round);
            if held != Some(*round) {
                let held = held.map_or("none".to_string(), |h| h.to_string());
                what.push(format!(
                    "{name} holds round {held}, {} handed down {round}",
                    x.name
                ));
            }
        }
    }
    what.join(", ")
}

/// Runs the demo; `progress` is called a few times per second.
pub fn run(
    config: &DemoConfig,
    progress: &mut dyn FnMut(&Snapshot),
) -> Result<report::Summary, DemoError> {
    config.validate()?;
    if config.drop.is_some() && !crate::netns::is_root() {
        return Err(DemoError::Config(
            "drop: random loss between robots needs their network namespaces (run as root)".into(),
        ));
    }
    let out = &config.out;
    config::prepare_out(out)?;
    let mut log = RunLog::default();
    let mut snap = Snapshot {
        phase: Phase::Rendering,
        flight_s: 0.0,
        flight_total_s: 0.0,
        rendered: (0, 0),
        robots: Vec::new(),
        note: None,
    };

    // 1. The world.
    let t = Instant::now();
    let cpu_before = cpu::own_cpu_s();
    let world = config::World::prepare(config, &mut |done, total| {
        snap.rendered = (done, total);
        progress(&snap);
    })?;
    log.render_s = t.elapsed().as_secs_f64();
    log.cpu.render_s = cpu::own_cpu_s() - cpu_before;
    let n = world.robots();

    // 2. The network.
    let net = if crate::netns::is_root() {
        log.mode = "netns".into();
        Some(Net::new("dm", n, [213, 9])?)
    } else {
        log.mode = "loopback".into();
        snap.note = Some(
            "not root: every robot on the loopback, always in range (no network namespaces, \
             no radio-range cuts)"
                .into(),
        );
        progress(&snap);
        None
    };
    // Secure by default: the team's certificates, mutual TLS and the access control.
    let tls = if config.insecure {
        log.security = SecuritySummary::insecure();
        None
    } else {
        let tls = config::team_certs(out, n)?;
        log.security = SecuritySummary::secure(&tls);
        Some(tls)
    };
    let addresses: Vec<String> = (0..n)
        .map(|i| match &net {
            Some(net) => config::endpoint(net.addr(i), 7447, tls.is_some()),
            None => config::endpoint("127.0.0.1", config.base_port + i as u16, tls.is_some()),
        })
        .collect();
    if config.ros2 {
        log.ros2_endpoints = addresses.iter().map(|a| config::ros2_endpoint(a)).collect();
        // In namespaces the host joins the robots' bridge, so a router here reaches them.
        let host = match &net {
            Some(net) => format!(" (this host is {} on their network)", net.attach_host()?),
            None => String::new(),
        };
        let line = format!(
            "ROS 2: the robots publish on {}{host}: connect a router to them (README, ROS 2)",
            log.ros2_endpoints.join(", ")
        );
        snap.note = Some(match snap.note.take() {
            Some(n) => format!("{n}; {line}"),
            None => line,
        });
        progress(&snap);
    }

    // 3. The robots, on one clock that starts once they had time to open their services.
    let start_unix_ms = config::unix_ms() + (config.startup_s * 1e3) as u64;
    let mut robots = Vec::with_capacity(n);
    for r in 0..n {
        let text = config::robot_toml(
            config,
            &world,
            r,
            &addresses,
            start_unix_ms,
            net.is_some(),
            tls.as_ref(),
        );
        robots.push(robot::Robot::create(out, r, &text)?);
    }
    // Range at the start: every pair is cut before anyone listens (the events put them in
    // range on time).
    let mut in_range = vec![vec![net.is_none(); n]; n];
    if let Some(net) = &net {
        for a in 0..n {
            for b in a + 1..n {
                net.cut(a, b)?;
            }
        }
        if let Some(p) = config.drop {
            net.drop_packets(p)?;
        }
    }
    let mut meter = cpu::CpuMeter::default();
    let groups = |robots: &[robot::Robot]| -> Vec<(usize, i32)> {
        robots
            .iter()
            .enumerate()
            .filter_map(|(r, x)| Some((r, x.pgid()?)))
            .collect()
    };
    snap.phase = Phase::Starting;
    for robot in &mut robots {
        robot.start(&config.exe, net.as_ref())?;
    }
    let flight_total_s = world.duration_s();
    snap.flight_total_s = flight_total_s;
    let clock_start = Instant::now() + Duration::from_secs_f64(config.startup_s);
    let flight_time =
        |now: Instant| now.saturating_duration_since(clock_start).as_secs_f64() * config.rate;
    let mut events = world.events.iter().peekable();
    let mut kill_state = vec![KillState::Pending; config.kills.len()];
    let mut last_sample = Instant::now() - Duration::from_secs(1);
    let t_flight = Instant::now();
    let machine_before = cpu::machine_busy_s();
    let demo_before = cpu::own_cpu_s();
    snap.phase = Phase::Flying;

    // 4. The flight.
    loop {
        let now = Instant::now();
        let ft = flight_time(now);
        snap.note = None;
        while let Some(e) = events.next_if(|e| e.time_s <= ft) {
            let (a, b) = (e.robot_a, e.robot_b);
            let enter = e.kind == RangeEventKind::Enter;
            in_range[a][b] = enter;
            in_range[b][a] = enter;
            if let Some(net) = &net {
                if enter {
                    net.join(a, b)?;
                } else {
                    net.cut(a, b)?;
                }
            }
            let what = if enter { "in range" } else { "out of range" };
            log.timeline.push(TimelineEvent {
                t_s: e.time_s,
                event: what.into(),
                robots: vec![letter(a).to_string(), letter(b).to_string()],
            });
            snap.note = Some(format!(
                "{:5.1} s  {} and {} {what}",
                e.time_s,
                letter(a),
                letter(b)
            ));
        }
        for (k, state) in config.kills.iter().zip(kill_state.iter_mut()) {
            match *state {
                KillState::Pending if ft >= k.at_s => {
                    // The killed processes' last readings: what they used until now.
                    meter.sample(&groups(&robots));
                    robots[k.robot].kill()?;
                    *state = KillState::Down(now);
                    log.timeline.push(TimelineEvent {
                        t_s: ft,
                        event: "killed (every process, SIGKILL)".into(),
                        robots: vec![letter(k.robot).to_string()],
                    });
                    snap.note = Some(format!("{ft:5.1} s  robot {} killed", letter(k.robot)));
                }
                KillState::Down(at)
                    if now.duration_since(at).as_secs_f64() >= config.restart_after_s =>
                {
                    robots[k.robot].start(&config.exe, net.as_ref())?;
                    *state = KillState::Restarted;
                    log.timeline.push(TimelineEvent {
                        t_s: ft,
                        event: "restarted (journal, new epochs)".into(),
                        robots: vec![letter(k.robot).to_string()],
                    });
                    snap.note = Some(format!("{ft:5.1} s  robot {} restarted", letter(k.robot)));
                }
                _ => {}
            }
        }
        for robot in &mut robots {
            robot.check_alive()?;
        }
        meter.sample(&groups(&robots));
        snap.flight_s = ft.min(flight_total_s);
        let previous = std::mem::take(&mut snap.robots);
        snap.robots = robots.iter().map(|r| r.snapshot()).collect();
        log_sessions(&mut log, ft, &previous, &snap.robots);
        if now.duration_since(last_sample) >= Duration::from_secs(1) {
            last_sample = now;
            log.bytes_over_time
                .push((ft, snap.robots.iter().map(|r| r.bytes_sent).collect()));
        }
        progress(&snap);
        let robots_down = kill_state.iter().any(|k| matches!(k, KillState::Down(_)));
        if ft >= flight_total_s + 1.0 && !robots_down {
            break;
        }
        std::thread::sleep(Duration::from_millis(250));
    }
    log.flight_s = t_flight.elapsed().as_secs_f64();
    meter.sample(&groups(&robots));
    log.cpu.flight_wall_s = log.flight_s;
    log.cpu.flight_robots_s = meter.sampled_total_s();
    log.cpu.flight_demo_s = cpu::own_cpu_s() - demo_before;
    if let (Some((before, cores)), Some((after, _))) = (machine_before, cpu::machine_busy_s()) {
        log.cpu.cores = cores;
        log.cpu.flight_machine_busy_s = Some(after - before);
    }

    // 5. Back at base: everyone in range until the team estimate settles.
    snap.phase = Phase::AtBase;
    if let Some(net) = &net {
        for a in 0..n {
            for b in a + 1..n {
                net.join(a, b)?;
            }
        }
    }
    log.timeline.push(TimelineEvent {
        t_s: flight_total_s,
        event: "back at base: every robot in range".into(),
        robots: (0..n).map(|r| letter(r).to_string()).collect(),
    });
    let t_settle = Instant::now();
    let mut stable_since: Option<(Instant, Vec<RobotSnapshot>)> = None;
    let mut met_at_base: std::collections::BTreeSet<(String, String)> = Default::default();
    let mut waited_for_delivery = false;
    loop {
        for robot in &mut robots {
            robot.check_alive()?;
        }
        meter.sample(&groups(&robots));
        let previous = std::mem::take(&mut snap.robots);
        snap.robots = robots.iter().map(|r| r.snapshot()).collect();
        snap.note = None;
        let ft = flight_total_s + t_settle.elapsed().as_secs_f64() * config.rate;
        log_sessions(&mut log, ft, &previous, &snap.robots);
        if last_sample.elapsed() >= Duration::from_secs(1) {
            last_sample = Instant::now();
            log.bytes_over_time
                .push((ft, snap.robots.iter().map(|r| r.bytes_sent).collect()));
        }
        progress(&snap);
        // Every pair has seen each other at base (their team links had a session to
        // exchange what the flight left), every back-end has converged, and every robot
        // holds the solve handed down to it (nothing left on the radio).
        for r in &snap.robots {
            for p in &r.present {
                let me = r.name.to_string();
                met_at_base.insert((me.clone().min(p.clone()), me.max(p.clone())));
            }
        }
        let all_met = met_at_base.len() >= n * (n - 1) / 2;
        // A team still split waits until every pair is in range now, not only once: a
        // meeting at base that the lossy radio cut after a second leaves both back-ends
        // `converged` with nobody present to wait for (a chaos run of 2026-12-05: b in
        // its own frame, its link to a down for the rest of the settle).
        let converged = all_met
            && (in_one_frame(&snap.robots) || all_pairs_present(&snap.robots))
            && snap.robots.iter().all(|r| r.converged);
        let delivered = estimates_delivered(&snap.robots);
        if converged && !delivered && !waited_for_delivery {
            // Said once per run: how often the back-ends' own word would have ended the
            // settle too early.
            waited_for_delivery = true;
            let what = format!(
                "every back-end converged, estimates still on the radio ({})",
                undelivered(&snap.robots)
            );
            log.timeline.push(TimelineEvent {
                t_s: ft,
                event: format!("at base: {what}"),
                robots: (0..n).map(|r| letter(r).to_string()).collect(),
            });
            snap.note = Some(format!("{ft:5.1} s  {what}"));
            progress(&snap);
        }
        let all_converged = converged && delivered;
        // Converged, and nothing moving for a while: no closure, no back-end round, not a
        // byte on the radio (the meeting at base has exchanged what it had to).
        let same = |a: &[RobotSnapshot], b: &[RobotSnapshot]| {
            a.iter().zip(b).all(|(x, y)| {
                x.closures == y.closures
                    && x.rounds == y.rounds
                    && x.round == y.round
                    && x.bytes_sent == y.bytes_sent
            })
        };
        let quiet = if in_one_frame(&snap.robots) {
            QUIET
        } else {
            QUIET_SPLIT
        };
        match &stable_since {
            Some((since, s)) if all_converged && same(s, &snap.robots) => {
                if since.elapsed() >= quiet && t_settle.elapsed() >= MEETING {
                    log.converged_at_base = true;
                    break;
                }
            }
            _ => stable_since = all_converged.then(|| (Instant::now(), snap.robots.clone())),
        }
        if t_settle.elapsed().as_secs_f64() >= config.settle_s {
            break;
        }
        std::thread::sleep(Duration::from_millis(250));
    }
    log.settle_s = t_settle.elapsed().as_secs_f64();

    // Stop every robot cleanly (its services drain and write their files).
    snap.phase = Phase::Stopping;
    progress(&snap);
    meter.sample(&groups(&robots));
    // From the highest robot down: the team's solver (the lowest) stops last, so no robot
    // sees it leave and takes over solving (a robot without the solver's graph solves
    // without the closures it held) while the team writes its final files.
    for robot in robots.iter_mut().rev() {
        robot.stop(&mut meter)?;
    }
    log.cpu.robots_s = (0..n).map(|r| meter.robot_s(r)).collect();
    log.cpu.per_process = (0..n).map(|r| meter.per_process(r)).collect();
    log.cpu.waited_children_s = cpu::waited_children_cpu_s();
    log.starts = robots.iter().map(|r| r.starts).collect();
    if let (Some(p), Some(net)) = (config.drop, &net) {
        let (seen, dropped) = net.dropped_packets();
        log.drop = Some((p, seen, dropped));
    }
    drop(net);

    snap.phase = Phase::Reporting;
    progress(&snap);
    let summary = report::write(config, &world, &log)?;
    // Every run also as ROS 2 messages, for ros2 bag / Foxglove (`<out>/run.mcap`).
    doorslam_ros2::record::record(out, None)
        .map_err(|e| DemoError::Report(format!("run.mcap: {e}")))?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn robot(name: char, anchor: &str) -> RobotSnapshot {
        RobotSnapshot {
            name,
            state: RobotState::Running,
            frames: None,
            lost: None,
            keyframes: 0,
            rendezvous: 0,
            meetings: Default::default(),
            present: Vec::new(),
            closures: 0,
            rejected: 0,
            rounds: 0,
            converged: true,
            round: None,
            rounds_handed_down: Default::default(),
            unacknowledged: 0,
            anchor: anchor.into(),
            bytes_sent: 0,
        }
    }

    #[test]
    fn the_team_is_settled_only_once_the_estimates_handed_down_arrived() {
        // a solved round 7 and handed it to its team link for b; b still settles on 6.
        let mut a = robot('a', "a");
        a.round = Some(7);
        a.rounds_handed_down = [("b".to_string(), 7)].into();
        let mut b = robot('b', "a");
        b.round = Some(6);
        assert!(!estimates_delivered(&[a.clone(), b.clone()]));
        assert_eq!(
            undelivered(&[a.clone(), b.clone()]),
            "b holds round 6, a handed down 7"
        );
        // A robot that holds no solve yet is not settled either.
        b.round = None;
        assert!(!estimates_delivered(&[a.clone(), b.clone()]));
        b.round = Some(7);
        assert!(estimates_delivered(&[a.clone(), b.clone()]));
        // Something a team link sent a present peer and has no acknowledgement of.
        b.unacknowledged = 2;
        assert!(!estimates_delivered(&[a.clone(), b.clone()]));
        assert_eq!(undelivered(&[a.clone(), b.clone()]), "b: 2 unacknowledged");
        b.unacknowledged = 0;
        // Estimates handed down for a robot the demo does not run: never delivered.
        a.rounds_handed_down.insert("c".into(), 7);
        assert!(!estimates_delivered(&[a, b]));
    }

    #[test]
    fn every_pair_is_present_only_when_each_robot_sees_every_other() {
        let mut a = robot('a', "a");
        let mut b = robot('b', "b");
        assert!(!all_pairs_present(&[a.clone(), b.clone()]));
        a.present = vec!["b".into()];
        // a sees b, b does not see a yet (one side of a reconnection).
        assert!(!all_pairs_present(&[a.clone(), b.clone()]));
        b.present = vec!["a".into()];
        assert!(all_pairs_present(&[a.clone(), b.clone()]));
        let c = robot('c', "c");
        assert!(!all_pairs_present(&[a, b, c]));
    }

    #[test]
    fn a_team_is_in_one_frame_only_when_every_robot_names_the_same_anchor() {
        assert!(in_one_frame(&[
            robot('a', "a"),
            robot('b', "a"),
            robot('c', "a")
        ]));
        // A restarted robot back in its own frame, or one not yet reporting: split.
        assert!(!in_one_frame(&[robot('a', "a"), robot('b', "b")]));
        assert!(!in_one_frame(&[robot('a', "a"), robot('b', "")]));
        assert!(!in_one_frame(&[robot('a', ""), robot('b', "")]));
    }
}
