//! `doorslam sim pcm-sweep`: the paper's simulation (Fig. 5/6) at pose-graph level.
//!
//! For each run a team is simulated ([`doorslam_hil::posegraph_sim`]), and for each PCM
//! threshold p the inter-robot closures are filtered by
//! - `pcm`: PCM's maximum clique alone;
//! - `pcm+readmit`: PCM, PGO on the clique, then every rejected closure whose residual at
//!   the optimized estimate is below χ²₆(0.99) is re-admitted and PGO runs again with GNC
//!   on the loop closures (so a wrong re-admission can still be dropped);
//! - `pcm+gnc`: PCM, then PGO with GNC (truncated least squares) on the clique's closures;
//!
//! and the team's trajectories are optimized (chordal + LM) with odometry and the kept
//! closures. Robots left without an accepted closure to robot a's component cannot be put
//! in the team frame: the ATE covers the robots connected to robot a. Reported per threshold and method, mean ± std over runs: % of outliers
//! rejected, % of inliers rejected, ATE (all robots, SE(3)-aligned to ground truth).
//! Baselines without any rejection (`none`) and with GNC alone (`gnc`) are reported once.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use doorslam_backend::eval::{absolute_trajectory_error, Alignment, Trajectory};
use doorslam_backend::init::Chordal;
use doorslam_backend::outliers::{Pcm, Scope};
use doorslam_backend::robust::chi2_quantile;
use doorslam_backend::{key, optimize, Kernel, PoseGraph, SolverOptions};
use doorslam_hil::posegraph_sim::{simulate, SimulatedTeam};
use nalgebra::Isometry3;

#[derive(Debug, Args)]
pub struct SweepArgs {
    #[arg(long, default_value_t = 100)]
    pub runs: usize,
    #[command(flatten)]
    pub team: crate::cli::sim::TeamArgs,
    /// PCM thresholds (probabilities).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.01,0.05,0.1,0.25,0.5,0.75,0.9,0.99"
    )]
    pub thresholds: Vec<f64>,
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Write an SVG plot of the rejection rates and ATE here.
    #[arg(long)]
    pub svg: Option<PathBuf>,
    /// Print one JSON object instead of the Markdown table.
    #[arg(long)]
    pub json: bool,
}

const METHODS: [&str; 3] = ["pcm", "pcm+readmit", "pcm+gnc"];

/// Mean and standard deviation accumulator.
#[derive(Debug, Clone, Default)]
struct Stat(Vec<f64>);

impl Stat {
    fn push(&mut self, v: f64) {
        self.0.push(v);
    }
    fn mean(&self) -> f64 {
        self.0.iter().sum::<f64>() / self.0.len().max(1) as f64
    }
    fn std(&self) -> f64 {
        let m = self.mean();
        (self.0.iter().map(|v| (v - m).powi(2)).sum::<f64>() / self.0.len().max(1) as f64).sqrt()
    }
}

#[derive(Debug, Clone, Default)]
struct Cell {
    outliers_rejected: Stat,
    inliers_rejected: Stat,
    ate: Stat,
    /// Robots in robot a's component (the ones the ATE covers).
    robots: Stat,
}

/// Result of one selection: which closures were kept and the ATE after PGO.
struct Outcome {
    kept: Vec<bool>,
    ate: f64,
    robots: usize,
}

/// Odometry plus the kept closures, optimized from the chordal initialization; with GNC
/// on the loop closures if `gnc`. Returns the estimate and the closures GNC kept.
fn solve(
    team: &SimulatedTeam,
    kept: &[bool],
    gnc: bool,
) -> Result<(PoseGraph<Isometry3<f64>>, Vec<bool>)> {
    let n_odo = team.odometry_edges().len();
    let mut g = team.graph.clone();
    let mut index_of_edge = Vec::new();
    let mut k = 0;
    g.retain_edges(|_| {
        let keep = k < n_odo || kept[k - n_odo];
        if keep && k >= n_odo {
            index_of_edge.push(k - n_odo);
        }
        k += 1;
        keep
    });
    let (mut g, index_of_edge) = connected_to_first(&g, &index_of_edge)?;
    Isometry3::chordal(&mut g, 0)?;
    let c2 = chi2_quantile(0.99, 6).context("χ² quantile")?;
    let opts = SolverOptions {
        loop_kernel: if gnc {
            Kernel::Gnc { c2 }
        } else {
            Kernel::None
        },
        ..Default::default()
    };
    let s = optimize(&mut g, 0, &opts)?;
    let mut final_kept = vec![false; kept.len()];
    let n_odo_connected = g.edges().len() - index_of_edge.len();
    for (w, &c) in s.weights[n_odo_connected..].iter().zip(&index_of_edge) {
        final_kept[c] = !gnc || *w > 0.5;
    }
    Ok((g, final_kept))
}

/// The part of `g` connected to its first pose (robots with no accepted closure to the
/// rest of the team cannot be placed in the team's frame), with the closure index of each
/// kept loop-closure edge carried along.
fn connected_to_first(
    g: &PoseGraph<Isometry3<f64>>,
    closure_of_edge: &[usize],
) -> Result<(PoseGraph<Isometry3<f64>>, Vec<usize>)> {
    let n_odo = g.edges().len() - closure_of_edge.len();
    let seen = g.reachable_from(0);
    let mut sub = PoseGraph::new();
    let mut new_index = vec![usize::MAX; g.len()];
    for (p, (&k, pose)) in g.keys().iter().zip(g.poses()).enumerate() {
        if seen[p] {
            new_index[p] = sub.add_pose(k, *pose);
        }
    }
    let mut closures = Vec::new();
    for (n, e) in g.edges().iter().enumerate() {
        if seen[e.i] && seen[e.j] {
            sub.add_edge(new_index[e.i], new_index[e.j], e.measured, e.information)?;
            if n >= n_odo {
                closures.push(closure_of_edge[n - n_odo]);
            }
        }
    }
    Ok((sub, closures))
}

fn robots_in(g: &PoseGraph<Isometry3<f64>>) -> usize {
    g.keys()
        .iter()
        .map(|k| key::robot(*k))
        .collect::<BTreeSet<_>>()
        .len()
}

fn ate(team: &SimulatedTeam, g: &PoseGraph<Isometry3<f64>>) -> Result<f64> {
    let mut est = Vec::new();
    let mut gt = Vec::new();
    for (k, p) in g.keys().iter().zip(g.poses()) {
        if let Some(t) = team.true_pose(*k) {
            est.push(*p);
            gt.push(*t);
        }
    }
    let r = absolute_trajectory_error(
        &Trajectory::from_poses(gt),
        &Trajectory::from_poses(est),
        Alignment::Se3,
    )?;
    Ok(r.stats.rmse)
}

/// PCM's kept closures as a mask over `team.closures`.
fn pcm_mask(team: &SimulatedTeam, p: f64) -> Result<Vec<bool>> {
    let mut pcm = Pcm::new(p, Scope::InterRobot)?;
    let s = pcm.run(&team.graph)?;
    let kept: BTreeSet<(u64, u64)> = s
        .inliers
        .iter()
        .flat_map(|&(a, b)| [(a, b), (b, a)])
        .collect();
    Ok(team
        .closures
        .iter()
        .map(|c| kept.contains(&(c.key_a, c.key_b)))
        .collect())
}

fn method(team: &SimulatedTeam, p: f64, name: &str) -> Result<Outcome> {
    let mask = pcm_mask(team, p)?;
    match name {
        "pcm" => {
            let (g, kept) = solve(team, &mask, false)?;
            Ok(Outcome {
                ate: ate(team, &g)?,
                robots: robots_in(&g),
                kept,
            })
        }
        "pcm+gnc" => {
            let (g, kept) = solve(team, &mask, true)?;
            Ok(Outcome {
                ate: ate(team, &g)?,
                robots: robots_in(&g),
                kept,
            })
        }
        "pcm+readmit" => {
            let (g, _) = solve(team, &mask, false)?;
            let gamma = chi2_quantile(0.99, 6).context("χ² quantile")?;
            let n_odo = team.odometry_edges().len();
            let rejected: Vec<usize> = (0..mask.len()).filter(|c| !mask[*c]).collect();
            let candidates: Vec<(u64, u64, &doorslam_backend::BetweenFactor<Isometry3<f64>>)> =
                rejected
                    .iter()
                    .map(|&c| {
                        let e = &team.graph.edges()[n_odo + c];
                        (team.graph.keys()[e.i], team.graph.keys()[e.j], e)
                    })
                    .collect();
            let mut readmitted = mask.clone();
            for k in doorslam_backend::outliers::readmit(&g, &candidates, gamma) {
                readmitted[rejected[k]] = true;
            }
            let (g, kept) = solve(team, &readmitted, true)?;
            Ok(Outcome {
                ate: ate(team, &g)?,
                robots: robots_in(&g),
                kept,
            })
        }
        other => bail!("unknown method {other}"),
    }
}

fn rates(team: &SimulatedTeam, kept: &[bool]) -> (f64, f64) {
    let (mut out, mut out_rej, mut inl, mut inl_rej) = (0, 0, 0, 0);
    for (c, k) in team.closures.iter().zip(kept) {
        if key::robot(c.key_a) == key::robot(c.key_b) {
            continue;
        }
        if c.inlier {
            inl += 1;
            inl_rej += usize::from(!k);
        } else {
            out += 1;
            out_rej += usize::from(!k);
        }
    }
    let pct = |a: usize, b: usize| {
        if b == 0 {
            100.0 * f64::from(u8::from(a == 0))
        } else {
            100.0 * a as f64 / b as f64
        }
    };
    (pct(out_rej, out).min(100.0), pct(inl_rej, inl))
}

pub fn run(args: SweepArgs) -> Result<()> {
    for p in &args.thresholds {
        if !(*p > 0.0 && *p < 1.0) {
            bail!("--thresholds: {p} is not a probability strictly between 0 and 1");
        }
    }
    anyhow::ensure!(args.runs > 0, "--runs must be at least 1");
    let mut cells = vec![vec![Cell::default(); METHODS.len()]; args.thresholds.len()];
    let (mut none, mut gnc_only) = (Cell::default(), Cell::default());
    let start = std::time::Instant::now();
    for run in 0..args.runs {
        let config = args.team.config(args.first_seed + run as u64);
        let team = simulate(&config)?;
        let all = vec![true; team.closures.len()];
        for (cell, gnc) in [(&mut none, false), (&mut gnc_only, true)] {
            let (g, kept) = solve(&team, &all, gnc)?;
            let (o, i) = rates(&team, &kept);
            cell.outliers_rejected.push(o);
            cell.inliers_rejected.push(i);
            cell.ate.push(ate(&team, &g)?);
            cell.robots.push(robots_in(&g) as f64);
        }
        for (t, &p) in args.thresholds.iter().enumerate() {
            for (m, name) in METHODS.iter().enumerate() {
                let outcome = method(&team, p, name)?;
                let (o, i) = rates(&team, &outcome.kept);
                let cell = &mut cells[t][m];
                cell.outliers_rejected.push(o);
                cell.inliers_rejected.push(i);
                cell.ate.push(outcome.ate);
                cell.robots.push(outcome.robots as f64);
            }
        }
        if (run + 1) % 10 == 0 || run + 1 == args.runs {
            eprintln!(
                "pcm-sweep: {}/{} runs, {:.1} s",
                run + 1,
                args.runs,
                start.elapsed().as_secs_f64()
            );
        }
    }
    if let Some(path) = &args.svg {
        std::fs::write(path, svg(&args.thresholds, &cells))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let fmt = |s: &Stat| format!("{:.1} ± {:.1}", s.mean(), s.std());
    let fmt_ate = |s: &Stat| format!("{:.3} ± {:.3}", s.mean(), s.std());
    if args.json {
        let row = |c: &Cell| {
            serde_json::json!({
                "outliers_rejected_pct": c.outliers_rejected.mean(), "outliers_rejected_std": c.outliers_rejected.std(),
                "inliers_rejected_pct": c.inliers_rejected.mean(), "inliers_rejected_std": c.inliers_rejected.std(),
                "ate_m": c.ate.mean(), "ate_std": c.ate.std(), "robots_connected": c.robots.mean(),
            })
        };
        let per: Vec<serde_json::Value> = args
            .thresholds
            .iter()
            .zip(&cells)
            .map(|(p, row_cells)| {
                let mut m = serde_json::Map::new();
                m.insert("threshold".into(), (*p).into());
                for (name, c) in METHODS.iter().zip(row_cells) {
                    m.insert((*name).into(), row(c));
                }
                serde_json::Value::Object(m)
            })
            .collect();
        println!(
            "{}",
            serde_json::json!({"runs": args.runs, "robots": args.team.robots, "poses": args.team.poses, "outliers": args.team.outliers,
            "correlated_groups": args.team.correlated_groups, "none": row(&none), "gnc": row(&gnc_only), "thresholds": per})
        );
        return Ok(());
    }
    println!(
        "{} runs, {} robots x {} poses, {:.0} % outliers, {} correlated groups; mean ± std over runs\n",
        args.runs,
        args.team.robots,
        args.team.poses,
        100.0 * args.team.outliers,
        args.team.correlated_groups
    );
    println!("| PCM p | method | outliers rejected (%) | inliers rejected (%) | ATE (m) | robots in ATE |");
    println!("| ---: | --- | ---: | ---: | ---: | ---: |");
    for (name, c) in [("none (all closures)", &none), ("GNC alone", &gnc_only)] {
        println!(
            "| - | {name} | {} | {} | {} | {:.1} |",
            fmt(&c.outliers_rejected),
            fmt(&c.inliers_rejected),
            fmt_ate(&c.ate),
            c.robots.mean()
        );
    }
    for (p, row_cells) in args.thresholds.iter().zip(&cells) {
        for (name, c) in METHODS.iter().zip(row_cells) {
            println!(
                "| {:.0} % | {name} | {} | {} | {} | {:.1} |",
                100.0 * p,
                fmt(&c.outliers_rejected),
                fmt(&c.inliers_rejected),
                fmt_ate(&c.ate),
                c.robots.mean()
            );
        }
    }
    Ok(())
}

/// A two-panel SVG: rejection rates (left) and ATE (right) against the threshold.
fn svg(thresholds: &[f64], cells: &[Vec<Cell>]) -> String {
    let (w, h, pad) = (420.0, 300.0, 50.0);
    let x = |i: usize| pad + (w - 2.0 * pad) * i as f64 / (thresholds.len().max(2) - 1) as f64;
    let max_ate = cells
        .iter()
        .flatten()
        .map(|c| c.ate.mean() + c.ate.std())
        .fold(1e-9, f64::max);
    let colors = ["#1f77b4", "#2ca02c", "#9467bd"];
    let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"11\">\n", 2.0 * w);
    for (panel, title) in [
        (0.0, "rejected (%): outliers solid, inliers dashed"),
        (w, "ATE after PGO (m)"),
    ] {
        s += &format!(
            "<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#888\"/>\n",
            panel + pad,
            pad,
            w - 2.0 * pad,
            h - 2.0 * pad
        );
        s += &format!("<text x=\"{}\" y=\"30\">{title}</text>\n", panel + pad);
        for (i, p) in thresholds.iter().enumerate() {
            s += &format!(
                "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{:.0}</text>\n",
                panel + x(i),
                h - pad + 15.0,
                100.0 * p
            );
        }
        s += &format!(
            "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">PCM threshold (%)</text>\n",
            panel + w / 2.0,
            h - 12.0
        );
    }
    let y_pct = |v: f64| h - pad - (h - 2.0 * pad) * v / 100.0;
    let y_ate = |v: f64| h - pad - (h - 2.0 * pad) * v / max_ate;
    s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"end\">100</text><text x=\"{}\" y=\"{}\" text-anchor=\"end\">0</text>\n", pad - 4.0, pad + 4.0, pad - 4.0, h - pad);
    s += &format!(
        "<text x=\"{}\" y=\"{}\" text-anchor=\"end\">{max_ate:.2}</text>\n",
        w + pad - 4.0,
        pad + 4.0
    );
    for (m, name) in METHODS.iter().enumerate() {
        let line = |f: &dyn Fn(&Cell) -> f64, y: &dyn Fn(f64) -> f64, offset: f64| -> String {
            cells
                .iter()
                .enumerate()
                .map(|(i, row)| format!("{:.1},{:.1}", offset + x(i), y(f(&row[m]))))
                .collect::<Vec<_>>()
                .join(" ")
        };
        let c = colors[m % colors.len()];
        s += &format!(
            "<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"2\" points=\"{}\"/>\n",
            line(&|c| c.outliers_rejected.mean(), &y_pct, 0.0)
        );
        s += &format!("<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"2\" stroke-dasharray=\"5,3\" points=\"{}\"/>\n", line(&|c| c.inliers_rejected.mean(), &y_pct, 0.0));
        s += &format!(
            "<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"2\" points=\"{}\"/>\n",
            line(&|c| c.ate.mean(), &y_ate, w)
        );
        s += &format!(
            "<text x=\"{}\" y=\"{}\" fill=\"{c}\">{name}</text>\n",
            w + pad + 8.0,
            pad + 14.0 + 14.0 * m as f64
        );
    }
    s + "</svg>\n"
}
