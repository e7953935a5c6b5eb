//! The demo's report, from the files the robots left in `<out>/<robot>/` and the world:
//!
//! - **Errors** (ATE, RMSE of keyframe positions against ground truth, SE(3)-aligned):
//!   the odometry alone (`odometry.tum`, each robot aligned on its own: its frame is its
//!   own), the team's estimate (`team_estimate.tum`) aligned per robot and — what matters
//!   for a shared map — with **one** alignment for all robots of the team's frame, and
//!   a centralized oracle on the same closures (every robot's `graph.g2o` merged, PCM with
//!   the same settings, Levenberg-Marquardt), also with one alignment.
//! - **Closures** against the simulator's truth: a closure is true when its measurement
//!   agrees with the ground-truth relative pose (within [`TRUE_TRANSLATION_M`] and
//!   [`TRUE_ROTATION_DEG`]); aliased when its frames are near a pair `closures.csv` lists
//!   as aliased; accepted unless the distributed back-end's PCM left it out.
//! - **Bandwidth**: `doorslam bw` of the run (paper Table II layout).
//! - the rendezvous **timeline**, and plots (see [`super::plots`]).
//!
//! `summary.json` holds the same figures; its fields are documented on [`Summary`].

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use doorslam_backend::eval::{
    absolute_trajectory_error, associate_by_timestamp, read_tum, umeyama, Alignment, Trajectory,
};
use doorslam_backend::g2o::{merge_g2o_files, ReadOptions};
use doorslam_backend::init::Chordal;
use doorslam_backend::outliers::{Pcm, Scope};
use doorslam_backend::{key, optimize, PoseGraph, SolverOptions};
use doorslam_geometry::SE3;
use nalgebra::Point3;
use serde::Serialize;

use super::config::{DemoConfig, World};
use super::{io_err, read_json, DemoError, RunLog, TimelineEvent};
use crate::flights::robot_name;

/// A closure agreeing with ground truth within this translation error is true.
pub const TRUE_TRANSLATION_M: f64 = 2.0;
/// ... and this rotation error (degrees).
pub const TRUE_ROTATION_DEG: f64 = 15.0;
/// Frames within this of an aliased candidate pair make a closure aliased.
pub const ALIAS_FRAMES: usize = 5;
/// Timestamps of keyframes and ground truth match within this (seconds).
const MAX_TIME_DIFF_S: f64 = 0.005;
/// An edge between two keyframes of one robot this far apart in time is a loop closure
/// (odometry joins consecutive keyframes; a restart's segment link spans the seconds the
/// robot was dead).
pub const OWN_LOOP_MIN_GAP_S: f64 = 10.0;

/// One robot's figures.
#[derive(Debug, Clone, Serialize)]
pub struct RobotSummary {
    pub keyframes: usize,
    /// Frames the front-end processed and lost (its `frontend.json`, when present).
    pub frames: Option<u64>,
    pub lost: Option<u64>,
    /// ATE (RMSE, m) of the odometry alone, aligned on its own.
    pub ate_vo_m: Option<f64>,
    /// ATE of the team estimate, aligned on its own.
    pub ate_team_m: Option<f64>,
    /// ATE of the team estimate in the team's frame: one alignment for every robot in it.
    pub ate_team_frame_m: Option<f64>,
    /// The robot ended in the team's frame (anchored to the anchor most robots share,
    /// with a team estimate): its `ate_team_frame_m` is measured with the others'.
    pub in_team_frame: bool,
    /// ATE of the centralized oracle (same closures, same PCM), one alignment.
    pub ate_centralized_m: Option<f64>,
    /// Whether the distributed back-end put the robot in the team's frame, whose robot
    /// anchors it, and whether it had converged when the robot stopped.
    pub anchored: bool,
    pub anchor: String,
    pub converged: bool,
    /// Payload bytes the robot's team link sent (resends included).
    pub bytes_sent: u64,
    /// Times the robot's processes were started.
    pub starts: u32,
    /// Times its team link was started (`status.json`): above `starts` when the team
    /// service failed and `up` restarted it.
    pub team_link_starts: u64,
    /// What its team link's presence checks mended (`status.json` `presence`: peers whose
    /// token put or delete Zenoh's subscriber missed, sessions reopened); 0s on a healthy
    /// radio.
    pub presence: doorslam_team::presence::PresenceMends,
    /// The peers its team link counted present when it stopped.
    pub present_at_end: Vec<String>,
    /// Messages its team link dropped because their sender was not present
    /// (`ledger.json` `dropped`, reason `unknown_peer`), by claimed sender.
    pub unknown_peer_drops: std::collections::BTreeMap<String, u64>,
    /// Every service failure `up` logged (`robot.log`: the service, its exit status), and
    /// every panic message: none in a healthy run, a killed robot's included.
    pub service_failures: Vec<String>,
    /// CPU seconds of all its processes (see `cpu`).
    pub cpu_s: f64,
    /// Its flight from ground truth: horizontal distance (m) and mean speed (m/s).
    pub distance_m: f64,
    pub speed_mps: f64,
}

/// The lines of a robot's log that say a service failed (`up`'s `[up] <service> failed
/// (<status>)...`) or panicked, in order; none when the log cannot be read.
pub fn service_failures(log: &Path) -> Vec<String> {
    std::fs::read_to_string(log)
        .map(|text| {
            text.lines()
                .filter(|l| {
                    (l.starts_with("[up] ") && l.contains(" failed (")) || l.contains("panicked at")
                })
                .map(str::to_string)
                .collect()
        })
        .unwrap_or_default()
}

/// One inter-robot closure.
#[derive(Debug, Clone, Serialize)]
pub struct ClosureRow {
    pub a: String,
    pub b: String,
    pub truth: bool,
    pub aliased: bool,
    pub accepted: bool,
    /// Error of the measurement against the ground-truth relative pose.
    pub translation_error_m: Option<f64>,
    pub rotation_error_deg: Option<f64>,
}

/// Closures against the simulator's truth.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ClosureSummary {
    pub total: usize,
    pub true_closures: usize,
    pub false_closures: usize,
    pub aliased: usize,
    pub accepted: usize,
    pub rejected: usize,
    pub true_accepted: usize,
    pub true_rejected: usize,
    /// False closures PCM kept (should be 0).
    pub false_accepted: usize,
    pub false_rejected: usize,
    pub aliased_accepted: usize,
    pub list: Vec<ClosureRow>,
}

/// Wall time of each phase and CPU time of the robots.
#[derive(Debug, Clone, Serialize)]
pub struct Durations {
    pub render_s: f64,
    pub flight_s: f64,
    pub settle_s: f64,
    pub report_s: f64,
    pub total_s: f64,
    /// CPU seconds of every robot process together (measured per process, see `cpu`).
    pub robots_cpu_s: f64,
    /// CPU seconds the demo's own process spent rendering.
    pub render_cpu_s: f64,
}

/// Random loss between robots (`--drop`).
#[derive(Debug, Clone, Serialize)]
pub struct DropSummary {
    pub probability: f64,
    /// Packets from other robots the robots received, summed, and of them those lost.
    pub packets: u64,
    pub dropped: u64,
}

/// The kill of `--kill`.
#[derive(Debug, Clone, Serialize)]
pub struct KillSummary {
    pub robot: String,
    pub at_s: f64,
    pub restart_after_s: f64,
    /// Whether the robot ended in the team's frame (what the team lost by the kill).
    pub in_team_frame: bool,
}

/// The flights: how they were planned, and what ground truth says of them.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Scenario {
    /// `sectors`, `designed` (rendered worlds) or `dataset`.
    pub plan: String,
    /// The slowest drone's configured speed (m/s) and the radio range (m), rendered worlds.
    pub speed_mps: Option<f64>,
    pub radio_range_m: Option<f64>,
    /// What each robot's route was designed for.
    pub roles: BTreeMap<String, String>,
    /// `revisits.<r>.<q>`: stretches of r's flight over places q saw before (q = r: its
    /// own, at least 20 s earlier), from ground truth.
    pub revisits: BTreeMap<String, BTreeMap<String, usize>>,
    /// Per robot: stretches over places any other robot saw (before or after).
    pub crossings: BTreeMap<String, usize>,
    /// The simulator's candidates (`closures.csv`, `revisits.csv`).
    pub overlap_candidates: usize,
    pub aliased_candidates: usize,
    pub own_overlap_candidates: usize,
    pub own_aliased_candidates: usize,
    /// Pairs coming into radio range during the flight (not at take-off).
    pub meetings_in_flight: usize,
}

/// `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub robots: usize,
    pub frames: usize,
    /// `netns` (every robot a host of its own) or `loopback` (not root).
    pub mode: String,
    pub source: String,
    pub per_robot: BTreeMap<String, RobotSummary>,
    /// ATE over every robot in the team's frame (one alignment), distributed and oracle.
    pub team_ate_m: Option<f64>,
    pub centralized_ate_m: Option<f64>,
    /// What the team bought: the robots' mean odometry-alone ATE over the team-frame ATE
    /// of the team (`team_ate_m`); above 1 the team's map is better than each robot alone.
    pub team_gain: Option<f64>,
    /// Robots in the team's frame, of `robots`.
    pub robots_in_team_frame: usize,
    pub converged_at_base: bool,
    /// Inter-robot closures.
    pub closures: ClosureSummary,
    /// Each robot's loop closures with its own earlier keyframes (at least
    /// [`OWN_LOOP_MIN_GAP_S`] apart), against the truth the same way.
    pub own_closures: ClosureSummary,
    /// The flights' design and what ground truth says of it.
    pub scenario: Scenario,
    /// `--drop`: random loss between robots, or null.
    pub drop: Option<DropSummary>,
    /// The first `--kill`: the robot killed, when, and after how long it restarted; or null.
    pub kill: Option<KillSummary>,
    /// Every `--kill`, in the order given, with what the team made of the robot after it.
    pub kills: Vec<KillSummary>,
    /// How the team link was secured (mutual TLS + access control unless `--insecure`).
    pub security: super::SecuritySummary,
    /// `--ros2`: every robot published its state as ROS 2 topics, on `ros2_endpoints`.
    pub ros2: bool,
    pub ros2_endpoints: Vec<String>,
    /// Whether every robot kept up with its camera on this machine.
    pub realtime: super::realtime::Realtime,
    /// Where the CPU went (robots, per process, demo, the machine).
    pub cpu: super::realtime::CpuSummary,
    /// `doorslam bw --json` of the run.
    pub bandwidth: serde_json::Value,
    pub timeline: Vec<TimelineEvent>,
    pub durations: Durations,
    pub plots: Vec<String>,
}

impl ClosureSummary {
    /// Counts one closure in.
    fn add(&mut self, row: ClosureRow) {
        let (t, a, k) = (row.truth, row.aliased, row.accepted);
        self.total += 1;
        self.true_closures += usize::from(t);
        self.false_closures += usize::from(!t);
        self.aliased += usize::from(a);
        self.accepted += usize::from(k);
        self.rejected += usize::from(!k);
        self.true_accepted += usize::from(t && k);
        self.true_rejected += usize::from(t && !k);
        self.false_accepted += usize::from(!t && k);
        self.false_rejected += usize::from(!t && !k);
        self.aliased_accepted += usize::from(a && k);
        self.list.push(row);
    }
}

fn report_err(e: impl std::fmt::Display) -> DemoError {
    DemoError::Report(e.to_string())
}

/// A robot's trajectory file, if written and not empty.
fn read_estimate(path: &Path) -> Option<Trajectory> {
    read_tum(path).ok().filter(|t| !t.is_empty())
}

/// Ground-truth and estimated positions of the keyframes both have.
fn associated(truth: &Trajectory, estimate: &Trajectory) -> Option<(Trajectory, Trajectory)> {
    associate_by_timestamp(truth, estimate, MAX_TIME_DIFF_S).ok()
}

fn rmse(errors: &[f64]) -> Option<f64> {
    (!errors.is_empty())
        .then(|| (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt())
}

/// Per robot: errors of each keyframe after one alignment of all robots together.
fn joint_errors(
    pairs: &BTreeMap<usize, (Trajectory, Trajectory)>,
) -> Option<BTreeMap<usize, Vec<(f64, f64)>>> {
    let (mut src, mut dst): (Vec<Point3<f64>>, Vec<Point3<f64>>) = (Vec::new(), Vec::new());
    for (gt, est) in pairs.values() {
        src.extend(est.positions());
        dst.extend(gt.positions());
    }
    let t = umeyama(&src, &dst, false).ok()?;
    Some(
        pairs
            .iter()
            .map(|(&r, (gt, est))| {
                let e = gt
                    .positions()
                    .iter()
                    .zip(est.positions())
                    .zip(gt.timestamps())
                    .map(|((g, p), &time)| (time, (g - t * p).norm()))
                    .collect();
                (r, e)
            })
            .collect(),
    )
}

/// `keyframes.csv` → id → stamp (seconds).
fn keyframe_stamps(path: &Path) -> BTreeMap<u64, f64> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return BTreeMap::new();
    };
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let (id, stamp) = l.split_once(',')?;
            Some((id.parse().ok()?, stamp.parse::<u64>().ok()? as f64 * 1e-9))
        })
        .collect()
}

/// The ground-truth pose (and frame index) nearest to `time`.
fn truth_at(truth: &Trajectory, time: f64) -> Option<(usize, SE3)> {
    let i = truth
        .timestamps()
        .iter()
        .enumerate()
        .min_by(|a, b| (a.1 - time).abs().total_cmp(&(b.1 - time).abs()))?
        .0;
    ((truth.timestamps()[i] - time).abs() <= MAX_TIME_DIFF_S).then(|| (i, truth.poses()[i]))
}

/// `closures.csv`'s aliased pairs: (robot_a, frame_a, robot_b, frame_b).
fn aliased_candidates(path: Option<&PathBuf>) -> Vec<(usize, usize, usize, usize)> {
    let Some(text) = path.and_then(|p| std::fs::read_to_string(p).ok()) else {
        return Vec::new();
    };
    let letter = |s: &str| s.bytes().next().map(|c| usize::from(c.wrapping_sub(b'a')));
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f.len() == 5 && f[4].trim() == "aliased").then_some(())?;
            Some((
                letter(f[0])?,
                f[1].parse().ok()?,
                letter(f[2])?,
                f[3].parse().ok()?,
            ))
        })
        .collect()
}

/// `revisits.csv`'s aliased pairs of a robot with itself: (robot, frame, robot, earlier).
fn own_aliased_candidates(path: Option<&PathBuf>) -> Vec<(usize, usize, usize, usize)> {
    let Some(text) = path.and_then(|p| std::fs::read_to_string(p).ok()) else {
        return Vec::new();
    };
    let letter = |s: &str| s.bytes().next().map(|c| usize::from(c.wrapping_sub(b'a')));
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f.len() == 4 && f[3].trim() == "aliased").then_some(())?;
            let r = letter(f[0])?;
            Some((r, f[1].parse().ok()?, r, f[2].parse().ok()?))
        })
        .collect()
}

/// The centralized oracle: every robot's graph merged, PCM as the robots run it, then
/// Levenberg-Marquardt on the part connected to robot a's first keyframe.
fn centralized(files: &[PathBuf], threshold: f64, min_clique: usize) -> Option<PoseGraph<SE3>> {
    let (graph, _) = merge_g2o_files(files, ReadOptions::default()).ok()?;
    let mut pcm = Pcm::new(threshold, Scope::InterRobot).ok()?;
    pcm.min_clique = min_clique;
    let s = pcm.run(&graph).ok()?;
    let keep: BTreeSet<(u64, u64)> = s
        .inliers
        .iter()
        .flat_map(|&(a, b)| [(a, b), (b, a)])
        .collect();
    let keys = graph.keys().to_vec();
    let inter =
        |e: &doorslam_backend::BetweenFactor<SE3>| key::robot(keys[e.i]) != key::robot(keys[e.j]);
    let mut filtered = graph.clone();
    filtered.retain_edges(|e| !inter(e) || keep.contains(&(keys[e.i], keys[e.j])));
    // The component of the first pose of the lowest robot.
    let mut adj = vec![Vec::new(); filtered.len()];
    for e in filtered.edges() {
        adj[e.i].push(e.j);
        adj[e.j].push(e.i);
    }
    let anchor = (0..filtered.len()).min_by_key(|&i| filtered.keys()[i])?;
    let mut seen = vec![false; filtered.len()];
    let mut stack = vec![anchor];
    seen[anchor] = true;
    while let Some(a) = stack.pop() {
        for &b in &adj[a] {
            if !seen[b] {
                seen[b] = true;
                stack.push(b);
            }
        }
    }
    let mut part = PoseGraph::<SE3>::new();
    for i in (0..filtered.len()).filter(|&i| seen[i]) {
        part.add_pose(filtered.keys()[i], filtered.poses()[i]);
    }
    for e in filtered.edges() {
        if seen[e.i] && seen[e.j] {
            let a = part.index_of(filtered.keys()[e.i])?;
            let b = part.index_of(filtered.keys()[e.j])?;
            part.add_edge(a, b, e.measured, e.information).ok()?;
        }
    }
    let a = part.index_of(filtered.keys()[anchor])?;
    SE3::chordal(&mut part, a).ok()?;
    optimize(&mut part, a, &SolverOptions::default()).ok()?;
    Some(part)
}

/// Writes `summary.json`, `report.md` and the plots; returns the summary.
pub fn write(config: &DemoConfig, world: &World, log: &RunLog) -> Result<Summary, DemoError> {
    let t_report = std::time::Instant::now();
    let out = &config.out;
    let n = world.robots();
    let letters: Vec<String> = (0..n).map(|r| robot_name(r).to_string()).collect();
    let dir = |r: usize| out.join(&letters[r]);
    let status = |r: usize| read_json(&dir(r).join("backend.json"));
    let truth: Vec<Option<Trajectory>> = world.truth.iter().cloned().map(Some).collect();

    // Errors.
    let mut per_robot = BTreeMap::new();
    let mut team_pairs = BTreeMap::new();
    let mut anchors = BTreeMap::new();
    for r in 0..n {
        let st = status(r);
        let get = |p: &str| st.as_ref().and_then(|s| s.pointer(p)).cloned();
        // The team link's status.json, read once for the fields below.
        let link = read_json(&dir(r).join("status.json"));
        let link_field = |k: &str| link.as_ref().and_then(|s| s.get(k)).cloned();
        let anchored = get("/team/anchored")
            .and_then(|v| v.as_bool())
            .unwrap_or(false);
        let anchor = get("/team/anchor")
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default();
        let ate = |file: &str| -> Option<(f64, (Trajectory, Trajectory))> {
            let est = read_estimate(&dir(r).join(file))?;
            let (gt, est) = associated(truth[r].as_ref()?, &est)?;
            let a = absolute_trajectory_error(&gt, &est, Alignment::Se3).ok()?;
            Some((a.stats.rmse, (gt, est)))
        };
        let vo = ate("odometry.tum");
        let team = ate("team_estimate.tum");
        if let (true, Some((_, pairs))) = (anchored, &team) {
            anchors.insert(r, anchor.clone());
            team_pairs.insert(r, pairs.clone());
        }
        let frontend = read_json(&dir(r).join("frontend.json"));
        per_robot.insert(
            letters[r].clone(),
            RobotSummary {
                keyframes: get("/keyframes").and_then(|v| v.as_u64()).unwrap_or(0) as usize,
                frames: frontend
                    .as_ref()
                    .and_then(|f| f.get("frames"))
                    .and_then(|v| v.as_u64()),
                lost: frontend
                    .as_ref()
                    .and_then(|f| f.get("lost"))
                    .and_then(|v| v.as_u64()),
                ate_vo_m: vo.map(|v| v.0),
                ate_team_m: team.map(|v| v.0),
                ate_team_frame_m: None,
                in_team_frame: false,
                ate_centralized_m: None,
                anchored,
                anchor,
                converged: get("/team/converged")
                    .and_then(|v| v.as_bool())
                    .unwrap_or(false),
                bytes_sent: super::robot::ledger_bytes_sent(&dir(r).join("ledger.json")),
                starts: log.starts.get(r).copied().unwrap_or(0),
                team_link_starts: link_field("link_starts")
                    .and_then(|v| v.as_u64())
                    .unwrap_or(0),
                presence: link_field("presence")
                    .and_then(|v| serde_json::from_value(v).ok())
                    .unwrap_or_default(),
                present_at_end: link_field("present")
                    .and_then(|v| serde_json::from_value(v).ok())
                    .unwrap_or_default(),
                unknown_peer_drops: unknown_peer_drops(&dir(r).join("ledger.json")),
                service_failures: service_failures(&dir(r).join("robot.log")),
                cpu_s: log.cpu.robots_s.get(r).copied().unwrap_or(0.0),
                distance_m: truth[r].as_ref().map_or(0.0, horizontal_length),
                speed_mps: truth[r].as_ref().map_or(0.0, |t| {
                    let s = t.timestamps();
                    let span = s.last().copied().unwrap_or(0.0) - s.first().copied().unwrap_or(0.0);
                    if span > 0.0 {
                        horizontal_length(t) / span
                    } else {
                        0.0
                    }
                }),
            },
        );
    }
    // The team's frame: the anchor most robots share, the lowest robot's on a tie (robot
    // a's, as the centralized oracle's).
    let team_anchor = {
        let mut count: BTreeMap<&String, usize> = BTreeMap::new();
        for a in anchors.values() {
            *count.entry(a).or_default() += 1;
        }
        count
            .into_iter()
            .min_by_key(|(a, c)| (std::cmp::Reverse(*c), (*a).clone()))
            .map(|(a, _)| a.clone())
    };
    team_pairs.retain(|r, _| Some(&anchors[r]) == team_anchor.as_ref());
    for r in team_pairs.keys() {
        if let Some(x) = per_robot.get_mut(&letters[*r]) {
            x.in_team_frame = true;
        }
    }
    let team_errors = joint_errors(&team_pairs);
    let mut all_team = Vec::new();
    if let Some(errors) = &team_errors {
        for (r, e) in errors {
            let v: Vec<f64> = e.iter().map(|x| x.1).collect();
            all_team.extend(v.iter().copied());
            if let Some(s) = per_robot.get_mut(&letters[*r]) {
                s.ate_team_frame_m = rmse(&v);
            }
        }
    }

    // The centralized oracle on the same closures.
    let graphs: Vec<PathBuf> = (0..n)
        .map(|r| dir(r).join("graph.g2o"))
        .filter(|p| p.is_file())
        .collect();
    // The robots run the back-end's default PCM settings (the demo writes no others).
    let pcm = doorslam_backend::service::BackendSection::default();
    let oracle = centralized(&graphs, pcm.pcm_threshold, pcm.pcm_min_clique);
    let mut all_oracle = Vec::new();
    if let Some(g) = &oracle {
        let mut pairs = BTreeMap::new();
        for (r, gt) in truth.iter().enumerate() {
            let stamps = keyframe_stamps(&dir(r).join("keyframes.csv"));
            let (mut times, mut poses) = (Vec::new(), Vec::new());
            for (k, p) in g.keys().iter().zip(g.poses()) {
                if key::robot(*k) == Some(r as u8) {
                    if let Some(&t) = stamps.get(&key::index(*k)) {
                        times.push(t);
                        poses.push(*p);
                    }
                }
            }
            let Ok(est) = Trajectory::new(times, poses) else {
                continue;
            };
            if let Some(p) = gt.as_ref().and_then(|gt| associated(gt, &est)) {
                pairs.insert(r, p);
            }
        }
        if let Some(errors) = joint_errors(&pairs) {
            for (r, e) in errors {
                let v: Vec<f64> = e.iter().map(|x| x.1).collect();
                all_oracle.extend(v.iter().copied());
                if let Some(s) = per_robot.get_mut(&letters[r]) {
                    s.ate_centralized_m = rmse(&v);
                }
            }
        }
    }

    // Closures against the truth.
    let mut aliased = aliased_candidates(world.closures_csv.as_ref());
    aliased.extend(own_aliased_candidates(world.revisits_csv.as_ref()));
    let mut rejected: BTreeSet<(String, String)> = BTreeSet::new();
    for r in 0..n {
        if let Some(list) = status(r)
            .as_ref()
            .and_then(|s| s.pointer("/team/rejected_closures"))
            .and_then(|v| v.as_array())
        {
            for pair in list {
                if let (Some(a), Some(b)) = (
                    pair.get(0).and_then(|x| x.as_str()),
                    pair.get(1).and_then(|x| x.as_str()),
                ) {
                    rejected.insert((a.to_string(), b.to_string()));
                    rejected.insert((b.to_string(), a.to_string()));
                }
            }
        }
    }
    let stamps: Vec<BTreeMap<u64, f64>> = (0..n)
        .map(|r| keyframe_stamps(&dir(r).join("keyframes.csv")))
        .collect();
    let mut closures = ClosureSummary::default();
    let mut own_closures = ClosureSummary::default();
    if let Ok((merged, _)) = merge_g2o_files(&graphs, ReadOptions::default()) {
        let keys = merged.keys();
        let mut seen = BTreeSet::new();
        for e in merged.edges() {
            let (a, b) = (keys[e.i], keys[e.j]);
            let (Some(ra), Some(rb)) = (key::robot(a), key::robot(b)) else {
                continue;
            };
            if !seen.insert((a.min(b), a.max(b))) {
                continue;
            }
            let (ra, rb) = (usize::from(ra), usize::from(rb));
            let stamp = |r: usize, k: u64| stamps.get(r)?.get(&key::index(k)).copied();
            let summary = if ra != rb {
                &mut closures
            } else {
                // One robot's edge: a loop closure only between keyframes far apart in
                // time (odometry joins neighbours).
                match (stamp(ra, a), stamp(rb, b)) {
                    (Some(ta), Some(tb)) if (ta - tb).abs() >= OWN_LOOP_MIN_GAP_S => {
                        &mut own_closures
                    }
                    _ => continue,
                }
            };
            let at = |r: usize, k: u64| {
                let t = stamp(r, k)?;
                truth.get(r)?.as_ref().and_then(|gt| truth_at(gt, t))
            };
            let (ta, tb) = (at(ra, a), at(rb, b));
            let error = ta.zip(tb).map(|((_, pa), (_, pb))| {
                let d = e.measured.inverse() * (pa.inverse() * pb);
                (d.translation.vector.norm(), d.rotation.angle().to_degrees())
            });
            let is_true =
                error.is_some_and(|(t, r)| t < TRUE_TRANSLATION_M && r < TRUE_ROTATION_DEG);
            let is_aliased = ta.zip(tb).is_some_and(|((fa, _), (fb, _))| {
                aliased.iter().any(|&(xa, xfa, xb, xfb)| {
                    let near = |f: usize, g: usize| f.abs_diff(g) <= ALIAS_FRAMES;
                    (xa == ra && xb == rb && near(xfa, fa) && near(xfb, fb))
                        || (xa == rb && xb == ra && near(xfa, fb) && near(xfb, fa))
                })
            });
            let (la, lb) = (key::label(a), key::label(b));
            let accepted = !rejected.contains(&(la.clone(), lb.clone()));
            summary.add(ClosureRow {
                a: la,
                b: lb,
                truth: is_true,
                aliased: is_aliased,
                accepted,
                translation_error_m: error.map(|e| e.0),
                rotation_error_deg: error.map(|e| e.1),
            });
        }
    }

    // Bandwidth.
    let (bandwidth, bw_table) = match doorslam_team::bw::load(out) {
        Ok(ledgers) => {
            let r = doorslam_team::bw::report(&ledgers);
            (serde_json::to_value(&r).unwrap_or_default(), r.table())
        }
        Err(e) => (serde_json::Value::Null, format!("no ledger: {e}")),
    };

    // Plots.
    let plots = super::plots::draw(out, world, &truth, &team_errors, &team_pairs, log)
        .map_err(report_err)?;

    // The value of the team, the run's honesty figures.
    let team_ate_m = rmse(&all_team);
    let vo: Vec<f64> = per_robot.values().filter_map(|x| x.ate_vo_m).collect();
    let team_gain = team_ate_m
        .filter(|t| *t > 0.0 && !vo.is_empty())
        .map(|t| vo.iter().sum::<f64>() / vo.len() as f64 / t);
    let robots_in_team_frame = per_robot.values().filter(|x| x.in_team_frame).count();
    let realtime = super::realtime::check(
        out,
        &letters,
        &world.robot_frames,
        world.rate_hz,
        &log.starts,
    );
    let cpu = super::realtime::cpu_summary(&log.cpu, &letters);
    let source = match (&config.dataset, &config.world) {
        (Some(d), _) => format!("dataset {} split into {n} robots", d.display()),
        (None, Some(w)) => format!("synthetic town, the world rendered in {}", w.display()),
        (None, None) => format!("synthetic town, seed {}", config.seed),
    };

    let kills: Vec<KillSummary> = config
        .kills
        .iter()
        .map(|k| {
            let robot = robot_name(k.robot).to_string();
            KillSummary {
                in_team_frame: per_robot.get(&robot).is_some_and(|r| r.in_team_frame),
                robot,
                at_s: k.at_s,
                restart_after_s: config.restart_after_s,
            }
        })
        .collect();
    let report_s = t_report.elapsed().as_secs_f64();
    let summary = Summary {
        robots: n,
        frames: world.robot_frames.iter().copied().max().unwrap_or(0),
        mode: log.mode.clone(),
        source,
        per_robot,
        team_ate_m,
        centralized_ate_m: rmse(&all_oracle),
        team_gain,
        robots_in_team_frame,
        converged_at_base: log.converged_at_base,
        closures,
        own_closures,
        scenario: scenario(world, &truth),
        drop: log.drop.map(|(probability, packets, dropped)| DropSummary {
            probability,
            packets,
            dropped,
        }),
        kill: kills.first().cloned(),
        kills,
        security: log.security.clone(),
        ros2: !log.ros2_endpoints.is_empty(),
        ros2_endpoints: log.ros2_endpoints.clone(),
        bandwidth,
        timeline: log.timeline.clone(),
        durations: Durations {
            render_s: log.render_s,
            flight_s: log.flight_s,
            settle_s: log.settle_s,
            report_s,
            total_s: log.render_s + log.flight_s + log.settle_s + report_s,
            robots_cpu_s: cpu.robots_s,
            render_cpu_s: cpu.render_s,
        },
        realtime,
        cpu,
        plots,
    };
    let json = serde_json::to_string_pretty(&summary).map_err(report_err)?;
    let path = out.join("summary.json");
    std::fs::write(&path, json).map_err(io_err(&path))?;
    let path = out.join("report.md");
    std::fs::write(&path, super::markdown::report(&summary, &bw_table)).map_err(io_err(&path))?;
    Ok(summary)
}

/// Horizontal length of a trajectory (metres).
fn horizontal_length(t: &Trajectory) -> f64 {
    t.positions()
        .windows(2)
        .map(|w| (w[1] - w[0]).xy().norm())
        .sum()
}

/// The flights' plan (`world.txt`) and what ground truth says of it.
fn scenario(world: &World, truth: &[Option<Trajectory>]) -> Scenario {
    let get = |key: &str| {
        world
            .description
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.clone())
    };
    let n = world.robots();
    let names: Vec<String> = (0..n).map(|r| robot_name(r).to_string()).collect();
    let tracks: Vec<(&[f64], &[SE3])> = truth
        .iter()
        .flatten()
        .map(|t| (t.timestamps(), t.poses()))
        .collect();
    let counts = crate::flights::overlap_counts_of(&tracks);
    let rows = |path: Option<&PathBuf>, kind: &str| {
        path.and_then(|p| std::fs::read_to_string(p).ok())
            .map_or(0, |t| {
                t.lines()
                    .skip(1)
                    .filter(|l| l.trim_end().ends_with(kind))
                    .count()
            })
    };
    Scenario {
        plan: get("plan").unwrap_or_else(|| {
            if world.description.is_empty() {
                "dataset".into()
            } else {
                "designed".into()
            }
        }),
        speed_mps: get("speed_mps").and_then(|v| v.parse().ok()),
        radio_range_m: get("radio_range_m").and_then(|v| v.parse().ok()),
        roles: names
            .iter()
            .filter_map(|r| Some((r.clone(), get(&format!("role_{r}"))?)))
            .collect(),
        revisits: (0..counts.revisits.len().min(n))
            .map(|r| {
                let row = (0..n)
                    .map(|q| (names[q].clone(), counts.revisits[r][q]))
                    .collect();
                (names[r].clone(), row)
            })
            .collect(),
        crossings: (0..counts.crossings.len().min(n))
            .map(|r| (names[r].clone(), counts.crossings[r].len()))
            .collect(),
        overlap_candidates: rows(world.closures_csv.as_ref(), ",overlap"),
        aliased_candidates: rows(world.closures_csv.as_ref(), ",aliased"),
        own_overlap_candidates: rows(world.revisits_csv.as_ref(), ",overlap"),
        own_aliased_candidates: rows(world.revisits_csv.as_ref(), ",aliased"),
        meetings_in_flight: world
            .events
            .iter()
            .filter(|e| e.kind == crate::flights::RangeEventKind::Enter && e.time_s > 0.0)
            .count(),
    }
}

/// `ledger.json`'s drops for reason `unknown_peer`, by claimed sender (empty when the file
/// is missing or unreadable: the summary says what it can).
fn unknown_peer_drops(ledger: &Path) -> std::collections::BTreeMap<String, u64> {
    let mut out = std::collections::BTreeMap::new();
    let Some(rows) = read_json(ledger).and_then(|l| l.get("dropped").cloned()) else {
        return out;
    };
    let rows: Vec<doorslam_team::ledger::DropEntry> =
        serde_json::from_value(rows).unwrap_or_default();
    for d in rows.into_iter().filter(|d| d.reason == "unknown_peer") {
        *out.entry(d.peer).or_default() += d.messages;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `up`'s failure lines and panics are picked out of a robot's log, starts and stops
    /// are not; a missing log has none.
    #[test]
    fn service_failures_are_read_from_the_robots_log() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("robot.log");
        std::fs::write(
            &log,
            "[up] started team (pid 7)\n\
             [team] INFO team: link open\n\
             [team] thread 'main' panicked at services/team/src/node.rs:1:1:\n\
             [up] team failed (exit status: 101): restarting in 1s\n\
             [up] team stopped (exit status: 0)\n",
        )
        .unwrap();
        assert_eq!(
            service_failures(&log),
            vec![
                "[team] thread 'main' panicked at services/team/src/node.rs:1:1:".to_string(),
                "[up] team failed (exit status: 101): restarting in 1s".to_string(),
            ]
        );
        assert!(service_failures(&dir.path().join("absent.log")).is_empty());
    }
}
