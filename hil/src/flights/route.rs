//! The town's street grid and smooth, constant-speed paths along it.
//!
//! Street centre lines run along the lot boundaries of [`World::town`](crate::World::town),
//! so a path on them stays `STREET_WIDTH / 2 + SIDEWALK_WIDTH` (7 m) clear of every
//! building at any height. Corners are circular arcs tangent to both streets: heading and
//! position are continuous, and at constant speed the acceleration is bounded by
//! `v² / CORNER_RADIUS_M` and the yaw rate by `v / CORNER_RADIUS_M`.

use nalgebra::{Point2, Vector2};

use crate::town::{LOTS, TOWN_SIZE};

/// Lot pitch (metres): the distance between neighbouring intersections.
pub(crate) const PITCH: f64 = TOWN_SIZE / LOTS as f64;
const ORIGIN: f64 = -0.5 * TOWN_SIZE;

/// Radius of the arc that rounds a 90° corner (metres). Its midpoint cuts the corner by
/// `R (1 - 1/√2)` ≈ 2.3 m, well inside the 7 m of street and sidewalk.
pub const CORNER_RADIUS_M: f64 = 8.0;

/// A street intersection by lattice indices, each in `0..=LOTS`.
pub(crate) type Node = (i32, i32);

/// The four street directions as lattice steps, counter-clockwise from east.
pub(crate) const STEPS: [Node; 4] = [(1, 0), (0, 1), (-1, 0), (0, -1)];

pub(crate) fn node_position(n: Node) -> Point2<f64> {
    Point2::new(ORIGIN + PITCH * n.0 as f64, ORIGIN + PITCH * n.1 as f64)
}

pub(crate) fn on_grid(n: Node) -> bool {
    let range = 0..=LOTS as i32;
    range.contains(&n.0) && range.contains(&n.1)
}

pub(crate) fn add(n: Node, step: Node) -> Node {
    (n.0 + step.0, n.1 + step.1)
}

pub(crate) fn sub(a: Node, b: Node) -> Node {
    (a.0 - b.0, a.1 - b.1)
}

/// The lot (lattice cell) containing a point of the ground.
pub(crate) fn lot_of(x: f64, y: f64) -> Node {
    (
        ((x - ORIGIN) / PITCH).floor() as i32,
        ((y - ORIGIN) / PITCH).floor() as i32,
    )
}

#[derive(Debug, Clone, PartialEq)]
enum Piece {
    Line {
        from: Point2<f64>,
        dir: Vector2<f64>,
    },
    /// `turn` is +1 for a left (counter-clockwise) turn, −1 for a right turn.
    Arc {
        centre: Point2<f64>,
        start_angle: f64,
        turn: f64,
    },
}

/// A planar path parametrized by arc length.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Path {
    /// Each piece with the arc length where it starts.
    pieces: Vec<(f64, Piece)>,
    length: f64,
}

impl Path {
    /// The path through consecutive neighbouring intersections, corners rounded. A
    /// reversal (which the planner never makes) is left as a sharp turn on the spot.
    pub(crate) fn through(nodes: &[Node]) -> Path {
        let points: Vec<Point2<f64>> = nodes.iter().map(|&n| node_position(n)).collect();
        let mut path = Path {
            pieces: Vec::new(),
            length: 0.0,
        };
        let Some(&first) = points.first() else {
            return path;
        };
        let mut cursor = first;
        for k in 1..points.len().saturating_sub(1) {
            let (Some(d_in), Some(d_out)) = (
                (points[k] - points[k - 1]).try_normalize(1e-9),
                (points[k + 1] - points[k]).try_normalize(1e-9),
            ) else {
                continue;
            };
            let cross = d_in.x * d_out.y - d_in.y * d_out.x;
            if cross.abs() < 0.5 {
                continue; // straight on (or a reversal): no arc
            }
            let turn = cross.signum();
            let a = points[k] - d_in * CORNER_RADIUS_M;
            path.push_line(cursor, a);
            let left = Vector2::new(-d_in.y, d_in.x);
            let centre = a + left * (turn * CORNER_RADIUS_M);
            let r = a - centre;
            path.pieces.push((
                path.length,
                Piece::Arc {
                    centre,
                    start_angle: r.y.atan2(r.x),
                    turn,
                },
            ));
            path.length += CORNER_RADIUS_M * std::f64::consts::FRAC_PI_2;
            cursor = points[k] + d_out * CORNER_RADIUS_M;
        }
        if let Some(&last) = points.last() {
            path.push_line(cursor, last);
        }
        path
    }

    fn push_line(&mut self, from: Point2<f64>, to: Point2<f64>) {
        let d = to - from;
        let length = d.norm();
        if length < 1e-9 {
            return;
        }
        self.pieces.push((
            self.length,
            Piece::Line {
                from,
                dir: d / length,
            },
        ));
        self.length += length;
    }

    pub(crate) fn length(&self) -> f64 {
        self.length
    }

    /// The straight pieces: (arc length where each starts, its length, start point, unit
    /// direction). A straight run through several intersections is one piece.
    pub(crate) fn straight_pieces(&self) -> Vec<(f64, f64, Point2<f64>, Vector2<f64>)> {
        let mut out = Vec::new();
        for (k, (start, piece)) in self.pieces.iter().enumerate() {
            if let Piece::Line { from, dir } = piece {
                let end = self.pieces.get(k + 1).map_or(self.length, |p| p.0);
                out.push((*start, end - start, *from, *dir));
            }
        }
        out
    }

    /// Position and heading (radians from +x, counter-clockwise) at arc length `s`,
    /// clamped to the path; `None` for an empty path.
    pub(crate) fn sample(&self, s: f64) -> Option<(Point2<f64>, f64)> {
        let s = s.clamp(0.0, self.length);
        let index = self.pieces.partition_point(|(start, _)| *start <= s);
        let (start, piece) = self.pieces.get(index.checked_sub(1)?)?;
        let along = s - start;
        Some(match piece {
            Piece::Line { from, dir } => (from + dir * along, dir.y.atan2(dir.x)),
            Piece::Arc {
                centre,
                start_angle,
                turn,
            } => {
                let angle = start_angle + turn * along / CORNER_RADIUS_M;
                let p = centre + Vector2::new(angle.cos(), angle.sin()) * CORNER_RADIUS_M;
                (p, angle + turn * std::f64::consts::FRAC_PI_2)
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corner_path_is_continuous_and_shorter_than_the_legs() {
        let path = Path::through(&[(1, 1), (2, 1), (2, 2)]);
        let cut = 2.0 * CORNER_RADIUS_M - CORNER_RADIUS_M * std::f64::consts::FRAC_PI_2;
        assert!((path.length() - (2.0 * PITCH - cut)).abs() < 1e-9);
        let mut previous = path.sample(0.0).unwrap();
        let mut s = 0.0;
        while s < path.length() {
            s += 0.05;
            let next = path.sample(s).unwrap();
            assert!((next.0 - previous.0).norm() <= 0.05 + 1e-9);
            assert!((next.1 - previous.1).abs() < 0.05 / CORNER_RADIUS_M + 1e-9);
            previous = next;
        }
        let (end, heading) = path.sample(path.length()).unwrap();
        assert!((end - node_position((2, 2))).norm() < 1e-9);
        assert!((heading - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
    }
}
