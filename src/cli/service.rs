//! `doorslam service <name> --config robot.toml`: one on-robot service process.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, ValueEnum};

use doorslam_camera::CameraSource;

use crate::config::RobotConfig;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ServiceName {
    Camera,
    Frontend,
    PlaceRecognition,
    Backend,
    Team,
    /// Simulation stand-in for the front-end: ground-truth keyframes (not VO).
    SimKeyframes,
    /// The robot's state as ROS 2 topics over Zenoh, as rmw_zenoh publishes (`[ros2]`).
    Ros2,
}

#[derive(Debug, Args)]
pub struct ServiceArgs {
    /// Which service this process runs.
    pub name: ServiceName,
    /// Robot configuration (TOML); built-in defaults when absent.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(args: ServiceArgs) -> Result<()> {
    let config = RobotConfig::load_or_default(args.config.as_ref())?;
    tracing::info!(robot = %config.robot.id, service = ?args.name, "starting service");
    trim_memory_every(config.up.trim_every_s);
    if args.name == ServiceName::Backend {
        // One thread for the back-end's dense kernels: faer's matrix products keep a
        // per-thread packing buffer (two L3 caches' worth, touched as the graph's
        // supernodes grow) for the life of each thread, so a thread pool holds one per
        // worker; sequential, the robot's other services keep the second core.
        faer::set_global_parallelism(faer::Par::Seq);
    }
    match args.name {
        ServiceName::Camera => Ok(doorslam_camera::run(
            &config.camera,
            &config.robot.id,
            config.robot.index,
        )?),
        ServiceName::SimKeyframes => {
            let c = doorslam_hil::sim_keyframes::SimKeyframesConfig {
                robot: config.robot.id.clone(),
                robot_index: config.robot.index,
                every: config.sim_keyframes.every,
            };
            doorslam_hil::sim_keyframes::run(&c)?;
            Ok(())
        }
        ServiceName::Frontend => {
            let camera = &config.camera;
            let replay = match (camera.source, &camera.replay) {
                (CameraSource::Replay, Some(r)) => Some(r.path.as_path()),
                _ => None,
            };
            let c = config.frontend.for_robot(
                &config.robot.id,
                config.robot.index,
                replay,
                [camera.width, camera.height],
            )?;
            doorslam_frontend::service::run(&c)?;
            Ok(())
        }
        ServiceName::PlaceRecognition => {
            let c = config.place.for_robot(&config.robot.id, config.robot.index);
            // Stopped by SIGTERM/SIGINT (iceoryx2's node sees them): `stop` stays unset.
            let stop = std::sync::atomic::AtomicBool::new(false);
            doorslam_place_recognition::service::run(&c, &stop)?;
            Ok(())
        }
        ServiceName::Backend => {
            let c = config
                .backend
                .for_robot(&config.robot.id, config.robot.index);
            doorslam_backend::service::run(&c)?;
            Ok(())
        }
        ServiceName::Ros2 => {
            if !config.ros2.enabled {
                anyhow::bail!(
                    "ros2.enabled = false: the ROS 2 publishers are off (set ros2.enabled = true)"
                );
            }
            let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
            let flag = stop.clone();
            ctrlc::set_handler(move || flag.store(true, std::sync::atomic::Ordering::SeqCst))?;
            let c = config.ros2.for_robot(
                &config.robot.id,
                u8::try_from(config.robot.index)?,
                &config.backend.state_dir,
            );
            let s = doorslam_ros2::live::run(&c, &stop)?;
            tracing::info!(
                ticks = s.ticks,
                reads = s.reads,
                read_errors = s.read_errors,
                samples = s.samples,
                bytes = s.bytes,
                seconds = s.seconds,
                "ros2: stopped"
            );
            Ok(())
        }
        ServiceName::Team => {
            // Stopped by SIGTERM/SIGINT: the ledger and status are written on the way out.
            let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
            let flag = stop.clone();
            ctrlc::set_handler(move || flag.store(true, std::sync::atomic::Ordering::SeqCst))?;
            let index = u8::try_from(config.robot.index)?;
            let status = match config.team.pieces {
                doorslam_team::runner::PiecesKind::Standin => {
                    tracing::warn!("team: stand-in pieces (simulated keyframes and descriptors, a truth-table verifier): a test of the link, not SLAM");
                    doorslam_team::runner::run(&config.team, &config.robot.id, index, &stop)?
                }
                doorslam_team::runner::PiecesKind::Robot => {
                    let pieces = doorslam_rendezvous::RobotPieces {
                        calibration: config.calibration()?,
                        matching: config.rendezvous.matching(
                            config.place.chain(),
                            config.place.own_loops,
                            config.place.temporal_exclusion,
                        ),
                    };
                    doorslam_rendezvous::run(&config.team, &config.robot.id, index, &pieces, &stop)?
                }
            };
            tracing::info!(published_bytes = status.published_bytes, "team: done");
            Ok(())
        }
    }
}

/// Hands the allocator's free memory back to the system every `every_s` seconds (0: never)
/// from a thread of its own. glibc keeps what a process frees (holes in its heaps, the
/// per-thread arenas) resident; a service that allocates per frame then looks as if it
/// grew (the soak of BENCHMARKS.md measured it: the front-end's heap 12 MB for 3.9 MB in
/// use). `malloc_trim(0)` releases the free pages of every arena; it takes each arena's
/// lock for a moment, no more.
fn trim_memory_every(every_s: f64) {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if every_s > 0.0 {
        let every = std::time::Duration::from_secs_f64(every_s);
        let spawned = std::thread::Builder::new()
            .name("malloc-trim".into())
            .spawn(move || loop {
                std::thread::sleep(every);
                // SAFETY: malloc_trim only walks glibc's own heaps under their locks.
                unsafe { libc::malloc_trim(0) };
            });
        if let Err(e) = spawned {
            tracing::warn!("memory trimming off: its thread did not start: {e}");
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    let _ = every_s;
}
