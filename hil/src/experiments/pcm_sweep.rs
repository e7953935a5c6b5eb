//! PCM threshold sweep on simulated teams: the paper's simulation (Fig. 5/6) at pose-graph
//! level, run by `doorslam sim pcm-sweep`.
//!
//! For each run a team is simulated ([`crate::posegraph_sim`]), and for each PCM
//! threshold p the inter-robot closures are filtered by each [`Method`] of
//! [`SweepConfig::methods`]:
//! - [`Method::Pcm`] (`pcm`): PCM's maximum clique alone;
//! - [`Method::PcmReadmit`] (`pcm+readmit`): PCM, PGO on the clique, then every rejected
//!   closure whose residual at the optimized estimate is below χ²₆(0.99) is re-admitted
//!   and PGO runs again with GNC on the loop closures (so a wrong re-admission can still
//!   be dropped);
//! - [`Method::PcmGnc`] (`pcm+gnc`): PCM, then PGO with GNC (truncated least squares) on
//!   the clique's closures;
//!
//! and the team's trajectories are optimized (chordal + LM) with odometry and the kept
//! closures. Robots left without an accepted closure to robot a's component cannot be put
//! in the team frame: the ATE covers the robots connected to robot a. Reported per
//! threshold and method, mean ± std over runs ([`Cell`]): % of outliers rejected, % of
//! inliers rejected, ATE (SE(3)-aligned to ground truth), robots in the ATE. The baselines
//! without any rejection ([`Method::NoRejection`], `none`) and with GNC alone
//! ([`Method::Gnc`], `gnc`) do not depend on the threshold and are reported once.

use std::collections::BTreeSet;
use std::fmt::Write as _;

use doorslam_backend::eval::{absolute_trajectory_error, Alignment, EvalError, Trajectory};
use doorslam_backend::init::Chordal;
use doorslam_backend::outliers::{readmit, Pcm, PcmError, Scope};
use doorslam_backend::robust::chi2_quantile;
use doorslam_backend::{
    key, optimize, BetweenFactor, Kernel, PoseGraph, SolveError, SolverOptions,
};
use nalgebra::Isometry3;

use crate::posegraph_sim::{simulate, SimConfig, SimError, SimulatedTeam};

/// How a run's loop closures are selected before the team's PGO.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Method {
    /// Baseline: every closure kept, plain least squares (`none`).
    NoRejection,
    /// Baseline: every closure, GNC (truncated least squares) on the loop closures (`gnc`).
    Gnc,
    /// PCM's maximum clique, then plain least squares (`pcm`).
    Pcm,
    /// PCM, PGO, re-admission of rejected closures consistent with the estimate, then PGO
    /// with GNC (`pcm+readmit`).
    PcmReadmit,
    /// PCM, then PGO with GNC on the clique's closures (`pcm+gnc`).
    PcmGnc,
}

impl Method {
    /// Every method, baselines first.
    pub const ALL: [Method; 5] = [
        Method::NoRejection,
        Method::Gnc,
        Method::Pcm,
        Method::PcmReadmit,
        Method::PcmGnc,
    ];
    /// The methods without PCM, which do not depend on the threshold: run once per team.
    pub const BASELINES: [Method; 2] = [Method::NoRejection, Method::Gnc];
    /// The methods swept over the PCM threshold, in the order they are reported.
    pub const PCM: [Method; 3] = [Method::Pcm, Method::PcmReadmit, Method::PcmGnc];

    /// The name in reports, JSON keys and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Method::NoRejection => "none",
            Method::Gnc => "gnc",
            Method::Pcm => "pcm",
            Method::PcmReadmit => "pcm+readmit",
            Method::PcmGnc => "pcm+gnc",
        }
    }

    /// Whether the method starts from PCM's clique (and so depends on the threshold).
    pub fn uses_pcm(self) -> bool {
        Method::PCM.contains(&self)
    }

    /// The method column of the Markdown table.
    fn label(self) -> &'static str {
        match self {
            Method::NoRejection => "none (all closures)",
            Method::Gnc => "GNC alone",
            other => other.name(),
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.pad(self.name())
    }
}

/// A name that is none of [`Method::ALL`]'s.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownMethod(pub String);

impl std::fmt::Display for UnknownMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names: Vec<&str> = Method::ALL.iter().map(|m| m.name()).collect();
        write!(
            f,
            "unknown method {:?} (one of {})",
            self.0,
            names.join(", ")
        )
    }
}

impl std::error::Error for UnknownMethod {}

impl std::str::FromStr for Method {
    type Err = UnknownMethod;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Method::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| UnknownMethod(s.to_string()))
    }
}

/// Failures of a sweep.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    /// A [`SweepConfig`] field is out of range; names the field.
    #[error("invalid sweep config: {field} = {value} ({reason})")]
    InvalidConfig {
        field: &'static str,
        value: String,
        reason: &'static str,
    },
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error(transparent)]
    Pcm(#[from] PcmError),
    #[error(transparent)]
    Solve(#[from] SolveError),
    #[error(transparent)]
    Eval(#[from] EvalError),
    #[error(transparent)]
    Edge(#[from] doorslam_backend::EdgeError),
}

/// What to sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepConfig {
    /// The simulated team; run k (from 0) simulates it with seed `team.seed + k`.
    pub team: SimConfig,
    /// Teams simulated (at least 1).
    pub runs: usize,
    /// PCM thresholds p, each strictly between 0 and 1.
    pub thresholds: Vec<f64>,
    /// Methods run at every threshold: PCM-based ones only ([`Method::uses_pcm`]); the
    /// [`Method::BASELINES`] always run, once per team.
    pub methods: Vec<Method>,
}

impl SweepConfig {
    /// The paper's sweep: `runs` teams of `team`, the thresholds of Fig. 5/6, every PCM
    /// method.
    pub fn new(team: SimConfig, runs: usize) -> Self {
        Self {
            team,
            runs,
            thresholds: vec![0.01, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.99],
            methods: Method::PCM.to_vec(),
        }
    }

    /// Checks the sweep's own fields (the team is checked by the simulator).
    pub fn validate(&self) -> Result<(), SweepError> {
        let invalid = |field, value: String, reason| SweepError::InvalidConfig {
            field,
            value,
            reason,
        };
        if self.runs == 0 {
            return Err(invalid("runs", "0".into(), "at least 1"));
        }
        if let Some(p) = self.thresholds.iter().find(|p| !(**p > 0.0 && **p < 1.0)) {
            return Err(invalid(
                "thresholds",
                p.to_string(),
                "not a probability strictly between 0 and 1",
            ));
        }
        if let Some(m) = self.methods.iter().find(|m| !m.uses_pcm()) {
            return Err(invalid(
                "methods",
                m.name().into(),
                "a baseline: it runs once per team, not per threshold",
            ));
        }
        Ok(())
    }
}

/// Values over the runs, summarized by mean and (population) standard deviation.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Stat(Vec<f64>);

impl Stat {
    fn push(&mut self, v: f64) {
        self.0.push(v);
    }

    /// Every run's value, in run order.
    pub fn values(&self) -> &[f64] {
        &self.0
    }

    pub fn mean(&self) -> f64 {
        self.0.iter().sum::<f64>() / self.0.len().max(1) as f64
    }

    pub fn std(&self) -> f64 {
        let m = self.mean();
        (self.0.iter().map(|v| (v - m).powi(2)).sum::<f64>() / self.0.len().max(1) as f64).sqrt()
    }
}

/// One method (at one threshold) over every run.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Cell {
    /// % of the inter-robot outlier closures rejected.
    pub outliers_rejected: Stat,
    /// % of the inter-robot inlier closures rejected.
    pub inliers_rejected: Stat,
    /// ATE RMSE after PGO over the robots connected to robot a, m.
    pub ate: Stat,
    /// Robots in robot a's component (the ones the ATE covers).
    pub robots: Stat,
}

impl Cell {
    fn push(&mut self, team: &SimulatedTeam, outcome: &Outcome) {
        let (o, i) = rates(team, &outcome.kept);
        self.outliers_rejected.push(o);
        self.inliers_rejected.push(i);
        self.ate.push(outcome.ate);
        self.robots.push(outcome.robots as f64);
    }
}

/// Every method at one threshold.
#[derive(Debug, Clone, PartialEq)]
pub struct ThresholdRow {
    pub threshold: f64,
    /// In the order of [`SweepConfig::methods`].
    pub methods: Vec<(Method, Cell)>,
}

/// What a sweep found.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepReport {
    pub config: SweepConfig,
    /// [`Method::BASELINES`], each over every run.
    pub baselines: Vec<(Method, Cell)>,
    /// One row per threshold, in the order of [`SweepConfig::thresholds`].
    pub thresholds: Vec<ThresholdRow>,
}

/// Result of one selection: which closures were kept and the ATE after PGO.
struct Outcome {
    kept: Vec<bool>,
    ate: f64,
    robots: usize,
}

/// χ²₆(0.99): GNC's truncation and the re-admission gate.
fn chi2_99_6() -> f64 {
    chi2_quantile(0.99, 6).expect("0.99 is a probability and 6 > 0 degrees of freedom")
}

/// Odometry plus the kept closures, optimized from the chordal initialization; with GNC
/// on the loop closures if `gnc`. Returns the estimate and the closures GNC kept.
fn solve(
    team: &SimulatedTeam,
    kept: &[bool],
    gnc: bool,
) -> Result<(PoseGraph<Isometry3<f64>>, Vec<bool>), SweepError> {
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
    let c2 = chi2_99_6();
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
) -> Result<(PoseGraph<Isometry3<f64>>, Vec<usize>), SweepError> {
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

fn ate(team: &SimulatedTeam, g: &PoseGraph<Isometry3<f64>>) -> Result<f64, SweepError> {
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
fn pcm_mask(team: &SimulatedTeam, p: f64) -> Result<Vec<bool>, SweepError> {
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

/// Runs `method` on `team`; `pcm` is PCM's mask at the threshold, for the methods that
/// use it.
fn evaluate(team: &SimulatedTeam, method: Method, pcm: &[bool]) -> Result<Outcome, SweepError> {
    let all = || vec![true; team.closures.len()];
    let (g, kept) = match method {
        Method::NoRejection => solve(team, &all(), false)?,
        Method::Gnc => solve(team, &all(), true)?,
        Method::Pcm => solve(team, pcm, false)?,
        Method::PcmGnc => solve(team, pcm, true)?,
        Method::PcmReadmit => {
            let (g, _) = solve(team, pcm, false)?;
            let n_odo = team.odometry_edges().len();
            let rejected: Vec<usize> = (0..pcm.len()).filter(|c| !pcm[*c]).collect();
            let candidates: Vec<(u64, u64, &BetweenFactor<Isometry3<f64>>)> = rejected
                .iter()
                .map(|&c| {
                    let e = &team.graph.edges()[n_odo + c];
                    (team.graph.keys()[e.i], team.graph.keys()[e.j], e)
                })
                .collect();
            let mut readmitted = pcm.to_vec();
            for k in readmit(&g, &candidates, chi2_99_6()) {
                readmitted[rejected[k]] = true;
            }
            solve(team, &readmitted, true)?
        }
    };
    Ok(Outcome {
        ate: ate(team, &g)?,
        robots: robots_in(&g),
        kept,
    })
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

/// Runs the sweep, calling `progress(done, total)` after every run (team).
pub fn run(
    config: &SweepConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SweepReport, SweepError> {
    config.validate()?;
    let mut baselines: Vec<(Method, Cell)> = Method::BASELINES
        .iter()
        .map(|m| (*m, Cell::default()))
        .collect();
    let mut thresholds: Vec<ThresholdRow> = config
        .thresholds
        .iter()
        .map(|&threshold| ThresholdRow {
            threshold,
            methods: config
                .methods
                .iter()
                .map(|m| (*m, Cell::default()))
                .collect(),
        })
        .collect();
    for run in 0..config.runs {
        let team = simulate(&SimConfig {
            seed: config.team.seed + run as u64,
            ..config.team.clone()
        })?;
        for (method, cell) in &mut baselines {
            cell.push(&team, &evaluate(&team, *method, &[])?);
        }
        for row in thresholds.iter_mut().filter(|r| !r.methods.is_empty()) {
            let mask = pcm_mask(&team, row.threshold)?;
            for (method, cell) in &mut row.methods {
                cell.push(&team, &evaluate(&team, *method, &mask)?);
            }
        }
        progress(run + 1, config.runs);
    }
    Ok(SweepReport {
        config: config.clone(),
        baselines,
        thresholds,
    })
}

impl SweepReport {
    /// The summary line and the Markdown table (what `doorslam sim pcm-sweep` prints).
    pub fn table(&self) -> String {
        let c = &self.config;
        let fmt = |s: &Stat| format!("{:.1} ± {:.1}", s.mean(), s.std());
        let fmt_ate = |s: &Stat| format!("{:.3} ± {:.3}", s.mean(), s.std());
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{} runs, {} robots x {} poses, {:.0} % outliers, {} correlated groups; mean ± std over runs\n",
            c.runs,
            c.team.robots,
            c.team.poses_per_robot,
            100.0 * c.team.outlier_fraction,
            c.team.correlated_groups
        );
        let _ = writeln!(s, "| PCM p | method | outliers rejected (%) | inliers rejected (%) | ATE (m) | robots in ATE |");
        let _ = writeln!(s, "| ---: | --- | ---: | ---: | ---: | ---: |");
        let mut line = |p: &str, method: Method, cell: &Cell| {
            let _ = writeln!(
                s,
                "| {p} | {} | {} | {} | {} | {:.1} |",
                method.label(),
                fmt(&cell.outliers_rejected),
                fmt(&cell.inliers_rejected),
                fmt_ate(&cell.ate),
                cell.robots.mean()
            );
        };
        for (method, cell) in &self.baselines {
            line("-", *method, cell);
        }
        for row in &self.thresholds {
            let p = format!("{:.0} %", 100.0 * row.threshold);
            for (method, cell) in &row.methods {
                line(&p, *method, cell);
            }
        }
        s
    }

    /// A two-panel SVG: rejection rates (left) and ATE (right) of the PCM methods
    /// against the threshold.
    pub fn svg(&self) -> String {
        let thresholds: Vec<f64> = self.thresholds.iter().map(|r| r.threshold).collect();
        let cells: Vec<Vec<&Cell>> = self
            .thresholds
            .iter()
            .map(|r| r.methods.iter().map(|(_, c)| c).collect())
            .collect();
        let methods = &self.config.methods;
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
        for (m, name) in methods.iter().enumerate() {
            let line = |f: &dyn Fn(&Cell) -> f64, y: &dyn Fn(f64) -> f64, offset: f64| -> String {
                cells
                    .iter()
                    .enumerate()
                    .map(|(i, row)| format!("{:.1},{:.1}", offset + x(i), y(f(row[m]))))
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn method_names_parse_back() {
        for m in Method::ALL {
            assert_eq!(m.name().parse::<Method>(), Ok(m));
            assert_eq!(m.to_string(), m.name());
        }
        assert!(Method::PCM.iter().all(|m| m.uses_pcm()));
        assert!(!Method::BASELINES.iter().any(|m| m.uses_pcm()));
        let err = "pcm+magic".parse::<Method>().unwrap_err().to_string();
        assert!(
            err.contains("pcm+magic") && err.contains("pcm+readmit"),
            "{err}"
        );
    }

    #[test]
    fn invalid_configs_name_the_field() {
        let mut c = SweepConfig::new(SimConfig::default(), 1);
        assert!(c.validate().is_ok());
        c.thresholds.push(1.5);
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains("thresholds") && err.contains("1.5"), "{err}");
        c.thresholds.pop();
        c.methods.push(Method::Gnc);
        assert!(c.validate().unwrap_err().to_string().contains("methods"));
        c.methods.pop();
        c.runs = 0;
        assert!(c.validate().unwrap_err().to_string().contains("runs"));
    }

    #[test]
    fn stat_is_mean_and_population_std() {
        let mut s = Stat::default();
        for v in [1.0, 3.0] {
            s.push(v);
        }
        assert_eq!((s.mean(), s.std()), (2.0, 1.0));
        assert_eq!(Stat::default().mean(), 0.0);
    }

    /// A small team: PCM at 99 % rejects every uniform outlier and the report has a row
    /// per threshold and method, in order.
    #[test]
    fn a_small_sweep_reports_every_threshold_and_method() {
        let team = SimConfig {
            robots: 3,
            poses_per_robot: 60,
            seed: 1,
            ..SimConfig::default()
        };
        let config = SweepConfig {
            thresholds: vec![0.5, 0.99],
            methods: vec![Method::PcmGnc, Method::Pcm],
            ..SweepConfig::new(team, 2)
        };
        let mut calls = Vec::new();
        let report = run(&config, &mut |done, total| calls.push((done, total))).unwrap();
        assert_eq!(calls, [(1, 2), (2, 2)]);
        let methods: Vec<Method> = report.baselines.iter().map(|(m, _)| *m).collect();
        assert_eq!(methods, Method::BASELINES);
        assert_eq!(report.thresholds.len(), 2);
        for row in &report.thresholds {
            let methods: Vec<Method> = row.methods.iter().map(|(m, _)| *m).collect();
            assert_eq!(methods, config.methods);
            assert!(row.methods.iter().all(|(_, c)| c.ate.values().len() == 2));
        }
        let pcm = &report.thresholds[1].methods[1].1;
        assert_eq!(pcm.outliers_rejected.mean(), 100.0);
        let table = report.table();
        assert!(table.contains("| 99 % | pcm | 100.0 ± 0.0 |"), "{table}");
        assert!(table.contains("| - | none (all closures) |"), "{table}");
        let svg = report.svg();
        assert!(
            svg.starts_with("<svg") && svg.contains(">pcm+gnc</text>"),
            "{svg}"
        );
    }
}
