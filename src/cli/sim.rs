//! `doorslam sim ...`: simulated data for tests, benchmarks and HIL.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Subcommand};
use doorslam_hil::posegraph_sim::{simulate, write_dataset, SimConfig};

#[derive(Debug, Args)]
pub struct SimArgs {
    #[command(subcommand)]
    pub command: SimCommand,
}

#[derive(Debug, Subcommand)]
pub enum SimCommand {
    /// Multi-robot pose graph (the paper's ARGoS experiment at pose-graph level): random
    /// walks, odometry and closures with σ_R / σ_t noise, uniform and correlated outlier
    /// closures; writes graph.g2o, gt_<robot>.txt/.tum and labels.txt.
    Graph(GraphArgs),
    /// PCM threshold sweep on simulated teams (paper Fig. 5/6): outliers and inliers
    /// rejected and ATE after PGO, for PCM alone, PCM + re-admission, and PCM + GNC.
    PcmSweep(crate::bench::pcm_sweep::SweepArgs),
}

#[derive(Debug, Args)]
pub struct GraphArgs {
    #[arg(long, default_value_t = 5)]
    pub robots: usize,
    #[arg(long, default_value_t = 100)]
    pub poses: usize,
    /// Fraction of inter-robot closures that are outliers.
    #[arg(long, default_value_t = 0.3)]
    pub outliers: f64,
    /// Groups of mutually consistent wrong closures (perceptual aliasing).
    #[arg(long, default_value_t = 0)]
    pub correlated_groups: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: SimArgs) -> Result<()> {
    match args.command {
        SimCommand::PcmSweep(a) => crate::bench::pcm_sweep::run(a)?,
        SimCommand::Graph(a) => {
            let config = SimConfig {
                robots: a.robots,
                poses_per_robot: a.poses,
                outlier_fraction: a.outliers,
                correlated_groups: a.correlated_groups,
                seed: a.seed,
                ..SimConfig::default()
            };
            let team = simulate(&config)?;
            write_dataset(&team, &a.out)?;
            let c = team.counts();
            println!(
                "{}: {} robots x {} poses, {} inter-robot inliers, {} uniform + {} correlated outliers (fraction {:.3})",
                a.out.display(),
                a.robots,
                a.poses,
                c.inter_inliers,
                c.uniform_outliers,
                c.correlated_outliers,
                team.outlier_fraction()
            );
        }
    }
    Ok(())
}
