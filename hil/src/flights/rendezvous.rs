//! Rendezvous: when pairs of drones are within radio range of each other.
//!
//! Computed from the ground-truth camera positions at the frame times (every drone
//! records at the same instants), so a radio emulator or a team test can replay exactly
//! when links come and go: per pair, `enter` and `leave` alternate, starting with `enter`
//! (at time 0 if the pair starts in range); a pair still in range at the end has no
//! final `leave`.

use super::Flight;

/// A pair of drones coming into or going out of radio range.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum RangeEventKind {
    Enter,
    Leave,
}

impl RangeEventKind {
    pub fn as_str(self) -> &'static str {
        match self {
            RangeEventKind::Enter => "enter",
            RangeEventKind::Leave => "leave",
        }
    }
}

/// At frame `frame` (time `time_s`), robots `robot_a < robot_b` entered or left range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeEvent {
    pub time_s: f64,
    pub frame: usize,
    pub kind: RangeEventKind,
    pub robot_a: usize,
    pub robot_b: usize,
}

/// Enter/leave events of every pair, in time order (pairs in index order within a frame).
/// A pair is in range at a frame when the cameras are at most `range_m` apart.
pub fn rendezvous_events(flights: &[Flight], range_m: f64) -> Vec<RangeEvent> {
    let frames = flights
        .iter()
        .map(|f| f.poses.len().min(f.times.len()))
        .min()
        .unwrap_or(0);
    let mut in_range = vec![vec![false; flights.len()]; flights.len()];
    let mut events = Vec::new();
    for k in 0..frames {
        for (a, fa) in flights.iter().enumerate() {
            for (b, fb) in flights.iter().enumerate().skip(a + 1) {
                let d = (fa.poses[k].translation.vector - fb.poses[k].translation.vector).norm();
                let now = d <= range_m;
                if now != in_range[a][b] {
                    in_range[a][b] = now;
                    events.push(RangeEvent {
                        time_s: fa.times[k],
                        frame: k,
                        kind: if now {
                            RangeEventKind::Enter
                        } else {
                            RangeEventKind::Leave
                        },
                        robot_a: a,
                        robot_b: b,
                    });
                }
            }
        }
    }
    events
}
