//! `doorslam dpgo FILE [FILE...]`: distributed pose-graph optimization of a team, played
//! in-process over an emulated link, compared with the centralized optimum.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use doorslam_backend::distributed::condensed::PcmSettings;
use doorslam_backend::distributed::runner::{run_over, RunOptions, Transport};
use doorslam_backend::distributed::{AgentOptions, Method};
use doorslam_backend::key;
use doorslam_backend::outliers::labels::unordered;
use doorslam_backend::outliers::{inject_outliers, read_labels};
use doorslam_hil::dpgo::{Faults, LinkOptions, SessionLink};
use doorslam_team::protocol::ProtocolConfig;

use super::pgo::InformationArg;

#[derive(Debug, Args)]
pub struct DpgoArgs {
    /// 3-D g2o graph(s) with multi-robot keys: one merged file, or one file per robot
    /// (edges present in two files kept once).
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Probability that a message between robots is lost.
    #[arg(long, default_value_t = 0.0)]
    pub drop: f64,
    /// Probability that a message is held back 1-3 rounds (later ones overtake it; the
    /// team link only).
    #[arg(long, default_value_t = 0.0)]
    pub reorder: f64,
    /// Probability that a message arrives twice (the team link only).
    #[arg(long, default_value_t = 0.0)]
    pub duplicate: f64,
    /// The transport between the agents: the team link robots run (session: one
    /// PeerSession per pair of neighbours, its delivery contract, acknowledgements and
    /// resends counted in the bytes), or the runner's own (direct: the agents acknowledge
    /// and resend themselves, each message lost with --drop).
    #[arg(long, value_enum, default_value_t = LinkArg::Session)]
    pub link: LinkArg,
    /// Local time of one round, in seconds (the team link's clock).
    #[arg(long, default_value_t = 0.1)]
    pub round_s: f64,
    /// The team link resends an unacknowledged message after this long, in seconds
    /// (doubling per resend up to 16 times).
    #[arg(long, default_value_t = 0.3)]
    pub retransmit_s: f64,
    /// Seed of the loss draws.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Most rounds (every robot steps once per round).
    #[arg(long, default_value_t = 500)]
    pub max_rounds: u64,
    /// DOOR-SLAM's KITTI stopping thresholds (rotation 0.1, pose 0.5) instead of ours
    /// (for --method dgs).
    #[arg(long)]
    pub paper_thresholds: bool,
    /// Over-relaxation γ of DGS's two linear stages (default 1 over --link direct, where
    /// robots step in Gauss-Seidel order; 0.5 over the team link, where they solve on
    /// estimates a round old).
    #[arg(long)]
    pub gamma: Option<f64>,
    /// Over the team link, damp (γ 0.5, or --gamma) only the steps that reverse a robot's
    /// previous one, full steps otherwise (for --method dgs).
    #[arg(long)]
    pub damp_on_reversal: bool,
    /// The distributed solver: the paper's two-stage distributed Gauss-Seidel with
    /// block-coordinate refinement (dgs), or the condensed separator graph (condensed).
    #[arg(long, value_enum, default_value_t = MethodArg::Condensed)]
    pub method: MethodArg,
    /// Run PCM inside the loop with this probability threshold (condensed method; the
    /// centralized reference runs offline PCM with the same settings).
    #[arg(long)]
    pub pcm: Option<f64>,
    /// Ground truth of the closures (`doorslam sim graph`'s labels.txt, or a benchmark's
    /// inter_robot_labels.txt; 1 inlier / 0 outlier): report PCM's precision and recall in
    /// the loop.
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Smallest clique PCM keeps per robot pair.
    #[arg(long, default_value_t = 2)]
    pub min_clique: usize,
    /// Plain pairwise PCM: do not check closures left without a clique through 3-robot
    /// cycles.
    #[arg(long)]
    pub no_cycles: bool,
    /// Add outlier closures (this fraction of all inter-robot closures after adding them),
    /// as DOOR-SLAM's dataset simulation: translation uniform in [0, 10] m per axis,
    /// rotation uniform in [-π, π] per Euler angle; the graph's own closures are the
    /// inliers (labels for --pcm's precision and recall).
    #[arg(long, value_name = "FRACTION")]
    pub inject_outliers: Option<f64>,
    /// Seed of the injected outliers.
    #[arg(long, default_value_t = 1)]
    pub outlier_seed: u64,
    /// Robot ROBOT asks its neighbours for the team map at round N: ROBOT@N (repeatable);
    /// the bytes count under the kind team_map.
    #[arg(long, value_name = "ROBOT@ROUND")]
    pub team_map: Vec<String>,
    /// Feed each robot's poses N per round (with their odometry, closures once both poses
    /// exist), as a running back-end is fed, instead of all at the start.
    #[arg(long, value_name = "N")]
    pub stream: Option<usize>,
    /// Send whole condensed graphs instead of updates of the version a neighbour holds
    /// (to measure what the updates save).
    #[arg(long)]
    pub whole_graphs: bool,
    /// Condensed method: the solver copies its trajectory to a standby robot, so the robot
    /// that takes over when it leaves keeps its trajectory and every closure (the robots
    /// above it send theirs with it again). On by default; accepted for scripts that
    /// asked for it.
    #[arg(long, conflicts_with = "no_standby_copy")]
    pub standby_copy: bool,
    /// Condensed method: no standby copy (the solver's trajectory and the closures only it
    /// sent are lost when it leaves; measures what the copy costs).
    #[arg(long)]
    pub no_standby_copy: bool,
    /// Condensed method: condense each robot's graph once, at its odometry (the scheme
    /// before relinearization, to measure what relinearizing buys).
    #[arg(long)]
    pub no_relinearize: bool,
    /// Iteration limit of the solver of the team's separator graph (condensed method).
    #[arg(long)]
    pub max_iterations: Option<usize>,
    /// Plain Gauss-Seidel / block-coordinate descent, without Nesterov momentum.
    #[arg(long)]
    pub no_momentum: bool,
    /// DGS stage 1 ends when a robot's relaxed rotations change by less than this in one
    /// step (Frobenius norm over its poses; default 0.01, the paper's 0.1).
    #[arg(long)]
    pub rotation_change: Option<f64>,
    /// DGS stage 2 ends when a robot's translations change by less than this in one step
    /// (m, norm over its poses; default 0.01, the paper's 0.5).
    #[arg(long)]
    pub pose_change: Option<f64>,
    /// A DGS stage ends after this much solving time even if it has not converged
    /// (seconds on the agents' clock, --round-s per round; default 20).
    #[arg(long)]
    pub max_stage_s: Option<f64>,
    /// DGS: a robot sends a separator's estimate only once it moved by more than this from
    /// what the neighbour holds (relaxed rotation: Frobenius norm; pose: m + rad; default
    /// 0.001). 0 sends every change.
    #[arg(long)]
    pub send_change: Option<f64>,
    /// DGS: a robot that converged in a stage waits at most this long for its neighbours
    /// to converge too before it moves on (seconds on the agents' clock; default 1).
    #[arg(long)]
    pub patience_s: Option<f64>,
    /// Add the team's χ² every N rounds, and at every round a robot changes stage, to the
    /// JSON as `trace` (round, chi2, stages, largest_change, rotation_error_deg against the
    /// centralized two-stage rotations, translations_solved_chi2: the translations solved
    /// centrally from the robots' rotations).
    #[arg(long, value_name = "N")]
    pub trace_every: Option<u64>,
    /// Robot ROBOT (a letter) joins at round N: ROBOT@N (repeatable).
    #[arg(long, value_name = "ROBOT@ROUND")]
    pub join: Vec<String>,
    /// Robot ROBOT is out of range from round A to round B: ROBOT@A..B (repeatable).
    #[arg(long, value_name = "ROBOT@A..B")]
    pub outage: Vec<String>,
    /// Skip lines with unknown tags (with a warning) instead of failing.
    #[arg(long)]
    pub skip_unknown: bool,
    /// Information matrices that are not positive definite: refuse (check) or repair
    /// (nearest-pd); the distributed back-end needs positive-definite ones.
    #[arg(long, value_enum, default_value_t = InformationArg::Check)]
    pub information: InformationArg,
    /// Write the team's estimate as it ends to this g2o file: every robot's poses as
    /// `VERTEX_SE3:QUAT` lines, after one comment `# robot R anchor A` per robot in a frame
    /// (A: the robot whose first pose fixes it).
    #[arg(long, value_name = "FILE.g2o")]
    pub out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LinkArg {
    Session,
    Direct,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum MethodArg {
    Dgs,
    Condensed,
}

fn robot_letter(flag: &str, s: &str) -> Result<u8> {
    match s.as_bytes() {
        [c] => key::robot_of_char(*c),
        _ => None,
    }
    .with_context(|| {
        format!("{flag} {s:?}: the robot is one letter a-z or A-Z, as in the graph's keys")
    })
}

fn parse_at(flag: &str, v: &[String]) -> Result<BTreeMap<u8, u64>> {
    v.iter()
        .map(|s| {
            let (r, n) = s
                .split_once('@')
                .with_context(|| format!("{flag} {s:?}: expected ROBOT@ROUND, e.g. c@20"))?;
            Ok((
                robot_letter(flag, r)?,
                n.parse()
                    .with_context(|| format!("{flag} {s:?}: round {n:?} is not a number"))?,
            ))
        })
        .collect()
}

fn parse_outage(v: &[String]) -> Result<BTreeMap<u8, std::ops::Range<u64>>> {
    v.iter()
        .map(|s| {
            let parsed = s.split_once('@').and_then(|(r, span)| {
                let (a, b) = span.split_once("..")?;
                Some((r, a.parse::<u64>().ok()?, b.parse::<u64>().ok()?))
            });
            let Some((r, a, b)) = parsed.filter(|(_, a, b)| a < b) else {
                bail!("--outage {s:?}: expected ROBOT@A..B with A < B, e.g. b@10..60");
            };
            Ok((robot_letter("--outage", r)?, a..b))
        })
        .collect()
}

pub fn run(args: DpgoArgs) -> Result<()> {
    for (flag, p) in [
        ("--drop", args.drop),
        ("--reorder", args.reorder),
        ("--duplicate", args.duplicate),
    ] {
        if !(0.0..1.0).contains(&p) {
            bail!("{flag} {p}: a probability in [0, 1)");
        }
    }
    if args.link == LinkArg::Direct && (args.reorder > 0.0 || args.duplicate > 0.0) {
        bail!("--reorder and --duplicate need --link session (the runner's own link only drops)");
    }
    for (flag, t) in [
        ("--round-s", args.round_s),
        ("--retransmit-s", args.retransmit_s),
    ] {
        if !(0.001..=3600.0).contains(&t) {
            bail!("{flag} {t}: seconds between 0.001 and 3600");
        }
    }
    if matches!(args.information, InformationArg::AsIs) {
        bail!("--information as-is: the distributed back-end needs positive-definite information (use check or nearest-pd)");
    }
    let mut graph = super::pcm::merge_files(&args.files, args.skip_unknown, args.information)?;
    let mut labels = match &args.labels {
        Some(path) => Some(read_labels(path)?),
        None => None,
    };
    if let Some(f) = args.inject_outliers {
        if args.labels.is_some() {
            bail!("--inject-outliers labels the closures itself: leave out --labels");
        }
        let (g, l) = inject_outliers(&graph, f, args.outlier_seed)
            .with_context(|| format!("--inject-outliers {f}"))?;
        graph = g;
        labels = Some(l);
    }
    let mut agent = if args.paper_thresholds {
        AgentOptions {
            method: Method::Dgs,
            ..AgentOptions::paper()
        }
    } else {
        AgentOptions::default()
    };
    if let Some(g) = args.gamma {
        if !(g > 0.0 && g < 2.0) {
            bail!("--gamma {g}: over-relaxation needs 0 < γ < 2");
        }
        // With --damp-on-reversal γ is the damped step's; full steps stay full.
        if !args.damp_on_reversal {
            agent.gamma = g;
        }
        agent.async_gamma = g;
    }
    agent.damp_on_reversal = args.damp_on_reversal;
    agent.momentum = !args.no_momentum;
    for (flag, v, field) in [
        (
            "--rotation-change",
            args.rotation_change,
            &mut agent.rotation_change,
        ),
        ("--pose-change", args.pose_change, &mut agent.pose_change),
    ] {
        if let Some(v) = v {
            if !(v > 0.0 && v.is_finite()) {
                bail!("{flag} {v}: a positive threshold");
            }
            *field = v;
        }
    }
    if let Some(s) = args.max_stage_s {
        if !(0.001..=1e6).contains(&s) {
            bail!("--max-stage-s {s}: seconds between 0.001 and 1e6");
        }
        agent.max_stage = Duration::from_secs_f64(s);
    }
    if let Some(v) = args.send_change {
        if !(v >= 0.0 && v.is_finite()) {
            bail!("--send-change {v}: a threshold of 0 or more");
        }
        agent.send_rotation = v;
        agent.send_pose = v;
    }
    if let Some(s) = args.patience_s {
        if !(0.0..=1e6).contains(&s) {
            bail!("--patience-s {s}: seconds between 0 and 1e6");
        }
        agent.patience = Duration::from_secs_f64(s);
    }
    if args.trace_every == Some(0) {
        bail!("--trace-every 0: at least one round between points");
    }
    if args.no_relinearize {
        agent.relinearize_fraction = f64::INFINITY;
    }
    if let Some(n) = args.max_iterations {
        if n == 0 {
            bail!("--max-iterations 0: at least one iteration");
        }
        agent.solver.max_iterations = n;
    }
    agent.graph_updates = !args.whole_graphs;
    agent.standby_copy = !args.no_standby_copy;
    if args.stream == Some(0) {
        bail!("--stream 0: at least one pose per round");
    }
    if let Some(p) = args.pcm {
        if !(p > 0.0 && p < 1.0) {
            bail!("--pcm {p}: a probability strictly between 0 and 1");
        }
        if matches!(args.method, MethodArg::Dgs) {
            bail!("--pcm runs inside the condensed method only (DGS: check closures first with doorslam pcm)");
        }
        agent.pcm = Some(PcmSettings {
            threshold: p,
            min_clique: args.min_clique,
            cycles: !args.no_cycles,
        });
    }
    agent.method = match args.method {
        MethodArg::Dgs => Method::Dgs,
        MethodArg::Condensed => Method::Condensed,
    };
    // Validated above to 1 ms .. 1 h, so the cast neither truncates nor saturates.
    let round_ms = (args.round_s * 1000.0).round() as u64;
    let mut options = RunOptions {
        agent,
        drop: args.drop,
        seed: args.seed,
        max_rounds: args.max_rounds,
        join_at: parse_at("--join", &args.join)?,
        outage: parse_outage(&args.outage)?,
        team_map: parse_at("--team-map", &args.team_map)?,
        stream: args.stream,
        trace_every: args.trace_every,
        // The agents' clock and the team link's advance together, a round at a time.
        round: Duration::from_millis(round_ms),
    };
    let names = args
        .files
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let mut link = (args.link == LinkArg::Session).then(|| {
        options.agent.link_delivers = true;
        SessionLink::new(LinkOptions {
            faults: Faults {
                drop: args.drop,
                reorder: args.reorder,
                duplicate: args.duplicate,
                seed: args.seed,
            },
            round_ms,
            protocol: ProtocolConfig {
                retransmit_ms: (args.retransmit_s * 1000.0).round() as u64,
                ..ProtocolConfig::default()
            },
        })
    });
    let r = run_over(
        &graph,
        &options,
        link.as_mut().map(|l| l as &mut dyn Transport),
    )
    .with_context(|| format!("distributed PGO of {names}"))?;
    let link_json = link.as_ref().map(|l| {
        let d = l.delivery();
        serde_json::json!({
            "link": "session",
            "held_back": d.held_back,
            "beyond_hold_back": d.beyond_hold_back,
            "superseded": d.superseded,
            "most_waiting": d.most_waiting,
            "reordered": l.reordered,
            "duplicated": l.duplicated,
            "not_taken": l.not_taken,
        })
    });
    // Kept: every labelled closure PCM did not reject in the loop (the same verdicts on
    // every robot that solves).
    let quality = labels.as_ref().map(|l| {
        let rejected: BTreeSet<(u64, u64)> = r
            .rejected_keys
            .iter()
            .map(|&(a, b)| unordered(a, b))
            .collect();
        let kept: BTreeSet<(u64, u64)> = graph
            .edges()
            .iter()
            .map(|e| unordered(graph.keys()[e.i], graph.keys()[e.j]))
            .filter(|p| !rejected.contains(p))
            .collect();
        let q = l.quality(&kept);
        let inliers = q.true_positives + q.false_negatives;
        let outliers = l.len() - inliers;
        serde_json::json!({
            "pcm_precision": q.precision,
            "pcm_recall": q.recall,
            "inliers": inliers,
            "inliers_rejected": q.false_negatives,
            "outliers": outliers,
            "outliers_rejected": outliers - q.false_positives.min(outliers),
        })
    });
    if let Some(out) = &args.out {
        // Which frame each robot ended in, for tools that compare with ground truth
        // (a robot never connected to the anchor keeps its own frame).
        let mut text = String::new();
        for (robot, anchor) in &r.anchors {
            text.push_str(&format!(
                "# robot {} anchor {}\n",
                key::robot_char(*robot)?,
                key::robot_char(*anchor)?
            ));
        }
        for (k, x) in &r.estimate {
            text.push_str(&doorslam_backend::g2o::se3_vertex_line(*k, x));
            text.push('\n');
        }
        std::fs::write(out, text).with_context(|| format!("--out {}", out.display()))?;
    }
    if args.json {
        let mut v = serde_json::to_value(&r)?;
        if let (Some(serde_json::Value::Object(q)), Some(o)) = (&quality, v.as_object_mut()) {
            o.extend(q.clone());
        }
        match (&link_json, v.as_object_mut()) {
            (Some(serde_json::Value::Object(q)), Some(o)) => o.extend(q.clone()),
            (None, Some(o)) => {
                o.insert("link".into(), "direct".into());
            }
            _ => {}
        }
        println!("{v}");
    } else {
        println!(
            "{:?}: {} robots, {} poses ({} separators): {} in {} rounds",
            r.method,
            r.robots,
            r.poses,
            r.separators,
            if r.converged {
                "converged"
            } else {
                "NOT converged"
            },
            r.iterations
        );
        println!(
            "chi2 distributed {:.6e} vs centralized {:.6e} (gap {:+.3} %), ATE to centralized {:.4} m",
            r.distributed_chi2,
            r.centralized_chi2,
            100.0 * r.chi2_gap,
            r.ate_to_centralized
        );
        println!(
            "{} messages, {} bytes (centralized: {} bytes, ratio {:.3}); {} dropped, {} resent",
            r.messages, r.bytes, r.bytes_centralized, r.bytes_ratio, r.dropped, r.resent
        );
        if let Some(q) = &quality {
            println!(
                "PCM against the labels: precision {:.3}, recall {:.3}; outliers rejected {} of {}, inliers rejected {} of {}",
                q["pcm_precision"].as_f64().unwrap_or(f64::NAN),
                q["pcm_recall"].as_f64().unwrap_or(f64::NAN),
                q["outliers_rejected"],
                q["outliers"],
                q["inliers_rejected"], q["inliers"]
            );
        }
        if args.pcm.is_some() {
            println!(
                "PCM: {} of {} inter-robot closures rejected in the loop, {} by the centralized oracle",
                r.rejected_distributed, r.closures, r.rejected_centralized
            );
        }
    }
    Ok(())
}
