//! Ground-truth flights: smooth random walks of drones in a shared box, so paths cross.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use super::random::{Rng, Stream};
use super::SimConfig;

/// Half the side of the arena in x and y, m (a 20 m × 20 m area, as the paper's ARGoS arena
/// is small enough that every pair of drones meets several times).
pub const ARENA_HALF_M: f64 = 10.0;
/// Half the height of the arena, m: drones fly in a flat box, so that horizontal crossings
/// are also 3-D encounters.
pub const ARENA_HALF_HEIGHT_M: f64 = 3.0;

/// Near a side wall the drone starts turning back instead of bouncing off it.
const WALL_MARGIN_M: f64 = 3.0;
/// Yaw rate is an AR(1) process: persistence and per-step noise (rad).
const YAW_RATE_PERSISTENCE: f64 = 0.7;
const YAW_RATE_NOISE: f64 = 0.12;
const MAX_YAW_RATE: f64 = 0.5;
/// Extra yaw rate toward the centre when heading out near a wall (rad per step).
const WALL_TURN: f64 = 0.3;
/// Pitch (rad) is AR(1) too and kept small: mostly horizontal flight.
const PITCH_PERSISTENCE: f64 = 0.8;
const PITCH_NOISE: f64 = 0.03;
const MAX_PITCH: f64 = 0.2;
/// A drone banks into turns: roll = BANK · yaw rate.
const BANK: f64 = 0.5;

/// Whether `p` is inside the arena.
pub fn in_arena(p: &Point3<f64>) -> bool {
    p.x.abs() <= ARENA_HALF_M && p.y.abs() <= ARENA_HALF_M && p.z.abs() <= ARENA_HALF_HEIGHT_M
}

/// The body x axis (forward) of a drone with this attitude. nalgebra's Euler convention:
/// R = Rz(yaw) · Ry(pitch) · Rx(roll), so positive pitch points the nose down.
fn attitude(roll: f64, pitch: f64, yaw: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(roll, pitch, yaw)
}

/// One drone's flight of `n` poses, `step` m apart, starting anywhere in the arena.
fn random_walk(rng: &mut Rng, n: usize, step: f64) -> Vec<Isometry3<f64>> {
    let mut p = Point3::new(
        rng.uniform(-ARENA_HALF_M, ARENA_HALF_M),
        rng.uniform(-ARENA_HALF_M, ARENA_HALF_M),
        rng.uniform(-ARENA_HALF_HEIGHT_M, ARENA_HALF_HEIGHT_M),
    );
    let mut yaw = rng.uniform(-std::f64::consts::PI, std::f64::consts::PI);
    let (mut yaw_rate, mut pitch) = (0.0_f64, 0.0_f64);
    let mut poses = Vec::with_capacity(n);
    for _ in 0..n {
        poses.push(Isometry3::from_parts(
            Translation3::from(p.coords),
            attitude(BANK * yaw_rate, pitch, yaw),
        ));
        yaw_rate = YAW_RATE_PERSISTENCE * yaw_rate + YAW_RATE_NOISE * rng.gaussian();
        let wall_distance = ARENA_HALF_M - p.x.abs().max(p.y.abs());
        let heading = Vector3::new(yaw.cos(), yaw.sin(), 0.0);
        let outward = heading.x * p.x + heading.y * p.y > 0.0;
        if wall_distance < WALL_MARGIN_M && outward {
            // Turn the short way toward the centre: sign of (heading × to_centre).z.
            let turn = heading.x * -p.y - heading.y * -p.x;
            yaw_rate += WALL_TURN * turn.signum();
        }
        yaw_rate = yaw_rate.clamp(-MAX_YAW_RATE, MAX_YAW_RATE);
        yaw += yaw_rate;
        // The weak pull toward mid-height keeps drones from hugging floor or ceiling.
        pitch = (PITCH_PERSISTENCE * pitch
            + PITCH_NOISE * rng.gaussian()
            + 0.02 * p.z / ARENA_HALF_HEIGHT_M)
            .clamp(-MAX_PITCH, MAX_PITCH);
        p = next_position(&p, &mut yaw, &mut pitch, step);
    }
    poses
}

/// Flies one step; a step that would leave the arena is mirrored at the wall it crosses
/// (yaw or pitch reflected), which keeps a step shorter than the arena inside it.
fn next_position(p: &Point3<f64>, yaw: &mut f64, pitch: &mut f64, step: f64) -> Point3<f64> {
    let forward = |yaw: f64, pitch: f64| attitude(0.0, pitch, yaw) * Vector3::x();
    let q = p + step * forward(*yaw, *pitch);
    if q.x.abs() > ARENA_HALF_M {
        *yaw = std::f64::consts::PI - *yaw;
    }
    if q.y.abs() > ARENA_HALF_M {
        *yaw = -*yaw;
    }
    if q.z.abs() > ARENA_HALF_HEIGHT_M {
        *pitch = -*pitch;
    }
    let q = p + step * forward(*yaw, *pitch);
    // Last guard for steps longer than the arena is high: clamp into it.
    Point3::new(
        q.x.clamp(-ARENA_HALF_M, ARENA_HALF_M),
        q.y.clamp(-ARENA_HALF_M, ARENA_HALF_M),
        q.z.clamp(-ARENA_HALF_HEIGHT_M, ARENA_HALF_HEIGHT_M),
    )
}

/// Ground truth of every robot, robot-major.
pub(super) fn simulate_truth(config: &SimConfig) -> Vec<Vec<Isometry3<f64>>> {
    let mut rng = Rng::new(config.seed, Stream::Trajectories);
    (0..config.robots)
        .map(|_| random_walk(&mut rng, config.poses_per_robot, config.step_m))
        .collect()
}
