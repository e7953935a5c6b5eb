//! Outlier loop closures injected into a team graph, as DOOR-SLAM's dataset simulation
//! does (lajoiepy/Buzz_SLAM `buzz_slam_dataset.cpp`): between two robots that meet, a
//! closure whose relative translation is uniform in [0, 10] m per axis (the sensor range)
//! and whose rotation has each Euler angle uniform in [−π, π].

use doorslam_geometry::{key, SE3};
use nalgebra::{Translation3, UnitQuaternion};

use super::labels::Labels;
use crate::graph::{EdgeClass, EdgeError, PoseGraph};
use crate::rng::SplitMix64;

/// DOOR-SLAM's `SENSOR_RANGE`: the largest translation of an injected outlier, per axis.
pub const OUTLIER_RANGE_M: f64 = 10.0;

/// A graph that cannot take outliers.
#[derive(Debug, thiserror::Error)]
pub enum InjectError {
    #[error("outlier fraction {0} must be in [0, 1)")]
    Fraction(f64),
    #[error(
        "the graph has no inter-robot loop closure: no robots meet, so no outlier can be placed"
    )]
    NoClosures,
    #[error(transparent)]
    Edge(#[from] EdgeError),
}

/// The graph with outliers added so that they make `fraction` of its inter-robot closures,
/// and the labels of every inter-robot closure (the graph's own taken as inliers). Each
/// outlier joins the robot pair of a closure drawn at random (robots that meet) at random
/// poses of the two, with that closure's information.
pub fn inject_outliers(
    graph: &PoseGraph<SE3>,
    fraction: f64,
    seed: u64,
) -> Result<(PoseGraph<SE3>, Labels), InjectError> {
    if !(0.0..1.0).contains(&fraction) {
        return Err(InjectError::Fraction(fraction));
    }
    let keys = graph.keys();
    let inliers: Vec<usize> = graph
        .edges()
        .iter()
        .enumerate()
        .filter(|(_, e)| graph.edge_class(e) == EdgeClass::InterLoop)
        .map(|(n, _)| n)
        .collect();
    if inliers.is_empty() {
        return Err(InjectError::NoClosures);
    }
    let mut labels = Labels::default();
    for &n in &inliers {
        let e = &graph.edges()[n];
        labels.insert(keys[e.i], keys[e.j], true);
    }
    // Poses of each robot, by index.
    let mut poses: std::collections::BTreeMap<u8, Vec<usize>> = Default::default();
    for (p, k) in keys.iter().enumerate() {
        if let Some(r) = key::robot(*k) {
            poses.entry(r).or_default().push(p);
        }
    }
    let count = (fraction / (1.0 - fraction) * inliers.len() as f64).round() as usize;
    let mut rng = SplitMix64::new(seed);
    let mut out = graph.clone();
    let pi = std::f64::consts::PI;
    for _ in 0..count {
        let e = &graph.edges()[inliers[rng.below(inliers.len())]];
        let (ra, rb) = (key::robot(keys[e.i]), key::robot(keys[e.j]));
        let (Some(pa), Some(pb)) = (
            ra.and_then(|r| poses.get(&r)),
            rb.and_then(|r| poses.get(&r)),
        ) else {
            continue;
        };
        let (i, j) = (pa[rng.below(pa.len())], pb[rng.below(pb.len())]);
        let t = Translation3::new(
            rng.uniform(0.0, OUTLIER_RANGE_M),
            rng.uniform(0.0, OUTLIER_RANGE_M),
            rng.uniform(0.0, OUTLIER_RANGE_M),
        );
        let q = UnitQuaternion::from_euler_angles(
            rng.uniform(-pi, pi),
            rng.uniform(-pi, pi),
            rng.uniform(-pi, pi),
        );
        out.add_edge(i, j, SE3::from_parts(t, q), e.information)?;
        labels.insert(keys[i], keys[j], false);
    }
    Ok((out, labels))
}
