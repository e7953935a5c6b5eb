//! `doorslam sim ...`: simulated data for tests, benchmarks and HIL.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use doorslam_hil::experiments::pcm_sweep::{self, Cell, Method, SweepConfig, SweepReport};
use doorslam_hil::posegraph_sim::{simulate, write_dataset, SimConfig};
use doorslam_hil::sensor::{CameraModel, SensorModel};

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
    PcmSweep(SweepArgs),
    /// A single-robot pose graph cut into a team, as DOOR-SLAM's KITTI 00 split: robot r
    /// owns the r-th block of consecutive poses, the odometry between blocks is dropped,
    /// loops across blocks become inter-robot closures; planar graphs embedded in 3-D.
    /// Writes OUT (g2o, multi-robot keys) for `doorslam dpgo`.
    Split(SplitArgs),
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

/// `sim split`.
#[derive(Debug, Args)]
pub struct SplitArgs {
    /// A single-robot g2o graph (2-D or 3-D).
    pub file: PathBuf,
    #[arg(long, default_value_t = 5)]
    pub robots: usize,
    /// The team's graph (g2o).
    #[arg(long)]
    pub out: PathBuf,
}

fn run_split(a: SplitArgs) -> Result<()> {
    let file = doorslam_backend::read_g2o(&a.file, doorslam_backend::UnknownTags::Error)
        .with_context(|| format!("{}", a.file.display()))?;
    let team = doorslam_hil::dpgo::split_into_team(&file.graph, a.robots)
        .with_context(|| format!("{}", a.file.display()))?;
    let inter = team
        .edges()
        .iter()
        .filter(|e| team.edge_class(e) == doorslam_backend::EdgeClass::InterLoop)
        .count();
    doorslam_backend::write_g2o(&doorslam_backend::Graph::Se3(team.clone()), &a.out)
        .with_context(|| format!("{}", a.out.display()))?;
    println!(
        "{}: {} robots, {} poses, {} edges ({inter} inter-robot closures)",
        a.out.display(),
        a.robots,
        team.len(),
        team.edges().len()
    );
    Ok(())
}

pub fn run(args: SimArgs) -> Result<()> {
    match args.command {
        SimCommand::Split(a) => run_split(a)?,
        SimCommand::PcmSweep(a) => run_sweep(a)?,
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
pub struct SweepArgs {
    #[arg(long, default_value_t = 100)]
    pub runs: usize,
    #[command(flatten)]
    pub team: TeamArgs,
    /// PCM thresholds (probabilities).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.01,0.05,0.1,0.25,0.5,0.75,0.9,0.99"
    )]
    pub thresholds: Vec<f64>,
    /// Methods run at every threshold, in this order (the baselines always run, once).
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "pcm,pcm+readmit,pcm+gnc"
    )]
    pub methods: Vec<SweepMethod>,
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Write an SVG plot of the rejection rates and ATE here.
    #[arg(long)]
    pub svg: Option<PathBuf>,
    /// Print one JSON object instead of the Markdown table.
    #[arg(long)]
    pub json: bool,
}

/// The swept methods of [`Method`] (the ones that use PCM), as `--methods` spells them.
/// (No doc comments on the variants: clap would switch `--help` to its long layout.)
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SweepMethod {
    #[value(name = "pcm")]
    Pcm,
    #[value(name = "pcm+readmit")]
    PcmReadmit,
    #[value(name = "pcm+gnc")]
    PcmGnc,
}

impl From<SweepMethod> for Method {
    fn from(m: SweepMethod) -> Self {
        match m {
            SweepMethod::Pcm => Method::Pcm,
            SweepMethod::PcmReadmit => Method::PcmReadmit,
            SweepMethod::PcmGnc => Method::PcmGnc,
        }
    }
}

/// `sim pcm-sweep`: runs the sweep, prints the table (or JSON), writes the SVG.
fn run_sweep(args: SweepArgs) -> Result<()> {
    for p in &args.thresholds {
        if !(*p > 0.0 && *p < 1.0) {
            bail!("--thresholds: {p} is not a probability strictly between 0 and 1");
        }
    }
    anyhow::ensure!(args.runs > 0, "--runs must be at least 1");
    let config = SweepConfig {
        team: args.team.config(args.first_seed),
        runs: args.runs,
        thresholds: args.thresholds.clone(),
        methods: args.methods.iter().map(|m| Method::from(*m)).collect(),
    };
    let start = std::time::Instant::now();
    let report = pcm_sweep::run(&config, &mut |done, total| {
        if done % 10 == 0 || done == total {
            eprintln!(
                "pcm-sweep: {done}/{total} runs, {:.1} s",
                start.elapsed().as_secs_f64()
            );
        }
    })?;
    if let Some(path) = &args.svg {
        std::fs::write(path, report.svg())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        println!("{}", sweep_json(&report, &args.team));
    } else {
        print!("{}", report.table());
    }
    Ok(())
}

/// The `--json` object: the team, the baselines by name, one object per threshold with a
/// member per method.
fn sweep_json(report: &SweepReport, team: &TeamArgs) -> serde_json::Value {
    let row = |c: &Cell| {
        serde_json::json!({
            "outliers_rejected_pct": c.outliers_rejected.mean(), "outliers_rejected_std": c.outliers_rejected.std(),
            "inliers_rejected_pct": c.inliers_rejected.mean(), "inliers_rejected_std": c.inliers_rejected.std(),
            "ate_m": c.ate.mean(), "ate_std": c.ate.std(), "robots_connected": c.robots.mean(),
        })
    };
    let per: Vec<serde_json::Value> = report
        .thresholds
        .iter()
        .map(|t| {
            let mut m = serde_json::Map::new();
            m.insert("threshold".into(), t.threshold.into());
            for (method, c) in &t.methods {
                m.insert(method.name().into(), row(c));
            }
            serde_json::Value::Object(m)
        })
        .collect();
    let mut v = serde_json::Map::new();
    v.insert("runs".into(), report.config.runs.into());
    v.insert("robots".into(), team.robots.into());
    v.insert("poses".into(), team.poses.into());
    v.insert("outliers".into(), team.outliers.into());
    v.insert("correlated_groups".into(), team.correlated_groups.into());
    for (method, c) in &report.baselines {
        v.insert(method.name().into(), row(c));
    }
    v.insert("thresholds".into(), per.into());
    serde_json::Value::Object(v)
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
    /// How routes are planned: `designed` (anchor, follower and alias partner in groups of
    /// three) or `sectors` (every drone patrols its own sector, neighbours share a street:
    /// the demo's scenario).
    #[arg(long, value_enum, default_value_t = PlanArg::Designed)]
    pub plan: PlanArg,
    #[arg(long)]
    pub out: PathBuf,
    /// Print one JSON object on stdout instead of a summary line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub camera: CameraArgs,
}

/// The camera the world is imaged with (`doorslam_hil::sensor`). Defaults: an
/// MT9V034-like global-shutter sensor in daylight with cloud and building shade.
#[derive(Debug, Clone, Args)]
pub struct CameraArgs {
    /// `realistic`: sensor noise, auto-exposure following changing light, motion blur,
    /// vignetting; `ideal`: the renderer's noise-free, perfectly exposed pixels.
    #[arg(long, value_enum, default_value_t = CameraKind::Realistic)]
    pub camera: CameraKind,
    /// Read noise σ in 8-bit DN at unity gain (scaled by the gain); 0: none.
    #[arg(long, default_value_t = SensorModel::default().read_noise_dn)]
    pub noise_dn: f64,
    /// Electrons filling the 8-bit range at unity gain (sets the shot noise); 0: none.
    #[arg(long, default_value_t = SensorModel::default().full_well_e)]
    pub full_well_e: f64,
    /// Exposure time under the reference light (ms).
    #[arg(long, default_value_t = SensorModel::default().exposure_ms)]
    pub exposure_ms: f64,
    /// Longest exposure before the auto-exposure raises the gain (ms, ≤ the frame period).
    #[arg(long, default_value_t = SensorModel::default().max_exposure_ms)]
    pub max_exposure_ms: f64,
    /// Highest analog gain.
    #[arg(long, default_value_t = SensorModel::default().max_gain)]
    pub max_gain: f64,
    /// σ of the smooth random walk of the light (natural log, 0.2 ≈ ±20 %); 0: none.
    #[arg(long, default_value_t = SensorModel::default().exposure_walk)]
    pub exposure_walk: f64,
    /// Times per minute the drone flies into shade (a sudden step); 0: never.
    #[arg(long, default_value_t = SensorModel::default().shade_per_min)]
    pub shade_per_min: f64,
    /// How much darker the shade is (stops).
    #[arg(long, default_value_t = SensorModel::default().shade_stops)]
    pub shade_stops: f64,
    /// Time constant of the auto-exposure loop (s).
    #[arg(long, default_value_t = SensorModel::default().ae_time_constant_s)]
    pub ae_time_constant_s: f64,
    /// Motion blur from the camera's motion during the exposure.
    #[arg(long, value_enum, default_value_t = OnOff::On)]
    pub blur: OnOff,
    /// Fraction of light lost in the farthest image corner; 0: none.
    #[arg(long, default_value_t = SensorModel::default().vignetting)]
    pub vignetting: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PlanArg {
    Designed,
    Sectors,
}

impl From<PlanArg> for doorslam_hil::flights::FlightPlan {
    fn from(p: PlanArg) -> Self {
        match p {
            PlanArg::Designed => Self::Designed,
            PlanArg::Sectors => Self::Sectors,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum CameraKind {
    Realistic,
    Ideal,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

impl CameraArgs {
    /// The model these flags describe (checked against the frame rate when used).
    pub fn model(&self) -> CameraModel {
        match self.camera {
            CameraKind::Ideal => CameraModel::Ideal,
            CameraKind::Realistic => CameraModel::Realistic(SensorModel {
                full_well_e: self.full_well_e,
                read_noise_dn: self.noise_dn,
                exposure_ms: self.exposure_ms,
                max_exposure_ms: self.max_exposure_ms,
                max_gain: self.max_gain,
                exposure_walk: self.exposure_walk,
                shade_per_min: self.shade_per_min,
                shade_stops: self.shade_stops,
                ae_time_constant_s: self.ae_time_constant_s,
                blur: self.blur == OnOff::On,
                vignetting: self.vignetting,
                ..SensorModel::default()
            }),
        }
    }
}

/// `sim world`: plans the team, then renders and writes every robot's sequence.
fn run_world(a: WorldArgs) -> Result<()> {
    use doorslam_hil::flights::{
        camera_for_resolution, simulate_team, write_team, ClosureKind, FlightConfig,
    };

    let camera = camera_for_resolution(&a.resolution).context("--resolution")?;
    let model = a.camera.model();
    if let CameraModel::Realistic(sensor) = &model {
        sensor
            .validate(a.rate_hz)
            .context("camera options (--noise-dn, --exposure-ms, ...)")?;
    }
    let config = FlightConfig {
        robots: a.robots,
        frames: a.frames,
        rate_hz: a.rate_hz,
        radio_range_m: a.radio_range_m,
        speed_mps: a.speed_mps,
        seed: a.seed,
        plan: a.plan.into(),
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
    write_team(&a.out, &world, &team, &model, &progress)
        .with_context(|| format!("writing the world into {}", a.out.display()))?;
    let seconds = start.elapsed().as_secs_f64();
    if a.json {
        let json = serde_json::json!({
            "out": a.out.display().to_string(),
            "robots": a.robots,
            "frames": a.frames,
            "resolution": format!("{}x{}", camera.width(), camera.height()),
            "camera": model.name(),
            "overlap_candidates": overlaps,
            "aliased_candidates": aliased,
            "own_candidates": team.own.len(),
            "plan": config.plan.as_str(),
            "rendezvous_events": team.events.len(),
            "seconds": seconds,
        });
        println!("{json}");
    } else {
        println!(
            "{}: {} robots x {} frames at {}x{} ({} camera) in {seconds:.1} s; {overlaps} overlap and {aliased} aliased closure candidates, {} rendezvous events",
            a.out.display(),
            a.robots,
            a.frames,
            camera.width(),
            camera.height(),
            model.name(),
            team.events.len()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sweep_methods_are_spelled_as_in_the_reports() {
        let swept: Vec<Method> = SweepMethod::value_variants()
            .iter()
            .map(|m| Method::from(*m))
            .collect();
        assert_eq!(swept, Method::PCM);
        for m in SweepMethod::value_variants() {
            let name = m.to_possible_value().unwrap().get_name().to_string();
            assert_eq!(name, Method::from(*m).name());
        }
    }
}
