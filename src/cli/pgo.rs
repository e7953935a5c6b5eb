//! `doorslam pgo FILE`: optimize a pose graph read from a g2o file.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use doorslam_backend::init::{self, Chordal};
use doorslam_backend::robust::chi2_quantile;
use doorslam_backend::{
    key, read_g2o_with, write_g2o, Graph, InformationPolicy, Kernel, LieGroup, Method, PoseGraph,
    ReadOptions, SolverOptions, UnknownTags,
};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SolverArg {
    /// Gauss-Newton.
    Gn,
    /// Levenberg-Marquardt.
    Lm,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum InitArg {
    /// The poses in the file (chained from edges where a pose has no VERTEX line).
    File,
    /// Compose edges from the first pose, odometry first.
    Odometry,
    /// Chordal relaxation: rotations first, then translations.
    Chordal,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RobustArg {
    None,
    Huber,
    Cauchy,
    /// Truncated least squares solved by graduated non-convexity.
    Gnc,
}

/// What to do with information matrices that are not positive definite (some public
/// benchmark files have them, e.g. 5,021 of SE-Sync cubicle's 16,869 edges).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum InformationArg {
    /// Refuse the file, saying how many edges are affected and where.
    Check,
    /// Use the matrices as written. Levenberg-Marquardt's damping keeps its steps defined
    /// (Gauss-Newton may fail), but the cost is no sum of squares and may go below zero
    /// (stop_reason negative_cost). GTSAM reads such files without complaint, yet it
    /// whitens with an unchecked, partial Cholesky factor: not the matrix as written either.
    AsIs,
    /// Replace each by the nearest positive-definite matrix (eigenvalues clamped to a small
    /// positive floor relative to the largest).
    NearestPd,
}

impl From<InformationArg> for InformationPolicy {
    fn from(a: InformationArg) -> Self {
        match a {
            InformationArg::Check => InformationPolicy::Check,
            InformationArg::AsIs => InformationPolicy::AsIs,
            InformationArg::NearestPd => InformationPolicy::NearestPd,
        }
    }
}

#[derive(Debug, Args)]
pub struct PgoArgs {
    /// Pose graph in g2o format (VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT).
    pub file: PathBuf,
    #[arg(long, value_enum, default_value_t = SolverArg::Lm)]
    pub solver: SolverArg,
    /// Initial guess; chordal by default because it does not depend on the file's poses
    /// (LM from poor initial poses can stop in a local minimum, e.g. on torus3D).
    #[arg(long, value_enum, default_value_t = InitArg::Chordal)]
    pub init: InitArg,
    /// Robust kernel on loop closures (odometry stays quadratic).
    #[arg(long, value_enum, default_value_t = RobustArg::None)]
    pub robust: RobustArg,
    /// Kernel threshold as a probability: residuals below the χ² quantile of this
    /// probability (with the edge's degrees of freedom) count as inliers.
    #[arg(long, default_value_t = 0.99)]
    pub robust_p: f64,
    #[arg(long, default_value_t = 100)]
    pub max_iterations: usize,
    /// Skip lines with unknown tags (with a warning) instead of failing.
    #[arg(long)]
    pub skip_unknown: bool,
    /// Information matrices that are not positive definite: refuse the file (check), use
    /// them as written (as-is) or repair them (nearest-pd).
    #[arg(long, value_enum, default_value_t = InformationArg::Check)]
    pub information: InformationArg,
    /// Write the optimized graph here (g2o).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

struct Outcome {
    poses: usize,
    edges: usize,
    initial_chi2: f64,
    init_chi2: f64,
    summary: doorslam_backend::Summary,
    time_s: f64,
}

fn run_graph<G: Chordal>(
    g: &mut PoseGraph<G>,
    anchor: usize,
    args: &PgoArgs,
    opts: &SolverOptions,
) -> Result<Outcome> {
    let initial_chi2 = g.chi2();
    let t = Instant::now();
    match args.init {
        InitArg::File => {}
        InitArg::Odometry => init::odometry(g, anchor)?,
        InitArg::Chordal => G::chordal(g, anchor)?,
    }
    let init_chi2 = g.chi2();
    let summary = doorslam_backend::optimize(g, anchor, opts)?;
    Ok(Outcome {
        poses: g.len(),
        edges: g.edges().len(),
        initial_chi2,
        init_chi2,
        summary,
        time_s: t.elapsed().as_secs_f64(),
    })
}

fn kernel(robust: RobustArg, p: f64, dof: usize) -> Result<Kernel> {
    let Some(c2) = chi2_quantile(p, dof) else {
        bail!("--robust-p {p} must be a probability strictly between 0 and 1");
    };
    Ok(match robust {
        RobustArg::None => Kernel::None,
        RobustArg::Huber => Kernel::Huber { k: c2.sqrt() },
        RobustArg::Cauchy => Kernel::Cauchy { c: c2.sqrt() },
        RobustArg::Gnc => Kernel::Gnc { c2 },
    })
}

pub fn run(args: PgoArgs) -> Result<()> {
    let unknown = if args.skip_unknown {
        UnknownTags::Skip
    } else {
        UnknownTags::Error
    };
    let mut file = read_g2o_with(
        &args.file,
        ReadOptions {
            unknown,
            information: args.information.into(),
        },
    )?;
    for w in &file.warnings {
        tracing::warn!("{w}");
    }
    if !file.not_positive_definite.is_empty() {
        tracing::warn!(
            "{}: {} edges have an information matrix that is not positive definite ({})",
            args.file.display(),
            file.not_positive_definite.len(),
            match args.information {
                InformationArg::NearestPd => "replaced by the nearest positive-definite one",
                _ => "used as written",
            }
        );
    }
    if file.fixed.len() > 1 {
        // The solver fixes one pose (the gauge); more would need priors it does not have.
        tracing::warn!(
            "{}: FIX lists {} poses; only the first, {}, is held fixed",
            args.file.display(),
            file.fixed.len(),
            key::label(file.fixed[0])
        );
    }
    let dof = match &file.graph {
        Graph::Se2(_) => <nalgebra::Isometry2<f64> as LieGroup>::DIM,
        Graph::Se3(_) => <nalgebra::Isometry3<f64> as LieGroup>::DIM,
    };
    let opts = SolverOptions {
        method: match args.solver {
            SolverArg::Gn => Method::GaussNewton,
            SolverArg::Lm => Method::LevenbergMarquardt,
        },
        max_iterations: args.max_iterations,
        loop_kernel: kernel(args.robust, args.robust_p, dof)?,
        ..SolverOptions::default()
    };
    let anchor_of = |keys: &[u64]| {
        file.fixed
            .first()
            .and_then(|k| keys.iter().position(|x| x == k))
            .unwrap_or(0)
    };
    let outcome = match &mut file.graph {
        Graph::Se2(g) => {
            let a = anchor_of(g.keys());
            run_graph(g, a, &args, &opts)
        }
        Graph::Se3(g) => {
            let a = anchor_of(g.keys());
            run_graph(g, a, &args, &opts)
        }
    }
    .with_context(|| format!("optimizing {}", args.file.display()))?;
    if let Some(out) = &args.out {
        write_g2o(&file.graph, out)?;
    }
    let s = &outcome.summary;
    if args.json {
        let json = serde_json::json!({
            "file": args.file.display().to_string(),
            "poses": outcome.poses,
            "edges": outcome.edges,
            "initial_chi2": outcome.initial_chi2,
            "init_chi2": outcome.init_chi2,
            "final_chi2": s.final_chi2,
            "iterations": s.iterations,
            "converged": s.converged,
            "stop_reason": s.stop_reason.as_str(),
            "not_positive_definite_edges": file.not_positive_definite.len(),
            "repaired_edges": file.repaired_edges,
            "time_s": outcome.time_s,
        });
        println!("{json}");
    } else {
        println!(
            "{}: {} poses, {} edges; chi2 {:.6e} (file) -> {:.6e} (init) -> {:.6e} in {} iterations{}, {:.3} s",
            args.file.display(),
            outcome.poses,
            outcome.edges,
            outcome.initial_chi2,
            outcome.init_chi2,
            s.final_chi2,
            s.iterations,
            if s.converged {
                String::new()
            } else {
                format!(" ({})", s.stop_reason)
            },
            outcome.time_s
        );
    }
    Ok(())
}
