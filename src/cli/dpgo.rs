//! `doorslam dpgo FILE [FILE...]`: distributed pose-graph optimization of a team, played
//! in-process over an emulated link, compared with the centralized optimum.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use doorslam_backend::distributed::condensed::PcmSettings;
use doorslam_backend::distributed::runner::{run as run_team, RunOptions};
use doorslam_backend::distributed::{AgentOptions, Method};

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
    /// Over-relaxation γ of the two linear stages.
    #[arg(long)]
    pub gamma: Option<f64>,
    /// The distributed solver: the paper's two-stage distributed Gauss-Seidel with
    /// block-coordinate refinement (dgs), or the condensed separator graph (condensed).
    #[arg(long, value_enum, default_value_t = MethodArg::Condensed)]
    pub method: MethodArg,
    /// Run PCM inside the loop with this probability threshold (condensed method; the
    /// centralized reference runs offline PCM with the same settings).
    #[arg(long)]
    pub pcm: Option<f64>,
    /// Ground truth of the closures (`doorslam sim graph`'s labels.txt: key_a key_b ...
    /// label, 1 inlier / 0 outlier): report PCM's precision and recall in the loop.
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Smallest clique PCM keeps per robot pair.
    #[arg(long, default_value_t = 2)]
    pub min_clique: usize,
    /// Plain Gauss-Seidel / block-coordinate descent, without Nesterov momentum.
    #[arg(long)]
    pub no_momentum: bool,
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
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum MethodArg {
    Dgs,
    Condensed,
}

fn robot_letter(flag: &str, s: &str) -> Result<u8> {
    match s.as_bytes() {
        [c @ b'a'..=b'z'] => Ok(c - b'a'),
        _ => bail!("{flag} {s:?}: the robot is one letter a-z, as in the graph's keys"),
    }
}

fn parse_join(v: &[String]) -> Result<BTreeMap<u8, u64>> {
    v.iter()
        .map(|s| {
            let (r, n) = s
                .split_once('@')
                .with_context(|| format!("--join {s:?}: expected ROBOT@ROUND, e.g. c@20"))?;
            Ok((
                robot_letter("--join", r)?,
                n.parse()
                    .with_context(|| format!("--join {s:?}: round {n:?} is not a number"))?,
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

/// Precision and recall of the kept closures against a labels file.
fn pcm_quality(path: &std::path::Path, rejected: &[(u64, u64)]) -> Result<(f64, f64)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let rejected: std::collections::BTreeSet<(u64, u64)> = rejected
        .iter()
        .flat_map(|&(a, b)| [(a, b), (b, a)])
        .collect();
    let (mut tp, mut fp, mut fne) = (0u64, 0u64, 0u64);
    for (n, line) in text.lines().enumerate() {
        if line.starts_with('#') || line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        let parse = |i: usize| -> Result<u64> {
            f.get(i).and_then(|v| v.parse().ok()).with_context(|| {
                format!(
                    "{}:{}: field {} is not a number",
                    path.display(),
                    n + 1,
                    i + 1
                )
            })
        };
        let (a, b, label) = (parse(0)?, parse(1)?, parse(6)?);
        let kept = !rejected.contains(&(a, b));
        match (label == 1, kept) {
            (true, true) => tp += 1,
            (false, true) => fp += 1,
            (true, false) => fne += 1,
            (false, false) => {}
        }
    }
    let precision = tp as f64 / (tp + fp).max(1) as f64;
    let recall = tp as f64 / (tp + fne).max(1) as f64;
    Ok((precision, recall))
}

pub fn run(args: DpgoArgs) -> Result<()> {
    if !(0.0..1.0).contains(&args.drop) {
        bail!("--drop {}: a probability in [0, 1)", args.drop);
    }
    if matches!(args.information, InformationArg::AsIs) {
        bail!("--information as-is: the distributed back-end needs positive-definite information (use check or nearest-pd)");
    }
    let graph = super::pcm::merge_files(&args.files, args.skip_unknown, args.information)?;
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
        agent.gamma = g;
    }
    agent.momentum = !args.no_momentum;
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
        });
    }
    agent.method = match args.method {
        MethodArg::Dgs => Method::Dgs,
        MethodArg::Condensed => Method::Condensed,
    };
    let options = RunOptions {
        agent,
        drop: args.drop,
        seed: args.seed,
        max_rounds: args.max_rounds,
        join_at: parse_join(&args.join)?,
        outage: parse_outage(&args.outage)?,
    };
    let names = args
        .files
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let r = run_team(&graph, &options).with_context(|| format!("distributed PGO of {names}"))?;
    let quality = match &args.labels {
        Some(path) => Some(pcm_quality(path, &r.rejected_keys)?),
        None => None,
    };
    if args.json {
        let mut v = serde_json::to_value(&r)?;
        if let (Some((precision, recall)), Some(o)) = (quality, v.as_object_mut()) {
            o.insert("pcm_precision".into(), precision.into());
            o.insert("pcm_recall".into(), recall.into());
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
        if let Some((precision, recall)) = quality {
            println!("PCM against the labels: precision {precision:.3}, recall {recall:.3}");
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
