//! `doorslam demo`: a team of robots flies through the synthetic town (or a dataset split
//! into robots), every robot a host of its own running its full set of services, and a
//! report folder people can look at (`doorslam_hil::demo`). One live line per robot.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use doorslam_hil::demo::{self, DemoConfig, Kill, Phase, Snapshot};
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CameraArg {
    Realistic,
    Ideal,
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Robots in the team.
    #[arg(long, default_value_t = 3)]
    pub robots: usize,
    /// Frames per robot (10 per second of flight); or give `--duration-s`, not both.
    /// Default: 90 s of flight (900 frames).
    #[arg(long, conflicts_with = "duration_s")]
    pub frames: Option<usize>,
    /// Seconds of flight per robot (10 frames per second); or give `--frames`, not both.
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// Speed of the slowest drone (m/s); each of the others flies up to 10 % faster.
    #[arg(long, default_value_t = demo::config::DEFAULT_SPEED_MPS)]
    pub speed_mps: f64,
    /// Random loss between robots: each packet from another robot is dropped with this
    /// probability (nftables; needs root), e.g. `0.3`.
    #[arg(long)]
    pub drop: Option<f64>,
    /// A KITTI-layout folder (with poses.txt) split into the robots, instead of the town.
    #[arg(long, conflicts_with = "world")]
    pub dataset: Option<PathBuf>,
    /// Fly a world rendered before (an earlier demo's `<out>/world`, or `doorslam sim
    /// world --plan sectors`) instead of rendering one; its robots must be `--robots`,
    /// its frames, speed and seed are its own.
    #[arg(long, conflicts_with_all = ["frames", "duration_s", "seed", "camera"])]
    pub world: Option<PathBuf>,
    /// The report folder (default: a new `doorslam-demo-<unix time>` here).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Kill every process of one robot at a flight time, e.g. `b@12`; it restarts after
    /// `--restart-after-s` from its journal and rejoins. Repeat for several robots (a chaos
    /// run: `--kill a@30 --kill b@50 --drop 0.3`), at most once per robot.
    #[arg(long)]
    pub kill: Vec<Kill>,
    #[arg(long, default_value_t = 3.0)]
    pub restart_after_s: f64,
    /// Replay speed (1 = real time).
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// Seed of the town and the flights.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The simulated camera: `realistic` (sensor noise, exposure changes, motion blur) or
    /// `ideal` (noise-free, perfectly exposed renders).
    #[arg(long, value_enum, default_value_t = CameraArg::Realistic)]
    pub camera: CameraArg,
    /// Most seconds to wait at base, after the flight, for the team estimate to settle.
    #[arg(long, default_value_t = 30.0)]
    pub settle_s: f64,
    /// Plain TCP between the robots, open to any host on the network. Without it (the
    /// default) the demo issues a team CA and robot certificates into `<out>/certs` and
    /// every robot uses mutual TLS and the access control.
    #[arg(long)]
    pub insecure: bool,
    /// Every robot also publishes its state as ROS 2 topics (`[ros2] enabled`, plain TCP
    /// on its address, port 7547; loopback: 17547 + robot), for RViz / Foxglove with
    /// `rmw_zenoh_cpp` (README, ROS 2).
    #[arg(long)]
    pub ros2: bool,
    /// Print `summary.json` on stdout at the end.
    #[arg(long)]
    pub json: bool,
}

fn robot_line(r: &demo::RobotSnapshot) -> String {
    let frames = match (r.frames, r.lost) {
        (Some(f), Some(l)) if l > 0 => format!("frames {f:4} (lost {l})  "),
        (Some(f), _) => format!("frames {f:4}  "),
        _ => String::new(),
    };
    format!(
        "{:?}  {frames}keyframes {:3}  rendezvous {:2}  closures {:3} ({} rejected)  rounds {:3}  sent {:7.1} kB{}{}{}",
        r.state,
        r.keyframes,
        r.rendezvous,
        r.closures,
        r.rejected,
        r.rounds,
        r.bytes_sent as f64 / 1e3,
        r.round.map_or(String::new(), |n| format!("  on solve {n}")),
        if r.unacknowledged > 0 {
            format!("  {} unacknowledged", r.unacknowledged)
        } else {
            String::new()
        },
        if r.converged { "  converged" } else { "" }
    )
}

fn header(s: &Snapshot) -> String {
    match s.phase {
        Phase::Rendering => format!(
            "rendering the flights: {}/{} stereo frames",
            s.rendered.0, s.rendered.1
        ),
        Phase::Starting => "starting the robots".into(),
        Phase::Flying => format!("flying: {:5.1} / {:.1} s", s.flight_s, s.flight_total_s),
        Phase::AtBase => {
            "back at base: every robot in range, waiting for the team estimate to settle".into()
        }
        Phase::Stopping => "stopping the robots".into(),
        Phase::Reporting => "writing the report".into(),
    }
}

/// Frames per robot from `--frames` or `--duration-s` (clap refuses both).
fn frames(args: &DemoArgs) -> Result<usize> {
    match (args.frames, args.duration_s) {
        (Some(f), _) => Ok(f),
        (None, Some(d)) => {
            anyhow::ensure!(
                d.is_finite() && (1.0..=3600.0).contains(&d),
                "--duration-s {d}: from 1 to 3600 seconds"
            );
            Ok((d * demo::config::RATE_HZ).round() as usize)
        }
        (None, None) => Ok(demo::config::DEFAULT_FRAMES),
    }
}

pub fn run(args: DemoArgs) -> Result<()> {
    let exe = std::env::current_exe().context("locating the doorslam binary")?;
    let out = args.out.clone().unwrap_or_else(|| {
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        PathBuf::from(format!("doorslam-demo-{t}"))
    });
    let mut config = DemoConfig::new(exe, out.clone());
    config.robots = args.robots;
    config.frames = frames(&args)?;
    config.speed_mps = args.speed_mps;
    config.drop = args.drop;
    config.world = args.world.clone();
    config.dataset = args.dataset.clone();
    config.kills = args.kill;
    config.restart_after_s = args.restart_after_s;
    config.rate = args.rate;
    config.seed = args.seed;
    config.settle_s = args.settle_s;
    config.realistic_camera = args.camera == CameraArg::Realistic;
    config.insecure = args.insecure;
    config.ros2 = args.ros2;

    let tty = std::io::stderr().is_terminal();
    let multi = MultiProgress::new();
    let style =
        ProgressStyle::with_template("{prefix:>3} {msg}").unwrap_or(ProgressStyle::default_bar());
    let top = multi.add(
        ProgressBar::new_spinner()
            .with_style(style.clone())
            .with_prefix(""),
    );
    let mut lines: Vec<ProgressBar> = Vec::new();
    let mut last_print = Instant::now() - Duration::from_secs(60);
    let mut progress = |s: &Snapshot| {
        if let Some(note) = &s.note {
            if tty {
                let _ = multi.println(note);
            } else {
                eprintln!("demo: {note}");
            }
        }
        if tty {
            top.set_message(header(s));
            while lines.len() < s.robots.len() {
                let r = &s.robots[lines.len()];
                lines.push(
                    multi.add(
                        ProgressBar::new_spinner()
                            .with_style(style.clone())
                            .with_prefix(r.name.to_string()),
                    ),
                );
            }
            for (bar, r) in lines.iter().zip(&s.robots) {
                bar.set_message(robot_line(r));
            }
        } else if last_print.elapsed() >= Duration::from_secs(5) {
            last_print = Instant::now();
            eprintln!("demo: {}", header(s));
            for r in &s.robots {
                eprintln!("demo:   {} {}", r.name, robot_line(r));
            }
        }
    };
    eprintln!(
        "doorslam demo: {} robots, report in {}",
        args.robots,
        out.display()
    );
    let summary = demo::run(&config, &mut progress)
        .with_context(|| format!("demo (report folder {})", out.display()))?;
    top.finish_and_clear();
    for l in &lines {
        l.finish();
    }
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!(
            "doorslam demo: {} robots; team ATE {} m (centralized oracle {} m), team gain {}, {} of {} robots in the team frame; closures {} ({} true, {} false kept by PCM); {:.1} kB between robots; {:.0} s",
            summary.robots,
            summary.team_ate_m.map_or("—".into(), |v| format!("{v:.2}")),
            summary.centralized_ate_m.map_or("—".into(), |v| format!("{v:.2}")),
            summary.team_gain.map_or("—".into(), |v| format!("{v:.2}")),
            summary.robots_in_team_frame,
            summary.robots,
            summary.closures.total,
            summary.closures.true_closures,
            summary.closures.false_accepted,
            summary.bandwidth.get("total_bytes").and_then(|v| v.as_u64()).unwrap_or(0) as f64 / 1e3,
            summary.durations.total_s
        );
        println!("{}", summary.realtime.verdict);
        println!("report: {}", out.join("report.md").display());
    }
    Ok(())
}
