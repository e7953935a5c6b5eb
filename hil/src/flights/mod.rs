//! Multi-drone flights through [`World::town`]: smooth street-following trajectories,
//! radio rendezvous events and ground-truth closure candidates, written as one
//! KITTI-layout stereo sequence per drone ([`write_team`]).
//!
//! Every drone records at the same instants `k / rate_hz`. Poses are camera-to-world of
//! the LEFT camera (camera x right, y down, z forward; world z up), as the renderer and
//! `doorslam_dataset::Dataset::with_truth` use them. The camera looks along the flight
//! direction, pitched down by `pitch_down_deg` so street, facades and a strip of sky
//! are all in view.
//!
//! Two plans ([`FlightPlan`]):
//! - **designed** (`sim world`'s default, see the `plan` module): the default 5-drone team
//!   has true overlaps (a drone sees again what another saw a few seconds earlier) and
//!   perceptual aliases (two drones see different copies of one repeated building from the
//!   same relative viewpoint);
//! - **sectors** (the demo's scenario, see the `sectors` module): every drone patrols the
//!   loop around its own sector of the town, neighbouring loops share a street flown the
//!   same way, so every drone re-visits places another drone saw, several times, and its
//!   own places a lap later.
//!
//! [`closure_candidates`] lists true overlaps and aliases between drones,
//! [`own_candidates`] a drone's own, [`overlap_counts`] counts the stretches of every
//! drone's flight over places others (or itself) saw. Everything is a pure function of the
//! world and [`FlightConfig`].

mod closures;
mod imaging;
mod output;
mod overlaps;
mod plan;
mod rendezvous;
mod resolution;
mod route;
mod sectors;

use std::path::PathBuf;

use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::camera::StereoCamera;
use crate::error::HilError;
use crate::world::World;

pub use closures::{
    closure_candidates, own_candidates, repeated_designs, seen_buildings, ClosureCandidate,
    ClosureKind, OVERLAP_MAX_ANGLE_DEG, OVERLAP_RADIUS_M, SEEN_FRACTION, SEEN_MAX_DEPTH_M,
};
pub use imaging::TeamCamera;
pub use output::{robot_name, write_team, Progress};
pub use overlaps::{
    overlap_counts, overlap_counts_of, OverlapCounts, Revisit, MIN_OWN_GAP_S, STRETCH_GAP_S,
};
pub use plan::FOLLOWER_LEAD_M;
pub use rendezvous::{rendezvous_events, RangeEvent, RangeEventKind};
pub use resolution::camera_for_resolution;
pub use route::CORNER_RADIUS_M;
pub use sectors::{Sector, MIN_LAPS, MIN_MEETING_S, MIN_SEPARATION_M, SPEED_SPREAD};

/// Most drones a team can have: robots are named `a` to `z`.
pub const MAX_ROBOTS: usize = doorslam_geometry::key::MAX_ROBOTS as usize;

/// Failures of planning or writing a team flight; each names the field or the file.
#[derive(Debug, thiserror::Error)]
pub enum FlightError {
    #[error("invalid flight config: {field} = {value} ({reason})")]
    Config {
        field: &'static str,
        value: String,
        reason: &'static str,
    },
    #[error("invalid resolution {spec:?}: {reason} (expected WIDTHxHEIGHT, `euroc` or `kitti`)")]
    Resolution { spec: String, reason: String },
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} holds {count} image(s) this run would not overwrite (an earlier, longer run?); use an empty output folder")]
    StaleFrames { path: PathBuf, count: usize },
    #[error(transparent)]
    Hil(#[from] HilError),
}

/// How the drones' routes are planned.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum FlightPlan {
    /// Groups of three: anchor, follower, alias partner, then random walks (`plan`).
    #[default]
    Designed,
    /// Every drone patrols its own sector; neighbouring sectors share a street (`sectors`).
    Sectors,
}

impl FlightPlan {
    /// `designed` or `sectors`, as `world.txt` and `--plan` spell it.
    pub fn as_str(self) -> &'static str {
        match self {
            FlightPlan::Designed => "designed",
            FlightPlan::Sectors => "sectors",
        }
    }
}

/// What to fly. `Default` is the 5-drone, 30-second team of `doorslam sim world`.
#[derive(Debug, Clone, PartialEq)]
pub struct FlightConfig {
    pub robots: usize,
    /// Frames per robot.
    pub frames: usize,
    pub rate_hz: f64,
    /// Horizontal speed. Designed plan: the mean, each drone flies at 85–115 % of it;
    /// sectors: the slowest drone's, each flies at 100 % to 100 + 100 × [`SPEED_SPREAD`] %.
    pub speed_mps: f64,
    pub min_altitude_m: f64,
    pub max_altitude_m: f64,
    /// Camera pitch below the horizon (degrees).
    pub pitch_down_deg: f64,
    pub radio_range_m: f64,
    pub seed: u64,
    pub plan: FlightPlan,
}

impl Default for FlightConfig {
    fn default() -> Self {
        Self {
            robots: 5,
            frames: 300,
            rate_hz: 10.0,
            speed_mps: 3.5,
            min_altitude_m: 4.0,
            max_altitude_m: 12.0,
            pitch_down_deg: 12.0,
            radio_range_m: 30.0,
            seed: 1,
            plan: FlightPlan::Designed,
        }
    }
}

fn config_error(field: &'static str, value: impl ToString, reason: &'static str) -> FlightError {
    FlightError::Config {
        field,
        value: value.to_string(),
        reason,
    }
}

impl FlightConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), FlightError> {
        if self.robots == 0 || self.robots > MAX_ROBOTS {
            return Err(config_error("robots", self.robots, "must be 1..=26"));
        }
        if self.frames == 0 {
            return Err(config_error("frames", self.frames, "must be > 0"));
        }
        let finite_in = |field, value: f64, lo: f64, hi: f64, reason| {
            if value.is_finite() && value >= lo && value <= hi {
                Ok(())
            } else {
                Err(config_error(field, value, reason))
            }
        };
        finite_in(
            "rate_hz",
            self.rate_hz,
            0.1,
            1000.0,
            "must be in [0.1, 1000]",
        )?;
        finite_in(
            "speed_mps",
            self.speed_mps,
            0.1,
            10.0,
            "must be in [0.1, 10]",
        )?;
        finite_in(
            "min_altitude_m",
            self.min_altitude_m,
            1.0,
            100.0,
            "must be in [1, 100]",
        )?;
        finite_in(
            "max_altitude_m",
            self.max_altitude_m,
            self.min_altitude_m,
            100.0,
            "must be in [min_altitude_m, 100]",
        )?;
        finite_in(
            "pitch_down_deg",
            self.pitch_down_deg,
            -45.0,
            80.0,
            "must be in [-45, 80]",
        )?;
        finite_in(
            "radio_range_m",
            self.radio_range_m,
            0.0,
            1e6,
            "must be in [0, 1e6]",
        )?;
        Ok(())
    }

    /// Time of frame `k` (seconds).
    pub fn time_of(&self, k: usize) -> f64 {
        k as f64 / self.rate_hz
    }
}

/// What a drone's route was designed for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FlightRole {
    /// Approaches `building`, a copy of a repeated design, and flies along one side.
    Anchor { building: usize },
    /// Flies its `leader`'s route [`FOLLOWER_LEAD_M`] ahead of it, then turns off.
    Follower { leader: usize },
    /// Passes `building`, another copy of the design `partner_of` passes, the same way.
    AliasPartner { partner_of: usize, building: usize },
    /// A random walk (the world has no repeated designs to aim at).
    Wanderer,
    /// Patrols the loop around `sector`; placed next to `parent`'s sector.
    Patrol {
        sector: Sector,
        parent: Option<usize>,
    },
}

impl std::fmt::Display for FlightRole {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            FlightRole::Anchor { building } => write!(f, "anchor past building {building}"),
            FlightRole::Follower { leader } => {
                write!(
                    f,
                    "follower {FOLLOWER_LEAD_M} m ahead of {}",
                    robot_name(leader)
                )
            }
            FlightRole::AliasPartner {
                partner_of,
                building,
            } => write!(
                f,
                "alias partner of {} past building {building}",
                robot_name(partner_of)
            ),
            FlightRole::Wanderer => write!(f, "random walk"),
            FlightRole::Patrol { sector, parent } => {
                write!(f, "patrol of the {sector}")?;
                match parent {
                    Some(p) => write!(f, ", next to {}", robot_name(p)),
                    None => Ok(()),
                }
            }
        }
    }
}

/// One drone's sampled flight.
#[derive(Debug, Clone, PartialEq)]
pub struct Flight {
    pub role: FlightRole,
    pub speed_mps: f64,
    /// Frame times (seconds).
    pub times: Vec<f64>,
    /// Left-camera poses, camera-to-world, one per frame.
    pub poses: Vec<Isometry3<f64>>,
    /// The continuous trajectory the frames sample (motion blur needs the pose during
    /// the exposure, between frames).
    trajectory: Trajectory,
}

impl Flight {
    /// Left-camera pose at any time `t` (seconds), on the same smooth trajectory as
    /// [`Flight::poses`] (`pose_at(times[k]) == poses[k]`). Before the first frame and
    /// after the route's end the drone hovers where the route begins or ends.
    pub fn pose_at(&self, t: f64) -> Isometry3<f64> {
        self.trajectory.pose_at(t)
    }
}

/// A route flown at constant speed with the camera pitched down: pose as a function of time.
#[derive(Debug, Clone, PartialEq)]
struct Trajectory {
    route: plan::Route,
    pitch: f64,
}

impl Trajectory {
    fn pose_at(&self, t: f64) -> Isometry3<f64> {
        let route = &self.route;
        let s = route.start_s + route.speed * t;
        let (p, yaw) = route
            .path
            .sample(s)
            .unwrap_or((nalgebra::Point2::origin(), 0.0));
        // The path clamps s to its length; the altitude must follow the same clamp.
        let s = s.clamp(0.0, route.path.length());
        let eye = nalgebra::Point3::new(p.x, p.y, route.altitude.at(s));
        heading_pose(eye, yaw, self.pitch)
    }
}

/// A planned team: flights, radio events and closure candidates.
#[derive(Debug, Clone, PartialEq)]
pub struct TeamFlight {
    pub config: FlightConfig,
    pub camera: StereoCamera,
    pub flights: Vec<Flight>,
    pub events: Vec<RangeEvent>,
    pub closures: Vec<ClosureCandidate>,
    /// Each drone's candidates with its own earlier frames ([`own_candidates`]).
    pub own: Vec<ClosureCandidate>,
}

impl TeamFlight {
    /// Number of closure candidates of a kind.
    pub fn count(&self, kind: ClosureKind) -> usize {
        self.closures.iter().filter(|c| c.kind == kind).count()
    }
}

/// Camera-to-world pose of a camera at `eye` heading `yaw` (radians from +x,
/// counter-clockwise), pitched down by `pitch` (radians), image rows level.
pub fn heading_pose(eye: nalgebra::Point3<f64>, yaw: f64, pitch: f64) -> Isometry3<f64> {
    let (sy, cy) = yaw.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    let z = Vector3::new(cy * cp, sy * cp, -sp);
    let x = Vector3::new(sy, -cy, 0.0);
    let y = z.cross(&x);
    let rotation = Rotation3::from_basis_unchecked(&[x, y, z]);
    Isometry3::from_parts(
        Translation3::from(eye.coords),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

/// Every drone's trajectory, sampled at the frame times.
pub fn fly_team(world: &World, config: &FlightConfig) -> Result<Vec<Flight>, FlightError> {
    config.validate()?;
    let pitch = config.pitch_down_deg.to_radians();
    let routes = match config.plan {
        FlightPlan::Designed => plan::plan_routes(world, config),
        FlightPlan::Sectors => sectors::plan_sectors(world, config),
    };
    let flights = routes
        .into_iter()
        .map(|route| {
            let times: Vec<f64> = (0..config.frames).map(|k| config.time_of(k)).collect();
            let trajectory = Trajectory { route, pitch };
            let poses = times.iter().map(|&t| trajectory.pose_at(t)).collect();
            Flight {
                role: trajectory.route.role,
                speed_mps: trajectory.route.speed,
                times,
                poses,
                trajectory,
            }
        })
        .collect();
    Ok(flights)
}

/// One robot's flight of `frames` frames at `rate_hz` through the town of `seed`, seen by
/// the EuRoC-like camera: the world and the planned team (`team.flights[0].poses` are the
/// true left-camera poses; `team.camera` the camera). What the front-end's tests fly.
pub fn one_robot_flight(
    seed: u64,
    frames: usize,
    rate_hz: f64,
) -> Result<(World, TeamFlight), FlightError> {
    let camera = StereoCamera::euroc_like();
    let config = FlightConfig {
        robots: 1,
        frames,
        rate_hz,
        seed,
        ..FlightConfig::default()
    };
    let world = World::town(config.seed);
    let team = simulate_team(&world, &camera, &config)?;
    Ok((world, team))
}

/// Plans the team and derives its rendezvous events and closure candidates (the camera
/// decides what counts as seen).
pub fn simulate_team(
    world: &World,
    camera: &StereoCamera,
    config: &FlightConfig,
) -> Result<TeamFlight, FlightError> {
    let flights = fly_team(world, config)?;
    let events = rendezvous_events(&flights, config.radio_range_m);
    let (closures, own) = closures::all_candidates(world, camera, &flights);
    Ok(TeamFlight {
        config: config.clone(),
        camera: *camera,
        flights,
        events,
        closures,
        own,
    })
}
