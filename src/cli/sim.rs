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
    /// Synthetic stereo world: N drones flying through a textured town; writes one
    /// KITTI-layout sequence per robot with ground truth, calibration and a rendezvous
    /// event log.
    World(WorldArgs),
}

/// The simulated team of `sim graph` and `sim pcm-sweep`.
#[derive(Debug, Clone, Args)]
pub struct TeamArgs {
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
}

impl TeamArgs {
    /// The simulator's configuration for this team and `seed`.
    pub fn config(&self, seed: u64) -> SimConfig {
        SimConfig {
            robots: self.robots,
            poses_per_robot: self.poses,
            outlier_fraction: self.outliers,
            correlated_groups: self.correlated_groups,
            seed,
            ..SimConfig::default()
        }
    }
}

#[derive(Debug, Args)]
pub struct GraphArgs {
    #[command(flatten)]
    pub team: TeamArgs,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: SimArgs) -> Result<()> {
    match args.command {
        SimCommand::PcmSweep(a) => crate::bench::pcm_sweep::run(a)?,
        SimCommand::World(a) => run_world(a)?,
        SimCommand::Graph(a) => {
            let config = a.team.config(a.seed);
            let team = simulate(&config)?;
            write_dataset(&team, &a.out)?;
            let c = team.counts();
            println!(
                "{}: {} robots x {} poses, {} inter-robot inliers, {} uniform + {} correlated outliers (fraction {:.3})",
                a.out.display(),
                a.team.robots,
                a.team.poses,
                c.inter_inliers,
                c.uniform_outliers,
                c.correlated_outliers,
                team.outlier_fraction()
            );
        }
    }
    Ok(())
}

#[derive(Debug, Args)]
pub struct WorldArgs {
    #[arg(long, default_value_t = 5)]
    pub robots: usize,
    /// Frames per robot.
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    #[arg(long, default_value_t = 10.0)]
    pub rate_hz: f64,
    /// WIDTHxHEIGHT (EuRoC-like intrinsics scaled to the width, same horizontal field
    /// of view), or the presets `euroc` (752x480) and `kitti` (1241x376, 54 cm baseline).
    #[arg(long, default_value = "752x480")]
    pub resolution: String,
    #[arg(long, default_value_t = 30.0)]
    pub radio_range_m: f64,
    /// Mean horizontal speed of the drones.
    #[arg(long, default_value_t = 3.5)]
    pub speed_mps: f64,
    /// Seeds both the town and the flights.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long)]
    pub out: PathBuf,
    /// Print one JSON object on stdout instead of a summary line.
    #[arg(long)]
    pub json: bool,
}

/// `sim world`: plans the team, then renders and writes every robot's sequence.
fn run_world(a: WorldArgs) -> Result<()> {
    use anyhow::Context;
    use doorslam_hil::flights::{
        camera_for_resolution, simulate_team, write_team, ClosureKind, FlightConfig,
    };

    let camera = camera_for_resolution(&a.resolution).context("--resolution")?;
    let config = FlightConfig {
        robots: a.robots,
        frames: a.frames,
        rate_hz: a.rate_hz,
        radio_range_m: a.radio_range_m,
        speed_mps: a.speed_mps,
        seed: a.seed,
        ..FlightConfig::default()
    };
    let world = doorslam_hil::World::town(a.seed);
    let team = simulate_team(&world, &camera, &config).context("planning the flights")?;
    let (overlaps, aliased) = (
        team.count(ClosureKind::Overlap),
        team.count(ClosureKind::Aliased),
    );
    let start = std::time::Instant::now();
    let total = a.robots * a.frames;
    let step = total.div_ceil(10).max(1);
    let progress = |done: usize, total: usize| {
        if done.is_multiple_of(step) || done == total {
            eprintln!(
                "sim world: {done}/{total} stereo frames ({}%), {:.0} s",
                100 * done / total.max(1),
                start.elapsed().as_secs_f64()
            );
        }
    };
    write_team(&a.out, &world, &team, &progress)
        .with_context(|| format!("writing the world into {}", a.out.display()))?;
    let seconds = start.elapsed().as_secs_f64();
    if a.json {
        let json = serde_json::json!({
            "out": a.out.display().to_string(),
            "robots": a.robots,
            "frames": a.frames,
            "resolution": format!("{}x{}", camera.width(), camera.height()),
            "overlap_candidates": overlaps,
            "aliased_candidates": aliased,
            "rendezvous_events": team.events.len(),
            "seconds": seconds,
        });
        println!("{json}");
    } else {
        println!(
            "{}: {} robots x {} frames at {}x{} in {seconds:.1} s; {overlaps} overlap and {aliased} aliased closure candidates, {} rendezvous events",
            a.out.display(),
            a.robots,
            a.frames,
            camera.width(),
            camera.height(),
            team.events.len()
        );
    }
    Ok(())
}
