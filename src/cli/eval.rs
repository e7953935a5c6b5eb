//! `doorslam eval ate|rpe EST GT`: trajectory error against ground truth (evo's numbers).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use doorslam_backend::eval::{
    absolute_trajectory_error, associate_by_index, associate_by_timestamp, read_trajectory,
    relative_pose_error, Alignment, ErrorStats, RpeDelta, Trajectory, TrajectoryFormat,
    DEFAULT_MAX_TIME_DIFF,
};
use doorslam_backend::{read_g2o, Graph, LieGroup, UnknownTags};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FormatArg {
    /// Poses of a g2o graph, in key order (timestamps = index).
    G2o,
    Kitti,
    Tum,
    Euroc,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum AlignArg {
    Se3,
    Sim3,
    None,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum DeltaUnit {
    /// Pairs of poses `delta` frames apart.
    Frames,
    /// Pairs every `delta` meters travelled along the estimate (evo's default for KITTI).
    M,
}

#[derive(Debug, Args)]
pub struct Common {
    /// Estimated trajectory.
    pub estimate: PathBuf,
    /// Ground-truth trajectory.
    pub reference: PathBuf,
    /// Format of both files (default: guessed from each file's extension and first line).
    #[arg(long, value_enum)]
    pub format: Option<FormatArg>,
    /// Format of the ground truth, when it differs from the estimate's.
    #[arg(long, value_enum)]
    pub gt_format: Option<FormatArg>,
    /// Maximum timestamp difference (s) when associating TUM/EuRoC poses.
    #[arg(long, default_value_t = DEFAULT_MAX_TIME_DIFF)]
    pub max_time_diff: f64,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Absolute trajectory error (translation) after alignment.
    Ate {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_enum, default_value_t = AlignArg::Se3)]
        align: AlignArg,
    },
    /// End-point drift: distance between the estimated and true end positions, both
    /// trajectories taken relative to their first pose, in % of the true path length.
    Drift {
        #[command(flatten)]
        common: Common,
    },
    /// Relative pose error (translation), not aligned.
    Rpe {
        #[command(flatten)]
        common: Common,
        #[arg(long, default_value_t = 1.0)]
        delta: f64,
        #[arg(long, value_enum, default_value_t = DeltaUnit::Frames)]
        delta_unit: DeltaUnit,
    },
}

#[derive(Debug, Args)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub command: EvalCommand,
}

fn g2o_trajectory(path: &Path) -> Result<Trajectory> {
    let file = read_g2o(path, UnknownTags::Skip)?;
    let mut keyed: Vec<(u64, Isometry3<f64>)> = match &file.graph {
        Graph::Se3(g) => g
            .keys()
            .iter()
            .copied()
            .zip(g.poses().iter().copied())
            .collect(),
        Graph::Se2(g) => g
            .keys()
            .iter()
            .zip(g.poses())
            .map(|(k, p)| {
                let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), p.rotation.angle());
                (
                    *k,
                    Isometry3::from_parts(Translation3::from(p.translation3()), yaw),
                )
            })
            .collect(),
    };
    keyed.sort_by_key(|(k, _)| *k);
    Ok(Trajectory::from_poses(
        keyed.into_iter().map(|(_, p)| p).collect(),
    ))
}

/// Reads a trajectory; returns it and whether it carries real timestamps.
fn load(path: &Path, format: Option<FormatArg>) -> Result<(Trajectory, bool)> {
    let format = match format {
        Some(f) => f,
        None if path.extension().is_some_and(|e| e == "g2o") => FormatArg::G2o,
        None => match TrajectoryFormat::from_path(path)? {
            TrajectoryFormat::Kitti => FormatArg::Kitti,
            TrajectoryFormat::Tum => FormatArg::Tum,
            TrajectoryFormat::Euroc => FormatArg::Euroc,
        },
    };
    Ok(match format {
        FormatArg::G2o => (g2o_trajectory(path)?, false),
        FormatArg::Kitti => (read_trajectory(path, TrajectoryFormat::Kitti)?, false),
        FormatArg::Tum => (read_trajectory(path, TrajectoryFormat::Tum)?, true),
        FormatArg::Euroc => (read_trajectory(path, TrajectoryFormat::Euroc)?, true),
    })
}

fn associated(c: &Common) -> Result<(Trajectory, Trajectory)> {
    let (est, est_timed) = load(&c.estimate, c.format)
        .with_context(|| format!("estimate {}", c.estimate.display()))?;
    let (gt, gt_timed) = load(&c.reference, c.gt_format.or(c.format))
        .with_context(|| format!("ground truth {}", c.reference.display()))?;
    Ok(if est_timed && gt_timed {
        associate_by_timestamp(&gt, &est, c.max_time_diff)?
    } else {
        associate_by_index(&gt, &est)?
    })
}

fn report(prefix: &str, stats: &ErrorStats, json: bool) {
    if json {
        let mut m = serde_json::Map::new();
        m.insert(format!("{prefix}_rmse"), stats.rmse.into());
        m.insert(format!("{prefix}_mean"), stats.mean.into());
        m.insert(format!("{prefix}_median"), stats.median.into());
        m.insert(format!("{prefix}_std"), stats.std.into());
        m.insert(format!("{prefix}_min"), stats.min.into());
        m.insert(format!("{prefix}_max"), stats.max.into());
        m.insert("pairs".into(), stats.pairs.into());
        println!("{}", serde_json::Value::Object(m));
    } else {
        println!(
            "{}: rmse {:.6} m, mean {:.6} m, median {:.6} m, max {:.6} m over {} pairs",
            prefix.to_uppercase(),
            stats.rmse,
            stats.mean,
            stats.median,
            stats.max,
            stats.pairs
        );
    }
}

pub fn run(args: EvalArgs) -> Result<()> {
    match args.command {
        EvalCommand::Ate { common, align } => {
            let (gt, est) = associated(&common)?;
            let alignment = match align {
                AlignArg::Se3 => Alignment::Se3,
                AlignArg::Sim3 => Alignment::Sim3,
                AlignArg::None => Alignment::None,
            };
            let ate = absolute_trajectory_error(&gt, &est, alignment)?;
            report("ate", &ate.stats, common.json);
        }
        EvalCommand::Drift { common } => {
            let (gt, est) = associated(&common)?;
            let d = doorslam_frontend::run::endpoint_drift(est.poses(), gt.poses())
                .context("end-point drift needs two poses and a path longer than 1 cm")?;
            if common.json {
                println!(
                    "{}",
                    serde_json::json!({
                        "distance_m": d.distance_m,
                        "endpoint_error_m": d.endpoint_error_m,
                        "drift_percent": d.percent,
                    })
                );
            } else {
                println!(
                    "end-point drift {:.3} m over {:.1} m ({:.2} %)",
                    d.endpoint_error_m, d.distance_m, d.percent
                );
            }
        }
        EvalCommand::Rpe {
            common,
            delta,
            delta_unit,
        } => {
            let (gt, est) = associated(&common)?;
            let delta = match delta_unit {
                DeltaUnit::Frames => {
                    anyhow::ensure!(
                        delta >= 1.0 && delta.fract() == 0.0,
                        "--delta {delta}: frames must be a whole number >= 1"
                    );
                    RpeDelta::Frames(delta as usize)
                }
                DeltaUnit::M => RpeDelta::Meters(delta),
            };
            let rpe = relative_pose_error(&gt, &est, delta)?;
            report("rpe", &rpe.stats, common.json);
        }
    }
    Ok(())
}
