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
