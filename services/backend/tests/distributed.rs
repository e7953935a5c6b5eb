//! The distributed back-end: agents played in-process over an emulated link reach the
//! centralized optimum (both methods), under message loss, with a robot joining late and
//! one leaving and returning; malformed and stale messages change nothing.
//!
//! Data: `shared/data/multi_robot/distributed_mapper` beside the repository (or
//! `$DOORSLAM_DATA`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use doorslam_backend::distributed::runner::{run, RunOptions, RunReport};
use doorslam_backend::distributed::{Agent, AgentOptions, DpgoError, Method};
use doorslam_backend::{key, read_g2o, Graph, PoseGraph, UnknownTags};
use doorslam_geometry::information::{matrix_from_upper, upper_from_diagonal};
use doorslam_geometry::{LieGroup, SE3};
use doorslam_ipc::wire::{
    Body, CompactPose, Estimate, Header, Message, PoseEstimate, PoseEstimates, RobotId, Stage,
};

fn data() -> PathBuf {
    std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
}

/// The per-robot files of a distributed-mapper example, merged (closures written in both
/// files kept once).
fn team(name: &str, robots: usize) -> PoseGraph<SE3> {
    let dir = data().join("multi_robot/distributed_mapper").join(name);
    let mut merged = PoseGraph::<SE3>::new();
    let mut seen = BTreeSet::new();
    for r in 0..robots {
        let path = dir.join(format!("{r}.g2o"));
        let file = read_g2o(&path, UnknownTags::Error)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let Graph::Se3(g) = file.graph else {
            panic!("{}: not 3-D", path.display())
        };
        for (idx, (&k, p)) in g.keys().iter().zip(g.poses()).enumerate() {
            if file.has_vertex[idx] || merged.index_of(k).is_none() {
                merged.add_pose(k, *p);
            }
        }
        for e in g.edges() {
            let (a, b) = (g.keys()[e.i], g.keys()[e.j]);
            if seen.insert((a, b)) {
                let (i, j) = (merged.index_of(a).unwrap(), merged.index_of(b).unwrap());
                merged.add_edge(i, j, e.measured, e.information).unwrap();
            }
        }
    }
    merged
}

fn options(method: Method) -> RunOptions {
    RunOptions {
        agent: AgentOptions {
            method,
            ..AgentOptions::default()
        },
        ..RunOptions::default()
    }
}

fn assert_near_optimum(what: &str, r: &RunReport, gap: f64) {
    println!("{what}: {r:?}");
    assert!(
        r.converged,
        "{what}: not converged in {} rounds",
        r.iterations
    );
    assert!(
        r.chi2_gap.abs() <= gap,
        "{what}: χ² {} vs centralized {} (gap {:.4} %)",
        r.distributed_chi2,
        r.centralized_chi2,
        100.0 * r.chi2_gap
    );
}

#[test]
fn four_robots_reach_the_centralized_optimum() {
    let g = team("example_4robots", 4);
    let condensed = run(&g, &options(Method::Condensed)).unwrap();
    assert_near_optimum("condensed", &condensed, 1e-4);
    assert!(condensed.ate_to_centralized < 1e-3, "{condensed:?}");
    assert!(condensed.iterations <= 10, "{condensed:?}");
    // The paper's method gets there too, in many more rounds and bytes.
    let dgs = run(&g, &options(Method::Dgs)).unwrap();
    assert_near_optimum("dgs", &dgs, 0.01);
    assert!(dgs.iterations > condensed.iterations && dgs.bytes > condensed.bytes);
}

#[test]
fn thirty_percent_message_loss_still_converges_there() {
    let g = team("example_4robots", 4);
    for method in [Method::Condensed, Method::Dgs] {
        let r = run(
            &g,
            &RunOptions {
                drop: 0.3,
                seed: 7,
                ..options(method)
            },
        )
        .unwrap();
        assert!(r.dropped > 0 && r.resent > 0, "{r:?}");
        if method == Method::Condensed {
            assert_near_optimum("condensed with 30 % loss", &r, 1e-4);
        } else {
            // DGS keeps creeping towards the optimum: within 1 % in the round budget,
            // though its stopping test (every neighbour's converged flag) does not settle.
            println!("dgs with 30 % loss: {r:?}");
            assert!(r.chi2_gap.abs() <= 0.01, "{r:?}");
        }
    }
}

#[test]
fn a_robot_joins_late_and_another_leaves_and_returns() {
    let g = team("example_4robots", 4);
    for method in [Method::Condensed, Method::Dgs] {
        let r = run(
            &g,
            &RunOptions {
                join_at: BTreeMap::from([(2, 8)]),
                outage: BTreeMap::from([(1, 3..30)]),
                ..options(method)
            },
        )
        .unwrap();
        assert!(r.iterations >= 30, "{r:?}");
        assert_near_optimum(
            &format!("{method:?} with a late join and an outage"),
            &r,
            0.01,
        );
    }
}

#[test]
fn nine_robots_condensed() {
    let g = team("example_9robots", 9);
    let r = run(&g, &options(Method::Condensed)).unwrap();
    assert_near_optimum("9 robots", &r, 1e-4);
}

/// Two robots' agents sharing one closure a1 — b0.
fn pair(method: Method) -> (Agent, Agent) {
    let info = matrix_from_upper(&upper_from_diagonal([1e4, 1e4, 1e4, 100.0, 100.0, 100.0]));
    let step = SE3::exp(&doorslam_geometry::Tangent::from_row_slice(&[
        0.0, 0.0, 0.1, 1.0, 0.0, 0.0,
    ]));
    let opts = AgentOptions {
        method,
        ..AgentOptions::default()
    };
    let mut agents = Vec::new();
    for r in 0..2u8 {
        let mut a = Agent::new(r, RobotId::new(&format!("r{r}")).unwrap(), 1, opts.clone());
        let mut x = SE3::identity();
        for i in 0..3 {
            a.add_pose(key::symbol(r, i).unwrap(), x).unwrap();
            x = x.compose(&step);
        }
        for i in 0..2 {
            let (k0, k1) = (key::symbol(r, i).unwrap(), key::symbol(r, i + 1).unwrap());
            a.add_odometry(k0, k1, step, info).unwrap();
        }
        agents.push(a);
    }
    let (a1, b0) = (key::symbol(0, 1).unwrap(), key::symbol(1, 0).unwrap());
    for a in &mut agents {
        a.add_closure(a1, b0, step, info).unwrap();
        a.set_present(1 - a.robot(), true);
    }
    let b = agents.pop().unwrap();
    let a = agents.pop().unwrap();
    (a, b)
}

fn estimates(a: &Agent) -> Vec<(u64, [f64; 7])> {
    a.estimate()
        .map(|(k, x)| (k, doorslam_geometry::pose_to_array(x)))
        .collect()
}

fn from_b(sequence: u64, key: u64, pose: SE3) -> Message {
    Message::new(
        Header {
            sender: RobotId::new("r1").unwrap(),
            epoch: 1,
            sequence,
        },
        Body::PoseEstimates(PoseEstimates {
            optimization: 1,
            round: 0,
            stage: Stage::Pose,
            flags: 0,
            anchor: 0,
            estimates: vec![PoseEstimate {
                key,
                value: Estimate::Pose(CompactPose::quantize(&pose).unwrap()),
            }],
        }),
    )
}

#[test]
fn malformed_stale_and_out_of_order_messages_change_nothing() {
    let (mut a, mut b) = pair(Method::Dgs);
    for _ in 0..30 {
        a.step().unwrap();
        for m in a.messages_for(1).unwrap() {
            b.receive(0, &m).unwrap();
        }
        b.step().unwrap();
        for m in b.messages_for(0).unwrap() {
            a.receive(1, &m).unwrap();
        }
    }
    let before = estimates(&a);
    // An estimate of a pose that shares no closure with robot a: refused.
    let b2 = key::symbol(1, 2).unwrap();
    let far = SE3::exp(&doorslam_geometry::Tangent::from_row_slice(&[
        0.0, 0.0, 0.0, 100.0, 0.0, 0.0,
    ]));
    let e = a.receive(1, &from_b(1000, b2, far)).unwrap_err();
    assert!(matches!(e, DpgoError::BadMessage { from: 1, .. }), "{e}");
    // A message claiming another robot's poses, from robot b: refused.
    let a0 = key::symbol(0, 0).unwrap();
    assert!(a.receive(1, &from_b(1001, a0, far)).is_err());
    // A stale message (a sequence older than what was applied): ignored.
    let b0 = key::symbol(1, 0).unwrap();
    assert!(!a.receive(1, &from_b(0, b0, far)).unwrap());
    // A message from a robot without closures: refused.
    assert!(a.receive(5, &from_b(2000, b0, far)).is_err());
    // A kind the back-end does not use: refused.
    let hello = Message::new(
        Header {
            sender: RobotId::new("r1").unwrap(),
            epoch: 1,
            sequence: 0,
        },
        Body::Hello(doorslam_ipc::wire::Hello { robot: 1 }),
    );
    assert!(a.receive(1, &hello).is_err());
    a.step().unwrap();
    let after = estimates(&a);
    for ((k0, x0), (k1, x1)) in before.iter().zip(&after) {
        assert_eq!(k0, k1);
        for (u, v) in x0.iter().zip(x1) {
            assert!(
                (u - v).abs() < 1e-6,
                "{} moved: {x0:?} -> {x1:?}",
                key::label(*k0)
            );
        }
    }
    assert!(
        a.stats().refused >= 4 && a.stats().ignored_stale >= 1,
        "{:?}",
        a.stats()
    );
}

#[test]
fn poses_out_of_order_or_twice_and_foreign_edges_are_refused_by_name() {
    let mut a = Agent::new(0, RobotId::new("r0").unwrap(), 1, AgentOptions::default());
    let k = |r, i| key::symbol(r, i).unwrap();
    a.add_pose(k(0, 5), SE3::identity()).unwrap();
    let e = a.add_pose(k(0, 3), SE3::identity()).unwrap_err();
    assert!(
        e.to_string().contains("a3") && e.to_string().contains("a5"),
        "{e}"
    );
    assert!(a.add_pose(k(0, 5), SE3::identity()).is_err());
    let e = a.add_pose(k(1, 6), SE3::identity()).unwrap_err();
    assert!(e.to_string().contains("b6"), "{e}");
    let info = matrix_from_upper(&upper_from_diagonal([1.0; 6]));
    let e = a
        .add_closure(k(0, 5), k(0, 6), SE3::identity(), info)
        .unwrap_err();
    assert!(matches!(e, DpgoError::NotInterRobot { .. }), "{e}");
    let mut bad = info;
    bad[(2, 2)] = -1.0;
    assert!(a
        .add_closure(k(0, 5), k(1, 0), SE3::identity(), bad)
        .is_err());
}

#[test]
fn a_malformed_condensed_graph_is_refused() {
    let (mut a, mut b) = pair(Method::Condensed);
    a.step().unwrap();
    b.step().unwrap();
    let mut m = b.messages_for(0).unwrap().pop().expect("b's graph");
    // Claim the graph is robot a's own: refused (and would name edges of robot b).
    if let Body::SeparatorGraph(g) = &mut m.body {
        g.origin = 0;
    }
    assert!(a.receive(1, &m).is_err());
    // The genuine one is taken, and both robots end at the same team estimate.
    for _ in 0..5 {
        for m in b.messages_for(0).unwrap() {
            a.receive(1, &m).unwrap();
        }
        for m in a.messages_for(1).unwrap() {
            b.receive(0, &m).unwrap();
        }
        a.step().unwrap();
        b.step().unwrap();
    }
    assert!(a.converged() && b.converged());
    let b_in_a_frame = {
        let x_a1 = a.estimate().nth(1).map(|(_, x)| *x).unwrap();
        let x_b0 = b.estimate().next().map(|(_, x)| *x).unwrap();
        x_a1.inverse().compose(&x_b0)
    };
    // The closure a1 -> b0 is the only link: the team estimate satisfies it exactly.
    let z = SE3::exp(&doorslam_geometry::Tangent::from_row_slice(&[
        0.0, 0.0, 0.1, 1.0, 0.0, 0.0,
    ]));
    assert!(z.inverse().compose(&b_in_a_frame).log().norm() < 1e-6);
}
