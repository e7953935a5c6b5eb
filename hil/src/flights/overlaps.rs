//! True overlaps counted from ground truth: how often each drone flies over places another
//! drone saw before, over its own places again, and over places others saw at any time.
//! What the sector plan is built for, and what its test checks for every team size.
//!
//! Two frames overlap as closure candidates do ([`OVERLAP_RADIUS_M`],
//! [`OVERLAP_MAX_ANGLE_DEG`]). A drone's frames that overlap form **stretches**: runs of
//! frames at most [`STRETCH_GAP_S`] apart, one pass over a place.

use std::collections::BTreeMap;

use nalgebra::Isometry3;

use super::closures::overlap_distance;
use super::Flight;
#[cfg(doc)]
use super::{OVERLAP_MAX_ANGLE_DEG, OVERLAP_RADIUS_M};

/// A drone's own earlier frame counts as an earlier visit only this long before
/// (seconds): consecutive frames always overlap.
pub const MIN_OWN_GAP_S: f64 = 20.0;
/// Overlapping frames closer than this in time are one stretch (seconds).
pub const STRETCH_GAP_S: f64 = 2.0;

/// One stretch of `robot`'s flight over places `other` saw before (`other == robot`: its
/// own places, at least [`MIN_OWN_GAP_S`] earlier).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Revisit {
    pub robot: usize,
    pub other: usize,
    pub first_frame: usize,
    pub last_frame: usize,
    /// `other`'s earlier frame nearest to `robot`'s first frame of the stretch.
    pub other_frame: usize,
    /// Flight time of `robot`'s first frame of the stretch (seconds).
    pub time_s: f64,
}

/// Overlap counts of a team flight.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OverlapCounts {
    /// `revisits[r][q]`: stretches of `r`'s flight over places `q` saw before.
    pub revisits: Vec<Vec<usize>>,
    /// Per drone: stretches of its flight over places another drone saw, before or
    /// after (crossings of the others' routes in the same direction), as (the other
    /// drone, flight time of the stretch's first frame), in time order; a stretch over
    /// places of two drones counts for each.
    pub crossings: Vec<Vec<(usize, f64)>>,
    /// Every stretch of `revisits`, by robot, other, time.
    pub stretches: Vec<Revisit>,
}

impl OverlapCounts {
    /// Stretches of `r`'s flight over places other drones saw before.
    pub fn others_revisited(&self, r: usize) -> usize {
        self.revisits.get(r).map_or(0, |row| {
            row.iter()
                .enumerate()
                .filter(|(q, _)| *q != r)
                .map(|x| x.1)
                .sum()
        })
    }

    /// Stretches of `r`'s flight over its own earlier places.
    pub fn own_revisited(&self, r: usize) -> usize {
        self.revisits
            .get(r)
            .and_then(|row| row.get(r))
            .copied()
            .unwrap_or(0)
    }
}

/// A cube of side [`OVERLAP_RADIUS_M`](super::OVERLAP_RADIUS_M).
type Cell = (i64, i64, i64);

fn cell(p: &Isometry3<f64>) -> Cell {
    let v = p.translation.vector / super::OVERLAP_RADIUS_M;
    (v.x.floor() as i64, v.y.floor() as i64, v.z.floor() as i64)
}

/// A cell and its 26 neighbours.
const NEIGHBOURS: [Cell; 27] = {
    let mut n = [(0, 0, 0); 27];
    let mut k = 0;
    while k < 27 {
        n[k] = (
            (k % 3) as i64 - 1,
            ((k / 3) % 3) as i64 - 1,
            (k / 9) as i64 - 1,
        );
        k += 1;
    }
    n
};

/// Groups frames (ascending) into stretches: (first, last).
fn stretches(frames: &[usize], times: &[f64]) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    for &k in frames {
        match out.last_mut() {
            Some(last) if times[k] - times[last.1] <= STRETCH_GAP_S => last.1 = k,
            _ => out.push((k, k)),
        }
    }
    out
}

/// Counts every drone's stretches over places others (and itself) saw.
pub fn overlap_counts(flights: &[Flight]) -> OverlapCounts {
    let tracks: Vec<(&[f64], &[Isometry3<f64>])> = flights
        .iter()
        .map(|f| (f.times.as_slice(), f.poses.as_slice()))
        .collect();
    overlap_counts_of(&tracks)
}

/// [`overlap_counts`] of ground-truth tracks: per drone its frame times (seconds, one
/// clock for all) and left-camera poses (camera-to-world).
pub fn overlap_counts_of(tracks: &[(&[f64], &[Isometry3<f64>])]) -> OverlapCounts {
    struct Track<'a> {
        times: &'a [f64],
        poses: &'a [Isometry3<f64>],
    }
    let flights: Vec<Track> = tracks
        .iter()
        .map(|&(times, poses)| {
            let k = times.len().min(poses.len());
            Track {
                times: &times[..k],
                poses: &poses[..k],
            }
        })
        .collect();
    let n = flights.len();
    let mut counts = OverlapCounts {
        revisits: vec![vec![0; n]; n],
        crossings: vec![Vec::new(); n],
        stretches: Vec::new(),
    };
    for (r, fr) in flights.iter().enumerate() {
        for (q, fq) in flights.iter().enumerate() {
            let mut any_other = Vec::new();
            let gap = if q == r { MIN_OWN_GAP_S } else { 0.0 };
            // q's frames by cell of the overlap radius: a frame's overlaps are in its
            // cell or a neighbouring one.
            let mut cells: BTreeMap<Cell, Vec<usize>> = BTreeMap::new();
            for (j, p) in fq.poses.iter().enumerate() {
                cells.entry(cell(p)).or_default().push(j);
            }
            // Per frame of r: the nearest earlier frame of q over the same place.
            let mut earlier: Vec<(usize, usize)> = Vec::new();
            for (i, (pi, ti)) in fr.poses.iter().zip(fr.times).enumerate() {
                let mut nearest: Option<(f64, usize)> = None;
                let mut any = false;
                let c = cell(pi);
                let near = NEIGHBOURS
                    .iter()
                    .filter_map(|d| cells.get(&(c.0 + d.0, c.1 + d.1, c.2 + d.2)))
                    .flatten();
                for &j in near {
                    let (pj, tj) = (&fq.poses[j], fq.times[j]);
                    if q == r && (ti - tj).abs() < gap {
                        continue;
                    }
                    let Some(d) = overlap_distance(pi, pj) else {
                        continue;
                    };
                    any = true;
                    if tj < ti - gap && nearest.is_none_or(|n| (d, j) < n) {
                        nearest = Some((d, j));
                    }
                }
                if q != r && any {
                    any_other.push(i);
                }
                if let Some((_, j)) = nearest {
                    earlier.push((i, j));
                }
            }
            counts.crossings[r].extend(
                stretches(&any_other, fr.times)
                    .into_iter()
                    .map(|(first, _)| (q, fr.times[first])),
            );
            let frames: Vec<usize> = earlier.iter().map(|e| e.0).collect();
            for (first, last) in stretches(&frames, fr.times) {
                let other_frame = earlier.iter().find(|e| e.0 == first).map_or(0, |e| e.1);
                counts.revisits[r][q] += 1;
                counts.stretches.push(Revisit {
                    robot: r,
                    other: q,
                    first_frame: first,
                    last_frame: last,
                    other_frame,
                    time_s: fr.times[first],
                });
            }
        }
        counts.crossings[r].sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    }
    counts
}
