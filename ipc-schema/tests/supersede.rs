//! A state message waiting to be sent absorbs a newer one ([`Body::supersede`]): the peer,
//! given the merged message alone, ends as after both in order.

use std::collections::BTreeMap;
use std::sync::Arc;

use doorslam_geometry::information::{matrix_from_upper, upper_from_diagonal};
use doorslam_geometry::{key, SE3};
use doorslam_ipc::wire::{
    Body, CompactPose, Estimate, GraphEdge, Information, PoseEstimate, PoseEstimates, Route,
    SeparatorGraph, Stage,
};
use proptest::prelude::*;

/// A graph as its receiver holds it: the edges of each key pair.
type Held = BTreeMap<(u64, u64), Vec<GraphEdge>>;

/// The receiver's rule (`SeparatorGraph`'s documentation): a whole graph replaces; an
/// update of the version held drops the pairs it removes or rewrites, then adds its edges.
fn apply(held: &Held, g: &SeparatorGraph) -> Held {
    let mut out = if g.base == 0 {
        Held::new()
    } else {
        held.clone()
    };
    for p in &g.removed {
        out.remove(p);
    }
    for e in &g.edges {
        out.remove(&(e.key_a, e.key_b));
    }
    for e in &g.edges {
        out.entry((e.key_a, e.key_b)).or_default().push(e.clone());
    }
    out
}

fn edge(a: u64, b: u64, x: f64) -> GraphEdge {
    let info =
        Information::from_matrix(&matrix_from_upper(&upper_from_diagonal([1.0; 6]))).unwrap();
    GraphEdge {
        key_a: key::symbol(1, a).unwrap(),
        key_b: key::symbol(1, b).unwrap(),
        relative: CompactPose::quantize(&SE3::translation(x, 0.0, 0.0)).unwrap(),
        information: Arc::new(info),
    }
}

/// An update: pairs removed, and pairs rewritten or added with 1-2 edges each.
type Update = (Vec<(u64, u64)>, Vec<(u64, u64, u8)>);

/// An update of `held`: some pairs removed, some rewritten or added (1-2 edges each).
fn arb_update() -> impl Strategy<Value = Update> {
    (
        prop::collection::vec((0u64..6, 0u64..6), 0..4),
        prop::collection::vec((0u64..6, 0u64..6, 1u8..3), 0..5),
    )
}

fn graph(version: u64, base: u64, u: &Update) -> SeparatorGraph {
    let k = |i| key::symbol(1, i).unwrap();
    let mut edges = Vec::new();
    let mut seen = std::collections::BTreeSet::new();
    for &(a, b, n) in &u.1 {
        if a == b || !seen.insert((a, b)) {
            continue;
        }
        for m in 0..n {
            edges.push(edge(a, b, version as f64 + f64::from(m) * 0.5));
        }
    }
    let removed = if base == 0 {
        Vec::new()
    } else {
        u.0.iter()
            .filter(|(a, b)| a != b)
            .map(|&(a, b)| (k(a), k(b)))
            .collect()
    };
    SeparatorGraph {
        origin: 1,
        version,
        base,
        removed,
        edges,
    }
}

proptest! {
    #[test]
    fn a_composed_graph_update_is_both_updates(
        start in arb_update(), first in arb_update(), second in arb_update(), whole_first in any::<bool>()
    ) {
        let g0 = graph(1, 0, &start);
        let held = apply(&Held::new(), &g0);
        let d1 = graph(2, if whole_first { 0 } else { 1 }, &first);
        let d2 = graph(3, 2, &second);
        let want = apply(&apply(&held, &d1), &d2);
        let mut merged = Body::SeparatorGraph(d1.clone());
        prop_assert!(merged.supersede(Body::SeparatorGraph(d2.clone())).is_ok());
        let Body::SeparatorGraph(m) = &merged else { unreachable!() };
        prop_assert_eq!((m.base, m.version), (d1.base, 3));
        prop_assert_eq!(apply(&held, m), want);
        // What travels is a valid message.
        let bytes = doorslam_ipc::wire::Message::new(
            doorslam_ipc::wire::Header {
                sender: doorslam_ipc::wire::RobotId::new("b").unwrap(),
                epoch: 1,
                sequence: 0,
            },
            merged.clone(),
        )
        .encode();
        prop_assert!(bytes.is_ok(), "{bytes:?}");
    }
}

fn estimates(anchor: u8, keys: &[(u64, f64)]) -> Body {
    Body::PoseEstimates(PoseEstimates {
        optimization: 1,
        round: 1,
        stage: Stage::Refine,
        flags: 0,
        anchor,
        estimates: keys
            .iter()
            .map(|&(i, x)| PoseEstimate {
                key: key::symbol(2, i).unwrap(),
                value: Estimate::Pose(
                    CompactPose::quantize(&SE3::translation(x, 0.0, 0.0)).unwrap(),
                ),
            })
            .collect(),
    })
}

#[test]
fn estimates_merge_per_key_within_a_frame_and_a_new_frame_replaces() {
    let mut a = estimates(0, &[(1, 1.0), (4, 4.0)]);
    a.supersede(estimates(0, &[(4, 5.0), (7, 7.0)])).unwrap();
    assert_eq!(a, estimates(0, &[(1, 1.0), (4, 5.0), (7, 7.0)]));
    a.supersede(estimates(1, &[(2, 2.0)])).unwrap();
    assert_eq!(a, estimates(1, &[(2, 2.0)]));
    // Another robot's estimates are another slot; a route is another kind.
    let other = Body::PoseEstimates(PoseEstimates {
        estimates: vec![PoseEstimate {
            key: key::symbol(3, 0).unwrap(),
            value: Estimate::Pose(CompactPose::quantize(&SE3::identity()).unwrap()),
        }],
        ..match estimates(1, &[]) {
            Body::PoseEstimates(p) => p,
            _ => unreachable!(),
        }
    });
    assert!(a.supersede(other).is_err());
    let route = Body::Route(Route {
        path: vec![0, 2],
        subtree: 0,
        session: 1,
    });
    assert!(a.supersede(route.clone()).is_err());
    let mut r = route;
    let newer = Body::Route(Route {
        path: vec![1, 2],
        subtree: 4,
        session: 2,
    });
    r.supersede(newer.clone()).unwrap();
    assert_eq!(r, newer);
    // A graph update of a version other than the one waiting cannot be merged.
    let mut g = Body::SeparatorGraph(graph(5, 0, &(vec![], vec![(0, 1, 1)])));
    assert!(g
        .supersede(Body::SeparatorGraph(graph(
            7,
            6,
            &(vec![], vec![(1, 2, 1)])
        )))
        .is_err());
    // Stream kinds have no slot.
    assert_eq!(
        Body::Hello(doorslam_ipc::wire::Hello {
            robot: 0,
            heard: None,
            base: 0
        })
        .slot(),
        None
    );
}
