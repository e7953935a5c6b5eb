//! Route design: which streets each drone flies, chosen so that the team produces both
//! kinds of inter-robot closure candidates a DOOR-SLAM run must handle.
//!
//! Drones come in groups of three, by robot index modulo 3:
//! - **anchor** (0): starts one block before a copy `A` of a repeated building design
//!   and flies past it along one side;
//! - **follower** (1): flies the anchor's route `FOLLOWER_LEAD_M` ahead of it, at its
//!   speed, then turns off at the first intersection after `A`. The anchor later sees
//!   what the follower saw (true overlaps), and the two start within radio range;
//! - **alias partner** (2): flies past another copy `A'` of the same design along the
//!   same side in the same direction, so its views of `A'` match the anchor's views of
//!   `A` (perceptual aliasing: false closure candidates).
//!
//! After the designed part, alias partners and later anchors head for another drone (see
//! `pursuit_target`) until they are predicted to meet it; then every drone wanders: a
//! seeded random walk on the street grid without reversals, long enough for the
//! requested number of frames.

use nalgebra::Point2;

use crate::rng::SplitMix64;
use crate::world::World;

use super::closures::repeated_designs;
use super::route::{add, lot_of, node_position, on_grid, sub, Node, Path, PITCH, STEPS};
use super::{FlightConfig, FlightRole};

/// How far ahead of its anchor a follower starts, along the anchor's route (metres):
/// inside the default radio range, and a few seconds of flight, so the anchor sees the
/// follower's views again a few seconds later.
pub const FOLLOWER_LEAD_M: f64 = 20.0;

/// Largest altitude swing around a drone's cruise altitude (metres).
pub(crate) const MAX_ALTITUDE_SWING_M: f64 = 1.5;
/// Horizontal distance over which the altitude goes through one full swing (metres).
const ALTITUDE_WAVELENGTH_M: f64 = 90.0;

/// A directed street segment flanking a building: fly from `from` to `to`, having
/// approached along the same street from `from - (to - from)`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pass {
    approach: Node,
    from: Node,
    to: Node,
}

/// Which side of its lot a pass runs along and in which direction, as the offsets of its
/// `from` and `to` nodes from the lot's south-west corner: the same choice gives the same
/// view of every copy of a design (copies have the same size and facing).
const PASSES: [(Node, Node); 8] = [
    ((0, 0), (1, 0)), // south side, heading east
    ((1, 0), (0, 0)), // south side, heading west
    ((0, 1), (1, 1)), // north side, heading east
    ((1, 1), (0, 1)), // north side, heading west
    ((0, 0), (0, 1)), // west side, heading north
    ((0, 1), (0, 0)), // west side, heading south
    ((1, 0), (1, 1)), // east side, heading north
    ((1, 1), (1, 0)), // east side, heading south
];

fn pass_of(lot: Node, choice: usize) -> Option<Pass> {
    let (from, to) = PASSES.get(choice)?;
    let (from, to) = (add(lot, *from), add(lot, *to));
    let approach = sub(from, sub(to, from));
    (on_grid(approach) && on_grid(to)).then_some(Pass { approach, from, to })
}

/// Smooth altitude over the horizontal arc length: a sinusoid around a cruise height.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Altitude {
    pub(crate) base: f64,
    pub(crate) swing: f64,
    pub(crate) phase: f64,
}

impl Altitude {
    pub(crate) fn at(&self, s: f64) -> f64 {
        self.base
            + self.swing * (std::f64::consts::TAU * s / ALTITUDE_WAVELENGTH_M + self.phase).sin()
    }
}

/// One drone's designed flight before sampling.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Route {
    pub role: FlightRole,
    pub path: Path,
    /// Arc length at the first frame.
    pub start_s: f64,
    pub speed: f64,
    pub altitude: Altitude,
}

/// Intermediate: the nodes of a route before it becomes a [`Path`].
struct Draft {
    role: FlightRole,
    nodes: Vec<Node>,
    start_s: f64,
    speed: f64,
}

/// Designs every drone's route, deterministically from `config.seed`.
pub(crate) fn plan_routes(world: &World, config: &FlightConfig) -> Vec<Route> {
    // Distinct from the town's own stream even when both use the same seed.
    let mut rng = SplitMix64::new(config.seed ^ 0xF11E_D5EE_D000_0001);
    let designs = repeated_designs(world);
    let duration = config.frames.saturating_sub(1) as f64 / config.rate_hz;
    let swing = MAX_ALTITUDE_SWING_M.min(0.25 * (config.max_altitude_m - config.min_altitude_m));
    let mut drafts: Vec<Draft> = Vec::with_capacity(config.robots);
    // (anchor robot, partner pass and building) of the current group.
    let mut group: Option<(usize, Option<(Pass, usize)>)> = None;
    for robot in 0..config.robots {
        let speed = config.speed_mps * rng.range(0.85, 1.15);
        let leader = group
            .as_ref()
            .and_then(|(l, _)| drafts.get(*l).map(|d| (*l, d)));
        let mut draft = match (robot % 3, leader, &group) {
            (1, Some((index, leader)), _) => follower(leader, index, &mut rng),
            (2, Some((index, _)), Some((_, Some((pass, building))))) => Draft {
                role: FlightRole::AliasPartner {
                    partner_of: index,
                    building: *building,
                },
                nodes: vec![pass.approach, pass.from, pass.to],
                start_s: 0.0,
                speed,
            },
            _ => {
                let (draft, partner) = anchor(world, &designs, robot / 3, speed, &mut rng);
                group = Some((robot, partner));
                draft
            }
        };
        // Extended now, not at the end: a follower copies its leader's whole route, a
        // pursuer needs its target's.
        let needed = draft.start_s + draft.speed * duration + PITCH;
        let partner_end = match &group {
            Some((leader, Some((pass, _)))) if *leader == robot && robot + 2 < config.robots => {
                Some(node_position(pass.to))
            }
            _ => None,
        };
        let meet_m = 0.5 * config.radio_range_m;
        if let Some(end) = partner_end {
            // The partner is not planned yet: head for where its designed part ends
            // while it heads for this drone.
            pursue(&mut draft, &|_| Some(end), meet_m, needed);
        } else if let Some(target) = pursuit_target(robot).and_then(|t| drafts.get(t)) {
            let path = Path::through(&target.nodes);
            let target_at = |t: f64| {
                path.sample(target.start_s + target.speed * t)
                    .map(|(p, _)| p)
            };
            pursue(&mut draft, &target_at, meet_m, needed);
        }
        extend_walk(&mut draft.nodes, needed, &mut rng);
        drafts.push(draft);
    }
    drafts
        .into_iter()
        .map(|d| Route {
            role: d.role,
            path: Path::through(&d.nodes),
            start_s: d.start_s,
            speed: d.speed,
            altitude: Altitude {
                base: rng.range(config.min_altitude_m + swing, config.max_altitude_m - swing),
                swing,
                phase: rng.range(0.0, std::f64::consts::TAU),
            },
        })
        .collect()
}

/// An anchor's draft past a copy of design `group % designs`, and the pass and building
/// its alias partner should fly. Without repeated designs, a random start.
fn anchor(
    world: &World,
    designs: &[Vec<usize>],
    group: usize,
    speed: f64,
    rng: &mut SplitMix64,
) -> (Draft, Option<(Pass, usize)>) {
    if let Some(pair) = designed_pass(world, designs, group, rng) {
        let (pass, a, partner) = pair;
        let draft = Draft {
            role: FlightRole::Anchor { building: a },
            nodes: vec![pass.approach, pass.from, pass.to],
            start_s: 0.0,
            speed,
        };
        return (draft, Some(partner));
    }
    let span = crate::town::LOTS + 1;
    let start = (rng.below(span) as i32, rng.below(span) as i32);
    let draft = Draft {
        role: FlightRole::Wanderer,
        nodes: vec![start],
        start_s: 0.0,
        speed,
    };
    (draft, None)
}

/// For group `group`: the anchor's pass, its building, and the partner's pass and
/// building — the same pass relative to the nearest other copy of the design, across the
/// line between the copies, so the pair can meet within a short flight. `None` without repeated designs or a pass that fits
/// on the grid for both copies.
fn designed_pass(
    world: &World,
    designs: &[Vec<usize>],
    group: usize,
    rng: &mut SplitMix64,
) -> Option<(Pass, usize, (Pass, usize))> {
    let lot_of_building = |index: usize| {
        world.buildings().get(index).map(|b| {
            let (lo, hi) = (b.bounds().min, b.bounds().max);
            lot_of(0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y))
        })
    };
    let copies = designs.get(group % designs.len().max(1))?;
    // Successive groups on the same design start from another copy.
    let a = copies[(group / designs.len()) % copies.len()];
    let lot_a = lot_of_building(a)?;
    let (b, lot_b) = copies
        .iter()
        .filter(|&&c| c != a)
        .filter_map(|&c| Some((c, lot_of_building(c)?)))
        .min_by_key(|(_, l)| (l.0 - lot_a.0).abs() + (l.1 - lot_a.1).abs())?;
    let choices: Vec<(Pass, Pass)> = (0..PASSES.len())
        .filter_map(|c| Some((pass_of(lot_a, c)?, pass_of(lot_b, c)?)))
        .collect();
    // Passes across the line between the copies, not along it: after their passes the
    // two drones can turn toward each other instead of one chasing the other.
    let offset = sub(lot_b, lot_a);
    let along = |p: &Pass| {
        let d = sub(p.to, p.from);
        (d.0 * offset.0 + d.1 * offset.1).abs()
    };
    let least = choices.iter().map(|(p, _)| along(p)).min()?;
    let choices: Vec<(Pass, Pass)> = choices
        .into_iter()
        .filter(|(p, _)| along(p) == least)
        .collect();
    let (pass, partner_pass) = choices[rng.below(choices.len())];
    Some((pass, a, (partner_pass, b)))
}

/// The leader's first three nodes, then a different turn than the leader's.
fn follower(leader: &Draft, leader_index: usize, rng: &mut SplitMix64) -> Draft {
    let mut nodes: Vec<Node> = leader.nodes.iter().take(3).copied().collect();
    if let (Some(&next), &[.., a, b]) = (leader.nodes.get(3), nodes.as_slice()) {
        let options: Vec<Node> = successors(a, b)
            .into_iter()
            .filter(|n| *n != next)
            .collect();
        if !options.is_empty() {
            nodes.push(options[rng.below(options.len())]);
        }
    }
    Draft {
        role: FlightRole::Follower {
            leader: leader_index,
        },
        nodes,
        start_s: FOLLOWER_LEAD_M,
        speed: leader.speed,
    }
}

/// Whom a drone heads for after its designed part, so that the drones which share
/// closure candidates also meet (DOOR-SLAM only finds closures during rendezvous): an
/// alias partner its anchor, an anchor without a partner the previous group's anchor
/// (an anchor with one heads for the end of the partner's pass instead). Followers
/// start in range of their anchor already.
fn pursuit_target(robot: usize) -> Option<usize> {
    match robot % 3 {
        2 => Some(robot - 2),
        0 if robot >= 3 => Some(robot - 3),
        _ => None,
    }
}

/// Extends `draft` greedily toward where the target will be (`target_at(time)`), one
/// intersection at a time, until it is predicted within `meet_m` of it or its route
/// reaches `length` metres.
fn pursue(
    draft: &mut Draft,
    target_at: &dyn Fn(f64) -> Option<Point2<f64>>,
    meet_m: f64,
    length: f64,
) {
    while let [.., a, b] = *draft.nodes.as_slice() {
        let s = Path::through(&draft.nodes).length();
        if s >= length {
            return;
        }
        // When the drone would reach the next intersection.
        let t = (s + PITCH - draft.start_s) / draft.speed;
        let Some(p) = target_at(t) else { return };
        let best = successors(a, b)
            .into_iter()
            .map(|n| (n, (node_position(n) - p).norm()))
            .min_by(|x, y| x.1.total_cmp(&y.1));
        let Some((next, distance)) = best else { return };
        draft.nodes.push(next);
        if distance <= meet_m {
            return;
        }
    }
}

/// Grid neighbours of `at` reachable from `previous` without reversing.
fn successors(previous: Node, at: Node) -> Vec<Node> {
    let back = sub(previous, at);
    STEPS
        .iter()
        .filter(|&&step| step != back)
        .map(|&step| add(at, step))
        .filter(|&n| on_grid(n))
        .collect()
}

/// Appends a random walk until the nodes span at least `length` metres of street.
fn extend_walk(nodes: &mut Vec<Node>, length: f64, rng: &mut SplitMix64) {
    if nodes.is_empty() {
        nodes.push((0, 0));
    }
    // Corners make the path shorter than its legs: measure the real path.
    while (nodes.len() - 1) as f64 * PITCH < length || Path::through(nodes).length() < length {
        let options = match nodes.as_slice() {
            [.., a, b] => successors(*a, *b),
            [a] => STEPS
                .iter()
                .map(|&s| add(*a, s))
                .filter(|&n| on_grid(n))
                .collect(),
            [] => Vec::new(),
        };
        if options.is_empty() {
            // Cannot happen on a grid of at least 2 × 2 nodes; stop rather than loop.
            return;
        }
        nodes.push(options[rng.below(options.len())]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passes_stay_on_the_grid_and_walks_never_reverse() {
        // Heading east along the south side of a border lot: the approach is off the grid.
        assert!(pass_of((0, 0), 0).is_none());
        assert!(pass_of((0, 0), 1).is_some());
        let pass = pass_of((2, 3), 0).unwrap();
        assert_eq!(
            (pass.approach, pass.from, pass.to),
            ((1, 3), (2, 3), (3, 3))
        );
        let mut rng = SplitMix64::new(3);
        let mut nodes = vec![(0, 0)];
        extend_walk(&mut nodes, 40.0 * PITCH, &mut rng);
        for w in nodes.windows(3) {
            assert_ne!(w[0], w[2]);
            assert_eq!((w[1].0 - w[0].0).abs() + (w[1].1 - w[0].1).abs(), 1);
        }
    }
}
