//! `doorslam pcm FILE.g2o [FILE...]`: reject outlier loop closures with PCM.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use doorslam_backend::outliers::labels::unordered;
use doorslam_backend::outliers::{read_labels, Pcm, Scope};
use doorslam_backend::{key, write_g2o, EdgeClass, Graph, PoseGraph, ReadOptions, UnknownTags};
use nalgebra::Isometry3;

use super::pgo::InformationArg;

#[derive(Debug, Args)]
pub struct PcmArgs {
    /// 3-D g2o graph(s) with multi-robot keys; several files (one per robot, as
    /// distributed mappers write them) are merged, edges present in two files kept once.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Probability p that a consistent pair passes (γ = χ²₆ quantile of p). The default
    /// 0.99 keeps most inliers and relies on the maximum clique to remove outliers; the
    /// paper's field setting 0.01 keeps only the most precise closures.
    #[arg(long, default_value_t = 0.99)]
    pub threshold: f64,
    /// Check loop closures within each robot instead of between robots.
    #[arg(long)]
    pub intra: bool,
    /// Give up proving the clique maximum after this many seconds (the best clique found
    /// is kept and reported with "exact": false).
    #[arg(long)]
    pub time_budget: Option<f64>,
    /// Smallest clique kept per robot pair: a single closure between two robots cannot be
    /// checked against anything, so by default (2) it waits for a consistent second one.
    #[arg(long, default_value_t = 2)]
    pub min_clique: usize,
    /// Plain pairwise PCM: do not check the closures of robot pairs left without an
    /// accepted clique (a closure alone between two robots) through 3-robot cycles.
    #[arg(long)]
    pub no_cycles: bool,
    /// Ground truth of the closures (`doorslam sim graph`'s labels.txt or a benchmark's
    /// inter_robot_labels.txt): report precision and recall of the kept closures.
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Skip lines with unknown tags (with a warning) instead of failing.
    #[arg(long)]
    pub skip_unknown: bool,
    /// Information matrices that are not positive definite: refuse the file (check), use
    /// them as written (as-is: PCM then fails on a candidate or odometry edge that has one,
    /// as it needs covariances) or repair them (nearest-pd).
    #[arg(long, value_enum, default_value_t = InformationArg::Check)]
    pub information: InformationArg,
    /// Write the merged graph with the rejected closures removed.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Merges per-robot files: poses from the file that has their VERTEX line, edges once.
fn merge(args: &PcmArgs) -> Result<PoseGraph<Isometry3<f64>>> {
    merge_files(&args.files, args.skip_unknown, args.information)
}

/// Merges per-robot files (or reads one merged file): poses from the file that has their
/// VERTEX line, edges once. Shared with `doorslam dpgo`.
pub(super) fn merge_files(
    files: &[PathBuf],
    skip_unknown: bool,
    information: InformationArg,
) -> Result<PoseGraph<Isometry3<f64>>> {
    let unknown = if skip_unknown {
        UnknownTags::Skip
    } else {
        UnknownTags::Error
    };
    let (merged, warnings) = doorslam_backend::g2o::merge_g2o_files(
        files,
        ReadOptions {
            unknown,
            information: information.into(),
        },
    )?;
    for w in &warnings {
        tracing::warn!("{w}");
    }
    Ok(merged)
}

pub fn run(args: PcmArgs) -> Result<()> {
    let graph = merge(&args)?;
    let scope = if args.intra {
        Scope::IntraRobot
    } else {
        Scope::InterRobot
    };
    let mut pcm = Pcm::new(args.threshold, scope).context("--threshold")?;
    pcm.min_clique = args.min_clique;
    pcm.cycles = !args.no_cycles && !args.intra;
    if let Some(b) = args.time_budget {
        pcm.budget = Some(super::seconds("--time-budget", b, super::MAX_WAIT_S)?);
    }
    let names = args
        .files
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let s = pcm.run(&graph).with_context(|| format!("PCM on {names}"))?;
    let quality = match &args.labels {
        Some(path) => {
            let kept: BTreeSet<(u64, u64)> =
                s.inliers.iter().map(|&(a, b)| unordered(a, b)).collect();
            Some(read_labels(path)?.quality(&kept))
        }
        None => None,
    };
    if let Some(out) = &args.out {
        let keep: BTreeSet<(u64, u64)> = s
            .inliers
            .iter()
            .flat_map(|&(a, b)| [(a, b), (b, a)])
            .collect();
        let candidate = if args.intra {
            EdgeClass::IntraLoop
        } else {
            EdgeClass::InterLoop
        };
        let mut filtered = graph.clone();
        let keys = graph.keys().to_vec();
        // One copy of a retransmitted closure: the others would count the measurement twice.
        let duplicates: BTreeSet<usize> = s.duplicates.iter().copied().collect();
        let mut n = 0;
        filtered.retain_edges(|e| {
            n += 1;
            !duplicates.contains(&(n - 1))
                && (graph.edge_class(e) != candidate || keep.contains(&(keys[e.i], keys[e.j])))
        });
        write_g2o(&Graph::Se3(filtered), out)?;
    }
    if args.json {
        let inliers: Vec<[u64; 2]> = s.inliers.iter().map(|&(a, b)| [a, b]).collect();
        let mut v = serde_json::json!({
            "closures": s.closures,
            "duplicates": s.duplicates.len(),
            "consistent_pairs": s.consistent_pairs,
            "inliers": inliers,
            "clique_size": s.clique_size,
            "cycle_confirmed": s.cycle_confirmed,
            "exact": s.exact,
            "time_s": s.time_s,
        });
        if let (Some(q), Some(o)) = (quality, v.as_object_mut()) {
            o.insert("precision".into(), q.precision.into());
            o.insert("recall".into(), q.recall.into());
        }
        println!("{v}");
    } else {
        println!(
            "{names}: {} candidate closures{}, {} consistent pairs, kept {} ({}), {:.4} s",
            s.closures,
            match s.duplicates.len() {
                0 => String::new(),
                n => format!(" ({n} duplicate copies ignored)"),
            },
            s.consistent_pairs,
            s.clique_size,
            if s.exact {
                "maximum clique"
            } else {
                "best clique within the time budget, not proven maximum"
            },
            s.time_s
        );
        let labels: Vec<String> = s
            .inliers
            .iter()
            .map(|&(a, b)| format!("{}-{}", key::label(a), key::label(b)))
            .collect();
        println!("kept: {}", labels.join(" "));
        if s.cycle_confirmed > 0 {
            println!(
                "{} of them confirmed through 3-robot cycles (no second closure of their pair)",
                s.cycle_confirmed
            );
        }
        if let Some(q) = quality {
            println!(
                "against the labels: precision {:.3}, recall {:.3}",
                q.precision, q.recall
            );
        }
    }
    Ok(())
}
