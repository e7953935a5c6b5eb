//! A single-robot pose graph cut into a team, as DOOR-SLAM's KITTI 00 experiment made its
//! five-robot split: robot r owns the r-th block of consecutive poses (its keys `r`, index
//! from 0), the odometry edge between two blocks is dropped (each robot's trajectory starts
//! on its own), and a loop closure whose ends fall in two blocks becomes an inter-robot
//! closure. A planar graph is embedded in 3-D (translation `(x, y, 0)`, rotation about z);
//! the dimensions the plane does not observe get weights from the ones it does (z the
//! weight of y, roll and pitch that of the heading, as the paper's split does), so a 3-D
//! solver sees a well-conditioned problem that stays planar.

use doorslam_backend::{Graph, PoseGraph};
use doorslam_geometry::{key, TangentMatrix, SE3};
use nalgebra::{Isometry2, Isometry3, Translation3, UnitQuaternion, Vector3};

/// Why a graph cannot be split.
#[derive(Debug, thiserror::Error)]
pub enum SplitError {
    #[error("cannot split {poses} poses into {robots} robots (1 to {max} robots, at least 2 poses each)", max = key::MAX_ROBOTS)]
    Robots { poses: usize, robots: usize },
    #[error("the graph already has multi-robot keys (pose {0}): split a single-robot graph")]
    MultiRobot(String),
    #[error(transparent)]
    Key(#[from] doorslam_geometry::KeyError),
    #[error(transparent)]
    Edge(#[from] doorslam_backend::EdgeError),
}

fn embed_pose(p: &Isometry2<f64>) -> SE3 {
    Isometry3::from_parts(
        Translation3::new(p.translation.vector.x, p.translation.vector.y, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), p.rotation.angle()),
    )
}

/// The planar information (rotation first: θ, x, y) in the 3-D tangent (φx, φy, φz, x, y,
/// z): the observed block kept with its correlations, roll and pitch weighted as θ, z as y.
fn embed_information(i: &TangentMatrix) -> TangentMatrix {
    let map = [2usize, 3, 4];
    let mut out = TangentMatrix::zeros();
    for (r, &mr) in map.iter().enumerate() {
        for (c, &mc) in map.iter().enumerate() {
            out[(mr, mc)] = i[(r, c)];
        }
    }
    out[(0, 0)] = i[(0, 0)];
    out[(1, 1)] = i[(0, 0)];
    out[(5, 5)] = i[(2, 2)];
    out
}

/// The team of `robots` robots made of `graph` (poses in key order; the last robot takes
/// the poses left over by the division). Poses keep their values (re-chained per robot by
/// whoever needs an odometry-only start).
pub fn split_into_team(graph: &Graph, robots: usize) -> Result<PoseGraph<SE3>, SplitError> {
    let g3: PoseGraph<SE3> = match graph {
        Graph::Se3(g) => g.clone(),
        Graph::Se2(g) => {
            let mut out = PoseGraph::new();
            for (k, p) in g.keys().iter().zip(g.poses()) {
                out.add_pose(*k, embed_pose(p));
            }
            for e in g.edges() {
                out.add_edge(
                    e.i,
                    e.j,
                    embed_pose(&e.measured),
                    embed_information(&e.information),
                )?;
            }
            out
        }
    };
    let n = g3.len();
    if robots == 0 || robots > usize::from(key::MAX_ROBOTS) || n < 2 * robots {
        return Err(SplitError::Robots { poses: n, robots });
    }
    if let Some(k) = g3.keys().iter().find(|k| key::robot(**k).is_some()) {
        return Err(SplitError::MultiRobot(key::label(*k)));
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&p| g3.keys()[p]);
    let block = n / robots;
    // Rank of each pose in key order → (robot, index).
    let mut rank = vec![0usize; n];
    for (r, &p) in order.iter().enumerate() {
        rank[p] = r;
    }
    let owner = |p: usize| (rank[p] / block).min(robots - 1);
    let mut team = PoseGraph::new();
    let mut node = vec![0usize; n];
    for &p in &order {
        let r = owner(p);
        let k = key::symbol(r as u8, (rank[p] - r * block) as u64)?;
        node[p] = team.add_pose(k, g3.poses()[p]);
    }
    for e in g3.edges() {
        let (ri, rj) = (owner(e.i), owner(e.j));
        // The odometry step from one block into the next: the robots start apart.
        if ri != rj && rank[e.i].abs_diff(rank[e.j]) == 1 {
            continue;
        }
        team.add_edge(node[e.i], node[e.j], e.measured, e.information)?;
    }
    Ok(team)
}

#[cfg(test)]
mod tests {
    use super::*;
    use doorslam_backend::EdgeClass;
    use nalgebra::Isometry2;

    #[test]
    fn blocks_become_robots_and_crossing_loops_closures() {
        let mut g = PoseGraph::<Isometry2<f64>>::new();
        for i in 0..10u64 {
            g.add_pose(
                i,
                Isometry2::new(nalgebra::Vector2::new(i as f64, 0.0), 0.0),
            );
        }
        let mut info = TangentMatrix::zeros();
        info[(0, 0)] = 100.0;
        info[(1, 1)] = 10.0;
        info[(2, 2)] = 20.0;
        info[(1, 2)] = 1.0;
        info[(2, 1)] = 1.0;
        let step = Isometry2::new(nalgebra::Vector2::new(1.0, 0.0), 0.0);
        for i in 0..9 {
            g.add_edge(i, i + 1, step, info).unwrap();
        }
        g.add_edge(8, 1, step, info).unwrap(); // crosses robots 0 and 2
        g.add_edge(2, 0, step, info).unwrap(); // inside robot 0
        let team = split_into_team(&Graph::Se2(g), 3).unwrap();
        assert_eq!(team.len(), 10);
        // Robot c takes the remainder: poses 6..9 are c0..c3.
        assert_eq!(
            team.keys()[9],
            key::symbol(2, 3).unwrap(),
            "{:?}",
            team.keys()
                .iter()
                .map(|k| key::label(*k))
                .collect::<Vec<_>>()
        );
        let classes: Vec<EdgeClass> = team.edges().iter().map(|e| team.edge_class(e)).collect();
        // 9 odometry steps minus 2 between blocks, one inter-robot closure, one own loop.
        assert_eq!(team.edges().len(), 9);
        assert_eq!(
            classes
                .iter()
                .filter(|c| **c == EdgeClass::InterLoop)
                .count(),
            1
        );
        let e = &team.edges()[0];
        assert_eq!(e.information[(2, 2)], 100.0);
        assert_eq!(e.information[(3, 4)], 1.0);
        assert_eq!(e.information[(0, 0)], 100.0);
        assert_eq!(e.information[(5, 5)], 20.0);
        assert!(split_into_team(&Graph::Se3(team.clone()), 2).is_err());
        assert!(matches!(
            split_into_team(&Graph::Se2(PoseGraph::new()), 2),
            Err(SplitError::Robots { .. })
        ));
    }
}
