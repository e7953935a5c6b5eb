//! Ground-truth inter-robot closure candidates of a team flight.
//!
//! - **overlap**: two drones' cameras within [`OVERLAP_RADIUS_M`] of each other with
//!   optical axes less than [`OVERLAP_MAX_ANGLE_DEG`] apart — their views share most of
//!   the scene, a true loop closure;
//! - **aliased**: two drones see *different* copies `A`, `A'` of one repeated design from
//!   the same relative viewpoint (the same overlap test, with each pose expressed relative
//!   to its copy), while not overlapping in the world — what place recognition will
//!   propose and what geometric verification may even accept: false closures.
//!
//! A building counts as seen when at least [`SEEN_FRACTION`] of a coarse grid of pixel
//! rays hits it within [`SEEN_MAX_DEPTH_M`] (so occlusion is accounted for).
//! For each pair of robots a < b and each frame of a, the closest matching frame of b is
//! reported, once per kind, so the lists stay proportional to the frame count.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Translation3, Vector3};
use rayon::prelude::*;

use crate::camera::StereoCamera;
use crate::geometry::Ray;
use crate::world::{Primitive, World};

use super::Flight;

/// Largest camera distance of a true overlap (metres).
pub const OVERLAP_RADIUS_M: f64 = 10.0;
/// Largest angle between the optical axes of a true overlap (degrees).
pub const OVERLAP_MAX_ANGLE_DEG: f64 = 45.0;
/// Fraction of the sample rays that must hit a building for it to count as seen.
pub const SEEN_FRACTION: f64 = 0.1;
/// Hits deeper than this do not count: too few pixels to recognize a place by.
pub const SEEN_MAX_DEPTH_M: f64 = 60.0;
/// The coarse ray grid (columns × rows) used to decide what a camera sees.
const SEEN_GRID: (u32, u32) = (16, 12);

/// What a pair of frames of two drones is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum ClosureKind {
    Overlap,
    Aliased,
}

impl ClosureKind {
    pub fn as_str(self) -> &'static str {
        match self {
            ClosureKind::Overlap => "overlap",
            ClosureKind::Aliased => "aliased",
        }
    }
}

/// A frame of robot `robot_a` and a frame of robot `robot_b`: `robot_a < robot_b` between
/// drones, `robot_a == robot_b` for a drone's own ([`own_candidates`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ClosureCandidate {
    pub robot_a: usize,
    pub frame_a: usize,
    pub robot_b: usize,
    pub frame_b: usize,
    pub kind: ClosureKind,
}

/// Groups (two or more) of building indices with the same style and the same size:
/// identical-looking buildings. Sorted by style, each group by index.
pub fn repeated_designs(world: &World) -> Vec<Vec<usize>> {
    let mut by_style: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
    for (index, b) in world.buildings().iter().enumerate() {
        by_style.entry(b.style()).or_default().push(index);
    }
    let size = |i: usize| {
        world
            .buildings()
            .get(i)
            .map(|b| b.bounds().max - b.bounds().min)
    };
    let mut groups = Vec::new();
    for indices in by_style.into_values() {
        // Same style but another size is not an alias; split by size.
        let mut rest = indices;
        while let Some(&first) = rest.first() {
            let (same, other): (Vec<usize>, Vec<usize>) = rest.iter().partition(
                |&&i| matches!((size(i), size(first)), (Some(a), Some(b)) if (a - b).norm() < 1e-9),
            );
            if same.len() >= 2 {
                groups.push(same);
            }
            rest = other;
        }
    }
    groups
}

/// Buildings (indices) that the camera at `pose` sees, with occlusion.
pub fn seen_buildings(world: &World, camera: &StereoCamera, pose: &Isometry3<f64>) -> Vec<usize> {
    let (cols, rows) = SEEN_GRID;
    let mut hits: BTreeMap<usize, usize> = BTreeMap::new();
    let origin = pose.translation.vector.into();
    for r in 0..rows {
        for c in 0..cols {
            let u = (c as f64 + 0.5) * camera.width() as f64 / cols as f64 - 0.5;
            let v = (r as f64 + 0.5) * camera.height() as f64 / rows as f64 - 0.5;
            let ray = Ray {
                origin,
                dir: pose.rotation * camera.ray_camera(u, v),
            };
            // The camera ray has unit z, so `t` is the hit's depth.
            if let Some(hit) = world.cast(&ray).filter(|h| h.t <= SEEN_MAX_DEPTH_M) {
                if let Primitive::Building { index, .. } = hit.surface.primitive {
                    *hits.entry(index).or_default() += 1;
                }
            }
        }
    }
    let needed = SEEN_FRACTION * (cols * rows) as f64;
    hits.into_iter()
        .filter(|&(_, n)| n as f64 >= needed)
        .map(|(i, _)| i)
        .collect()
}

/// Distance (metres) if the two camera poses overlap, `None` otherwise.
pub(crate) fn overlap_distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> Option<f64> {
    let distance = (a.translation.vector - b.translation.vector).norm();
    let (za, zb) = (a.rotation * Vector3::z(), b.rotation * Vector3::z());
    let angle = za.dot(&zb).clamp(-1.0, 1.0).acos();
    (distance <= OVERLAP_RADIUS_M && angle < OVERLAP_MAX_ANGLE_DEG.to_radians()).then_some(distance)
}

/// All overlap and aliased candidates between the drones of a team flight.
pub fn closure_candidates(
    world: &World,
    camera: &StereoCamera,
    flights: &[Flight],
) -> Vec<ClosureCandidate> {
    all_candidates(world, camera, flights).0
}

/// Every drone's candidates with its own earlier frames, at least
/// [`MIN_OWN_GAP_S`](super::MIN_OWN_GAP_S) earlier: `robot_a == robot_b`, `frame_a` the
/// later frame, `frame_b` the earlier one (the closest match, once per kind).
pub fn own_candidates(
    world: &World,
    camera: &StereoCamera,
    flights: &[Flight],
) -> Vec<ClosureCandidate> {
    all_candidates(world, camera, flights).1
}

/// Candidates between drones, and of each drone with itself (one pass over what every
/// frame sees).
pub(crate) fn all_candidates(
    world: &World,
    camera: &StereoCamera,
    flights: &[Flight],
) -> (Vec<ClosureCandidate>, Vec<ClosureCandidate>) {
    let designs = repeated_designs(world);
    let design_of: BTreeMap<usize, usize> = designs
        .iter()
        .enumerate()
        .flat_map(|(d, group)| group.iter().map(move |&b| (b, d)))
        .collect();
    // Per robot and frame: the seen buildings that have identical copies.
    let seen: Vec<Vec<Vec<usize>>> = flights
        .iter()
        .map(|f| {
            f.poses
                .par_iter()
                .map(|p| {
                    let mut s = seen_buildings(world, camera, p);
                    s.retain(|b| design_of.contains_key(b));
                    s
                })
                .collect()
        })
        .collect();
    let pairs = Pairs {
        world,
        designs: &designs,
        design_of: &design_of,
        seen: &seen,
        flights,
    };
    let mut between = Vec::new();
    let mut own = Vec::new();
    for a in 0..flights.len() {
        for b in a + 1..flights.len() {
            between.extend(pairs.candidates(a, b, None));
        }
        own.extend(pairs.candidates(a, a, Some(super::MIN_OWN_GAP_S)));
    }
    between.sort();
    own.sort();
    (between, own)
}

/// What candidate search between two drones shares.
struct Pairs<'a> {
    world: &'a World,
    designs: &'a [Vec<usize>],
    design_of: &'a BTreeMap<usize, usize>,
    /// Per robot and frame: seen buildings that have copies.
    seen: &'a [Vec<Vec<usize>>],
    flights: &'a [Flight],
}

impl Pairs<'_> {
    /// Translation taking building `b`'s corner to the origin: poses relative to a copy.
    fn corner(&self, b: usize) -> Option<Translation3<f64>> {
        self.world
            .buildings()
            .get(b)
            .map(|x| Translation3::from(-x.bounds().min.coords))
    }

    /// For each frame of `a`, the closest matching frame of `b` per kind; with
    /// `earlier_by`, only frames of `b` at least that many seconds earlier (own
    /// candidates, `a == b`).
    fn candidates(&self, a: usize, b: usize, earlier_by: Option<f64>) -> Vec<ClosureCandidate> {
        let (fa, fb) = (&self.flights[a], &self.flights[b]);
        let usable =
            |i: usize, j: usize| earlier_by.is_none_or(|gap| fb.times[j] <= fa.times[i] - gap);
        // Frames of b per building they see, to look aliases up directly.
        let mut frames_seeing: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for (j, s) in self.seen[b].iter().enumerate() {
            for &building in s {
                frames_seeing.entry(building).or_default().push(j);
            }
        }
        let mut out = Vec::new();
        for (i, pa) in fa.poses.iter().enumerate() {
            let closest = |candidates: &mut dyn Iterator<Item = (usize, f64)>| {
                candidates
                    .min_by(|x, y| x.1.total_cmp(&y.1))
                    .map(|(j, _)| j)
            };
            let overlap = closest(
                &mut fb
                    .poses
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| usable(i, *j))
                    .filter_map(|(j, pb)| Some((j, overlap_distance(pa, pb)?))),
            );
            if let Some(j) = overlap {
                out.push(candidate(a, i, b, j, ClosureKind::Overlap));
            }
            let mut aliases = Vec::new();
            for &copy_a in &self.seen[a][i] {
                let Some((design, Some(to_a))) = self
                    .design_of
                    .get(&copy_a)
                    .map(|&d| (d, self.corner(copy_a)))
                else {
                    continue;
                };
                let local_a = to_a * pa;
                for &copy_b in self.designs[design].iter().filter(|&&c| c != copy_a) {
                    let Some(to_b) = self.corner(copy_b) else {
                        continue;
                    };
                    for &j in frames_seeing.get(&copy_b).into_iter().flatten() {
                        let pb = &fb.poses[j];
                        if !usable(i, j) || overlap_distance(pa, pb).is_some() {
                            continue;
                        }
                        if let Some(d) = overlap_distance(&local_a, &(to_b * pb)) {
                            aliases.push((j, d));
                        }
                    }
                }
            }
            if let Some(j) = closest(&mut aliases.into_iter()) {
                out.push(candidate(a, i, b, j, ClosureKind::Aliased));
            }
        }
        out
    }
}

fn candidate(a: usize, i: usize, b: usize, j: usize, kind: ClosureKind) -> ClosureCandidate {
    ClosureCandidate {
        robot_a: a,
        frame_a: i,
        robot_b: b,
        frame_b: j,
        kind,
    }
}
