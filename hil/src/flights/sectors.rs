//! The sector patrol plan ([`FlightPlan::Sectors`](super::FlightPlan), the demo's
//! scenario): the town's street grid is cut into equal rectangles of whole lots
//! (sectors); each drone patrols the streets around its own sector, lap after lap.
//!
//! What a multi-robot SLAM run must show, and how the plan gets it:
//! - **re-visits of places another drone saw**: the chosen sectors are connected by shared
//!   sides, and neighbouring loops run in opposite senses (a checkerboard of clockwise and
//!   counter-clockwise sectors), so two neighbours fly their shared street in the same
//!   direction and see it from the same side: true overlaps. Every drone starts where the
//!   part of its loop it flies twice covers a shared side ([`plan_sectors`] checks it for
//!   every start it considers), so it flies shared streets at least twice, about a lap
//!   apart: crossings at different times; its second pass comes after its neighbour's
//!   first (speeds differ by at most [`SPEED_SPREAD`], less than a shared side is of a
//!   lap), so it re-visits what the neighbour saw;
//! - **re-visits of its own places**: the sector size is the largest whose lap the
//!   slowest drone flies at least [`MIN_LAPS`] times;
//! - **aliasing**: among the ways of choosing the sectors and the senses, the one whose
//!   loops pass the most pairs of *different* copies of one design the same way (same side
//!   of the lot, same direction: what [`closure_candidates`](super::closure_candidates)
//!   lists as aliased);
//! - **rendezvous**: the radio range is shorter than a sector, so drones meet only near a
//!   shared side at the same time. Start points are searched so that every drone meets
//!   the drone whose sector it was attached to (its parent) during the flight, not at
//!   take-off: they meet and part. This part is searched for, not guaranteed; the test of
//!   the plan (`hil/tests/sectors.rs`) counts the meetings with
//!   [`rendezvous_events`](super::rendezvous_events).
//!
//! Overlaps are counted from ground truth by [`super::overlap_counts`].

use std::collections::BTreeSet;

use nalgebra::{Point2, Point3};

use crate::rng::SplitMix64;
use crate::town::LOTS;
use crate::world::World;

use super::closures::repeated_designs;
use super::plan::{Altitude, Route, MAX_ALTITUDE_SWING_M};
use super::route::{add, lot_of, node_position, Node, Path, CORNER_RADIUS_M, PITCH};
use super::{FlightConfig, FlightRole};

/// The slowest drone flies its sector's loop at least this many times (when the town has
/// sectors that small; one-lot sectors otherwise).
pub const MIN_LAPS: f64 = 1.5;
/// Each drone flies at 100 % to 100 + 100 × this % of the configured speed: the
/// configured speed is the slowest drone's.
pub const SPEED_SPREAD: f64 = 0.1;
/// Two drones in range at least this long have met (seconds): time for the team link to
/// find the other (Zenoh scouts every 8 s at most) and exchange descriptors.
pub const MIN_MEETING_S: f64 = 10.0;
/// Planned drones never come closer than this to each other (metres).
pub const MIN_SEPARATION_M: f64 = 3.0;

/// Sector sizes (lots along x, along y), largest loop first.
const SIZES: [(i32, i32); 7] = [(3, 3), (3, 2), (2, 3), (2, 2), (2, 1), (1, 2), (1, 1)];
/// Start points are tried every this many metres along a loop.
const OFFSET_STEP_M: f64 = 2.5;
/// Positions are compared every this many seconds when searching start points.
const SAMPLE_S: f64 = 0.5;
/// Ways of choosing the sectors tried (random connected growths, each in both senses).
const LAYOUT_TRIES: usize = 96;
/// Start points of the first drone tried before keeping the plan with the most meetings.
const ROOT_TRIES: usize = 16;

/// One drone's sector: the rectangle of `size` lots whose south-west corner is the
/// intersection `origin`, flown clockwise or counter-clockwise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Sector {
    pub origin: (i32, i32),
    pub size: (i32, i32),
    pub clockwise: bool,
}

impl Sector {
    /// The four corners in flight order, from the south-west one.
    fn corners(&self) -> [Node; 4] {
        let ((x, y), (w, h)) = (self.origin, self.size);
        let ccw = [(x, y), (x + w, y), (x + w, y + h), (x, y + h)];
        if self.clockwise {
            [ccw[0], ccw[3], ccw[2], ccw[1]]
        } else {
            ccw
        }
    }

    /// The directed sides, corner to corner, in flight order.
    fn sides(&self) -> [(Node, Node); 4] {
        let c = self.corners();
        [(c[0], c[1]), (c[1], c[2]), (c[2], c[3]), (c[3], c[0])]
    }

    /// One lap through neighbouring intersections, from the first corner (which is not
    /// repeated at the end).
    fn lap_nodes(&self) -> Vec<Node> {
        let mut nodes = Vec::new();
        for (a, b) in self.sides() {
            let step = ((b.0 - a.0).signum(), (b.1 - a.1).signum());
            let mut n = a;
            while n != b {
                nodes.push(n);
                n = add(n, step);
            }
        }
        nodes
    }

    /// Length of one lap with its four rounded corners (metres).
    pub fn lap_m(&self) -> f64 {
        let (w, h) = self.size;
        let cut = (2.0 - std::f64::consts::FRAC_PI_2) * CORNER_RADIUS_M;
        2.0 * f64::from(w + h) * PITCH - 4.0 * cut
    }

    /// Every block edge of the loop (neighbouring intersections, in flight order).
    fn edges(&self) -> Vec<(Node, Node)> {
        let nodes = self.lap_nodes();
        (0..nodes.len())
            .map(|k| (nodes[k], nodes[(k + 1) % nodes.len()]))
            .collect()
    }
}

impl std::fmt::Display for Sector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}x{}-lot sector at ({}, {}), {}",
            self.size.0,
            self.size.1,
            self.origin.0,
            self.origin.1,
            if self.clockwise {
                "clockwise"
            } else {
                "counter-clockwise"
            }
        )
    }
}

/// The sector grid of one size: `cols × rows` sectors, (i, j) with origin (i w, j h).
#[derive(Debug, Clone, Copy)]
struct Grid {
    size: (i32, i32),
    /// The first sector's south-west corner (the grid need not start at the town's edge).
    offset: (i32, i32),
    cols: i32,
    rows: i32,
}

impl Grid {
    fn new(size: (i32, i32)) -> Self {
        Self::with_offset(size, (0, 0))
    }

    fn with_offset(size: (i32, i32), offset: (i32, i32)) -> Self {
        let lots = LOTS as i32;
        Grid {
            size,
            offset,
            cols: (lots - offset.0) / size.0,
            rows: (lots - offset.1) / size.1,
        }
    }

    /// The grids of one sector size: every offset within a sector.
    fn all_of(size: (i32, i32)) -> Vec<Grid> {
        (0..size.1)
            .flat_map(|oy| (0..size.0).map(move |ox| Grid::with_offset(size, (ox, oy))))
            .collect()
    }

    fn count(&self) -> usize {
        (self.cols * self.rows) as usize
    }

    fn cell(&self, index: usize) -> (i32, i32) {
        (index as i32 % self.cols, index as i32 / self.cols)
    }

    /// Sector `index`; neighbours in a checkerboard fly opposite senses, `flip` swaps all.
    fn sector(&self, index: usize, flip: bool) -> Sector {
        let (i, j) = self.cell(index);
        Sector {
            origin: (
                self.offset.0 + i * self.size.0,
                self.offset.1 + j * self.size.1,
            ),
            size: self.size,
            clockwise: ((i + j) % 2 == 1) != flip,
        }
    }

    /// Sectors sharing a side with `index`.
    fn neighbours(&self, index: usize) -> Vec<usize> {
        let (i, j) = self.cell(index);
        [(1, 0), (0, 1), (-1, 0), (0, -1)]
            .iter()
            .map(|(di, dj)| (i + di, j + dj))
            .filter(|&(a, b)| a >= 0 && b >= 0 && a < self.cols && b < self.rows)
            .map(|(a, b)| (b * self.cols + a) as usize)
            .collect()
    }
}

/// Directed sides two sectors both fly (neighbours in opposite senses share one).
fn shared_sides(a: &Sector, b: &Sector) -> Vec<(Node, Node)> {
    let sb = b.sides();
    a.sides().into_iter().filter(|s| sb.contains(s)).collect()
}

/// Building (index) standing in each lot, and the design group of each building.
struct Lots {
    building: std::collections::BTreeMap<Node, usize>,
    design: std::collections::BTreeMap<usize, usize>,
}

impl Lots {
    fn new(world: &World) -> Self {
        let building = world
            .buildings()
            .iter()
            .enumerate()
            .map(|(i, b)| {
                let (lo, hi) = (b.bounds().min, b.bounds().max);
                (lot_of(0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y)), i)
            })
            .collect();
        let design = repeated_designs(world)
            .into_iter()
            .enumerate()
            .flat_map(|(d, group)| group.into_iter().map(move |b| (b, d)))
            .collect();
        Lots { building, design }
    }

    /// The passes of a loop along copies of repeated designs: (design, building, the
    /// edge relative to the lot's south-west corner). Two passes with the same design and
    /// relative edge but different buildings see look-alikes the same way.
    fn passes(&self, sector: &Sector) -> Vec<(usize, usize, (Node, Node))> {
        let mut out = Vec::new();
        for (from, to) in sector.edges() {
            let d = (to.0 - from.0, to.1 - from.1);
            // The lots on either side of the edge (left, right of the direction).
            let lots = match d {
                (1, 0) => [(from.0, from.1), (from.0, from.1 - 1)],
                (0, 1) => [(from.0 - 1, from.1), (from.0, from.1)],
                (-1, 0) => [(to.0, to.1 - 1), (to.0, to.1)],
                _ => [(to.0, to.1), (to.0 - 1, to.1)],
            };
            for lot in lots {
                let Some(&b) = self.building.get(&lot) else {
                    continue;
                };
                if let Some(&design) = self.design.get(&b) {
                    let rel = |n: Node| (n.0 - lot.0, n.1 - lot.1);
                    out.push((design, b, (rel(from), rel(to))));
                }
            }
        }
        out
    }
}

/// Pairs of passes (by different drones; by the same drone) that see different copies
/// of one design the same way.
fn aliasing(lots: &Lots, sectors: &[Sector]) -> (usize, usize) {
    let passes: Vec<_> = sectors.iter().map(|s| lots.passes(s)).collect();
    let (mut between, mut own) = (0, 0);
    for (a, pa) in passes.iter().enumerate() {
        for (b, pb) in passes.iter().enumerate().skip(a) {
            for x in pa {
                for y in pb {
                    if x.0 == y.0 && x.1 != y.1 && x.2 == y.2 {
                        if a == b {
                            own += 1;
                        } else {
                            between += 1;
                        }
                    }
                }
            }
        }
    }
    (between, own / 2)
}

/// Which sectors, in which senses, in drone order (a breadth-first order from the first,
/// each with the earlier drone it is attached to).
struct Layout {
    sectors: Vec<Sector>,
    parents: Vec<Option<usize>>,
}

/// How a layout ranks: look-alikes seen the same way by two drones first, then the most
/// shared sides, then the fewest sides on the town's edge (half the view would be the empty
/// land outside), then the most look-alikes, then the closest to the town's centre.
type LayoutScore = (bool, usize, i64, usize, usize, i64);

/// Sides of a loop on the town's edge.
fn edge_sides(sector: &Sector) -> usize {
    let lots = LOTS as i32;
    sector
        .sides()
        .iter()
        .filter(|((x0, y0), (x1, y1))| {
            (x0 == x1 && (*x0 == 0 || *x0 == lots)) || (y0 == y1 && (*y0 == 0 || *y0 == lots))
        })
        .count()
}

/// Grows [`LAYOUT_TRIES`] random connected sets of `n` sectors of `grid` and keeps the
/// best ([`LayoutScore`]).
fn choose_layout(
    grid: &Grid,
    n: usize,
    lots: &Lots,
    rng: &mut SplitMix64,
) -> (Option<LayoutScore>, Layout) {
    let mut best: Option<(LayoutScore, Vec<usize>, bool)> = None;
    let centre = f64::from(LOTS as i32) / 2.0;
    for _ in 0..LAYOUT_TRIES {
        let mut set = vec![rng.below(grid.count())];
        while set.len() < n.min(grid.count()) {
            let frontier: BTreeSet<usize> = set
                .iter()
                .flat_map(|&s| grid.neighbours(s))
                .filter(|s| !set.contains(s))
                .collect();
            let frontier: Vec<usize> = frontier.into_iter().collect();
            if frontier.is_empty() {
                break;
            }
            set.push(frontier[rng.below(frontier.len())]);
        }
        let shared: usize = set
            .iter()
            .enumerate()
            .map(|(k, &a)| {
                set[k + 1..]
                    .iter()
                    .filter(|b| grid.neighbours(a).contains(b))
                    .count()
            })
            .sum();
        // Spread from the centre, in hundredths of a lot.
        let spread: f64 = set
            .iter()
            .map(|&s| {
                let o = grid.sector(s, false).origin;
                let cx = f64::from(o.0) + 0.5 * f64::from(grid.size.0) - centre;
                let cy = f64::from(o.1) + 0.5 * f64::from(grid.size.1) - centre;
                (cx * cx + cy * cy).sqrt()
            })
            .sum();
        for flip in [false, true] {
            let sectors: Vec<Sector> = set.iter().map(|&s| grid.sector(s, flip)).collect();
            let (between, own) = aliasing(lots, &sectors);
            let edges: usize = sectors.iter().map(edge_sides).sum();
            let score = (
                between > 0,
                shared,
                -(edges as i64),
                between,
                own,
                -(spread * 100.0).round() as i64,
            );
            if best.as_ref().is_none_or(|b| score > b.0) {
                best = Some((score, set.clone(), flip));
            }
        }
    }
    let Some((score, set, flip)) = best else {
        let empty = Layout {
            sectors: Vec::new(),
            parents: Vec::new(),
        };
        return (None, empty);
    };
    // Drone a patrols the sector with the most chosen neighbours, the others follow in
    // breadth-first order, each attached to an earlier one.
    let chosen = |s: &usize| set.contains(s);
    let degree = |s: usize| grid.neighbours(s).iter().filter(|x| chosen(x)).count();
    let root = set
        .iter()
        .copied()
        .max_by_key(|&s| (degree(s), std::cmp::Reverse(s)))
        .unwrap_or(set[0]);
    let mut order = vec![root];
    let mut parents = vec![None];
    let mut k = 0;
    while k < order.len() {
        for s in grid.neighbours(order[k]) {
            if chosen(&s) && !order.contains(&s) {
                order.push(s);
                parents.push(Some(k));
            }
        }
        k += 1;
    }
    let layout = Layout {
        sectors: order.iter().map(|&s| grid.sector(s, flip)).collect(),
        parents,
    };
    (Some(score), layout)
}

/// A drone's patrol before its start point is fixed.
struct Patrol {
    sector: Sector,
    parent: Option<usize>,
    speed: f64,
    altitude: Altitude,
    path: Path,
    /// Arc length where the loop's periodic part begins (the first corner's arc).
    origin_s: f64,
    /// Straight pieces over sides shared with other chosen sectors: (which shared side,
    /// arc length of the start, length).
    shared: Vec<(usize, f64, f64)>,
}

impl Patrol {
    fn new(
        sector: Sector,
        parent: Option<usize>,
        speed: f64,
        altitude: Altitude,
        length: f64,
        shared_sides: &[(Node, Node)],
    ) -> Self {
        let lap = sector.lap_nodes();
        let laps = (length / sector.lap_m()).ceil() as usize + 2;
        let mut nodes = vec![*lap.last().unwrap_or(&sector.origin)];
        for _ in 0..laps {
            nodes.extend(&lap);
        }
        nodes.push(lap[0]);
        let path = Path::through(&nodes);
        let on_side = |from: Point2<f64>, dir: nalgebra::Vector2<f64>, len: f64| {
            let mid = from + dir * (0.5 * len);
            shared_sides.iter().position(|&(a, b)| {
                let (pa, pb) = (node_position(a), node_position(b));
                let d = (pb - pa).normalize();
                let along = (mid - pa).dot(&d);
                (d - dir).norm() < 1e-6
                    && (mid - pa - d * along).norm() < 1e-6
                    && along > 0.0
                    && along < (pb - pa).norm()
            })
        };
        let shared = path
            .straight_pieces()
            .into_iter()
            .filter_map(|(s, len, from, dir)| Some((on_side(from, dir, len)?, s, len)))
            .collect();
        Patrol {
            sector,
            parent,
            speed,
            altitude,
            path,
            origin_s: PITCH - CORNER_RADIUS_M,
            shared,
        }
    }

    fn start_s(&self, offset: f64) -> f64 {
        self.origin_s + offset
    }

    /// The most times one shared side is flown from end to end when starting at
    /// `offset` and flying `length`.
    fn shared_passes(&self, offset: f64, length: f64) -> usize {
        let (a, b) = (self.start_s(offset), self.start_s(offset) + length);
        let mut per_side = std::collections::BTreeMap::new();
        for &(side, s, len) in &self.shared {
            if s >= a && s + len <= b {
                *per_side.entry(side).or_insert(0) += 1;
            }
        }
        per_side.into_values().max().unwrap_or(0)
    }

    fn position(&self, offset: f64, t: f64) -> Point3<f64> {
        let s = self.start_s(offset) + self.speed * t;
        let (p, _) = self.path.sample(s).unwrap_or((Point2::origin(), 0.0));
        let s = s.clamp(0.0, self.path.length());
        Point3::new(p.x, p.y, self.altitude.at(s))
    }

    fn route(&self, offset: f64) -> Route {
        Route {
            role: FlightRole::Patrol {
                sector: self.sector,
                parent: self.parent,
            },
            path: self.path.clone(),
            start_s: self.start_s(offset),
            speed: self.speed,
            altitude: self.altitude,
        }
    }
}

/// How well a start point fits the drones already placed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Fit {
    safe: bool,
    meets_parent: bool,
    /// A side shared with another chosen sector is flown twice (or none is shared).
    twice: bool,
    apart_at_takeoff: bool,
    /// The longest time in range with the parent, in samples.
    with_parent: usize,
    meetings: usize,
}

/// Meetings between two tracks: how many (in range at least [`MIN_MEETING_S`], after
/// take-off and apart again before the end), the longest time in range (samples), whether they start in range, and
/// whether they stay apart.
struct Meetings {
    count: usize,
    longest: usize,
    at_takeoff: bool,
    safe: bool,
}

fn meetings(a: &[Point3<f64>], b: &[Point3<f64>], range: f64) -> Meetings {
    let min_samples = (MIN_MEETING_S / SAMPLE_S).ceil() as usize;
    let (mut count, mut run, mut safe, mut longest) = (0, 0, true, 0);
    let close: Vec<bool> = a
        .iter()
        .zip(b)
        .map(|(p, q)| {
            let d = (p - q).norm();
            safe &= d >= MIN_SEPARATION_M;
            d <= range
        })
        .collect();
    let at_takeoff = close.first().copied().unwrap_or(false);
    for (k, &c) in close.iter().enumerate() {
        if c {
            run += 1;
        }
        let ends = !c || k + 1 == close.len();
        if ends && run > 0 {
            // A meeting starts after take-off and ends before landing: they meet and part.
            let started_at_takeoff = at_takeoff && run == k + usize::from(c);
            if !started_at_takeoff && !c {
                count += usize::from(run >= min_samples);
                longest = longest.max(run);
            }
            run = 0;
        }
    }
    Meetings {
        count,
        longest,
        at_takeoff,
        safe,
    }
}

/// Plans every drone's patrol (see the module docs), deterministically from the seed.
pub(crate) fn plan_sectors(world: &World, config: &FlightConfig) -> Vec<Route> {
    let mut rng = SplitMix64::new(config.seed ^ 0x5EC7_0125_EED0_0002);
    let n = config.robots;
    let duration = config.frames.saturating_sub(1) as f64 / config.rate_hz;
    let speeds: Vec<f64> = (0..n)
        .map(|_| config.speed_mps * (1.0 + SPEED_SPREAD * rng.unit()))
        .collect();
    let slowest = speeds.iter().copied().fold(f64::INFINITY, f64::min) * duration;
    let fits = |size: &&(i32, i32)| Grid::new(**size).count() >= n;
    let size = SIZES
        .iter()
        .filter(fits)
        .find(|s| Sector::lap_m(&Grid::new(**s).sector(0, false)) * MIN_LAPS <= slowest)
        .or_else(|| SIZES.iter().rev().find(fits))
        .copied()
        .unwrap_or((1, 1));
    let lots = Lots::new(world);
    let mut layout = None;
    for grid in Grid::all_of(size).iter().filter(|g| g.count() >= n) {
        let (score, candidate) = choose_layout(grid, n, &lots, &mut rng);
        if layout.as_ref().is_none_or(|(best, _)| score > *best) {
            layout = Some((score, candidate));
        }
    }
    let Some((_, layout)) = layout else {
        return Vec::new();
    };
    let swing = MAX_ALTITUDE_SWING_M.min(0.25 * (config.max_altitude_m - config.min_altitude_m));
    let altitudes: Vec<Altitude> = (0..n)
        .map(|_| Altitude {
            base: rng.range(config.min_altitude_m + swing, config.max_altitude_m - swing),
            swing,
            phase: rng.range(0.0, std::f64::consts::TAU),
        })
        .collect();
    let patrols: Vec<Patrol> = layout
        .sectors
        .iter()
        .enumerate()
        .map(|(r, sector)| {
            let shared: Vec<(Node, Node)> = layout
                .sectors
                .iter()
                .filter(|o| *o != sector)
                .flat_map(|o| shared_sides(sector, o))
                .collect();
            Patrol::new(
                *sector,
                layout.parents[r],
                speeds[r],
                altitudes[r],
                speeds[r] * duration + PITCH,
                &shared,
            )
        })
        .collect();
    let samples: Vec<f64> = (0..=(duration / SAMPLE_S).floor() as usize)
        .map(|k| k as f64 * SAMPLE_S)
        .collect();
    // Start points every few metres along the loop.
    let offsets = |p: &Patrol| -> Vec<f64> {
        (0..(p.sector.lap_m() / OFFSET_STEP_M) as usize)
            .map(|k| k as f64 * OFFSET_STEP_M)
            .collect()
    };
    let mut best: Option<((usize, usize, usize), Vec<f64>)> = None;
    for _ in 0..ROOT_TRIES {
        let mut chosen: Vec<f64> = Vec::with_capacity(n);
        let mut tracks: Vec<Vec<Point3<f64>>> = Vec::with_capacity(n);
        let (mut met_parent, mut twice, mut met) = (0, 0, 0);
        for p in &patrols {
            let candidates = offsets(p);
            let mut scored: Vec<(Fit, f64, Vec<Point3<f64>>)> = candidates
                .iter()
                .map(|&o| {
                    let track: Vec<Point3<f64>> =
                        samples.iter().map(|&t| p.position(o, t)).collect();
                    let mut fit = Fit {
                        safe: true,
                        meets_parent: p.parent.is_none(),
                        twice: p.shared.is_empty() || p.shared_passes(o, p.speed * duration) >= 2,
                        apart_at_takeoff: true,
                        meetings: 0,
                        with_parent: 0,
                    };
                    for (q, other) in tracks.iter().enumerate() {
                        let m = meetings(&track, other, config.radio_range_m);
                        fit.safe &= m.safe;
                        fit.apart_at_takeoff &= !m.at_takeoff;
                        fit.meetings += m.count;
                        if p.parent == Some(q) {
                            fit.meets_parent = m.count > 0;
                            fit.with_parent = m.longest;
                        }
                    }
                    (fit, o, track)
                })
                .collect();
            let top = scored.iter().map(|s| s.0).max();
            scored.retain(|s| Some(s.0) == top);
            let (fit, offset, track) = scored.swap_remove(rng.below(scored.len().max(1)));
            met_parent += usize::from(fit.meets_parent);
            twice += usize::from(fit.twice);
            met += fit.meetings;
            chosen.push(offset);
            tracks.push(track);
        }
        let score = (met_parent.min(twice), met_parent + twice, met);
        if best.as_ref().is_none_or(|b| score > b.0) {
            best = Some((score, chosen));
        }
        if best.as_ref().is_some_and(|b| b.0 .0 == n) {
            break;
        }
    }
    let offsets = best.map(|b| b.1).unwrap_or_default();
    patrols
        .iter()
        .zip(offsets)
        .map(|(p, o)| p.route(o))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbouring_sectors_share_one_side_in_the_same_direction() {
        let grid = Grid::new((2, 2));
        for flip in [false, true] {
            for a in 0..grid.count() {
                for b in 0..grid.count() {
                    let (sa, sb) = (grid.sector(a, flip), grid.sector(b, flip));
                    let shared = shared_sides(&sa, &sb).len();
                    let expected = if a == b {
                        4
                    } else {
                        usize::from(grid.neighbours(a).contains(&b))
                    };
                    assert_eq!(shared, expected, "{sa} and {sb}");
                }
            }
        }
        let s = grid.sector(4, false);
        assert_eq!(s.lap_nodes().len(), 8);
        let path = Path::through(&[s.lap_nodes(), s.lap_nodes(), vec![s.lap_nodes()[0]]].concat());
        // Two laps from corner to corner: seven corners rounded (the first and the last
        // are the path's ends), one fewer than two laps' eight.
        let cut = (2.0 - std::f64::consts::FRAC_PI_2) * CORNER_RADIUS_M;
        assert!((path.length() - (2.0 * s.lap_m() + cut)).abs() < 1e-9);
    }
}
