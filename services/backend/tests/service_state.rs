//! The back-end's state machine fed by values, no iceoryx2: bad samples are rejected before
//! they are journaled, duplicates and gaps are handled, edges wait for their keyframes, the
//! journal replays to the same graph, and optimization runs on schedule.

use doorslam_backend::journal::Entry;
use doorslam_backend::service::{BackendState, Outcome};
use doorslam_geometry::information::upper_from_diagonal;
use doorslam_geometry::{pose_from_array, pose_to_array, LieGroup, SE3};
use doorslam_ipc::{Feature, Keyframe, KeyframeSource, OdometryEdge, MAX_KEYFRAME_FEATURES};
use nalgebra::{Translation3, UnitQuaternion};

const ROBOT: u32 = 1;

/// Truth: a gentle arc, one keyframe per metre.
fn truth(id: u64) -> SE3 {
    let t = id as f64;
    SE3::from_parts(
        Translation3::new(t, 0.1 * t * t, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 0.2 * t),
    )
}

fn keyframe(id: u64) -> Keyframe {
    Keyframe {
        robot: ROBOT,
        source: KeyframeSource::VisualOdometry as u32,
        id,
        frame_seq: id * 5,
        stamp_ns: id * 1_000_000,
        // A drifted estimate: the optimizer has work to do.
        pose: pose_to_array(&(truth(id) * SE3::translation(0.05 * id as f64, 0.0, 0.0))),
        n_features: 0,
        reserved: 0,
        features: [Feature::default(); MAX_KEYFRAME_FEATURES],
    }
}

fn edge(from: u64, to: u64) -> OdometryEdge {
    OdometryEdge {
        robot: ROBOT,
        reserved: 0,
        from,
        to,
        stamp_ns: 0,
        relative: pose_to_array(&(truth(from).inverse() * truth(to))),
        information: upper_from_diagonal([1e4, 1e4, 1e4, 1e2, 1e2, 1e2]),
    }
}

fn state() -> BackendState {
    BackendState::new(ROBOT, 3).unwrap()
}

#[test]
fn bad_samples_are_rejected_before_the_journal() {
    let (mut s, mut journal) = (state(), Vec::new());
    assert_eq!(
        s.on_keyframe(&keyframe(0), &mut journal).unwrap(),
        Outcome::Accepted
    );
    let mut nan = keyframe(1);
    nan.pose[2] = f64::NAN;
    let mut zero_q = keyframe(1);
    zero_q.pose[3..].fill(0.0);
    let mut source = keyframe(1);
    source.source = 9;
    let mut other_robot = keyframe(1);
    other_robot.robot = 4;
    let mut huge_id = keyframe(1);
    huge_id.id = 1 << 56;
    for (bad, field) in [
        (nan, "pose"),
        (zero_q, "pose"),
        (source, "source"),
        (other_robot, "robot"),
        (huge_id, "id"),
    ] {
        match s.on_keyframe(&bad, &mut journal).unwrap() {
            Outcome::Rejected(e) => {
                assert_eq!((e.topic, e.field), ("keyframes", field), "{e}");
                assert_eq!(e.robot, bad.robot);
            }
            other => panic!("{field}: {other:?}"),
        }
    }
    assert_eq!(
        s.on_keyframe(&keyframe(1), &mut journal).unwrap(),
        Outcome::Accepted
    );
    let mut indefinite = edge(0, 1);
    indefinite.information[0] = -1.0;
    let mut nan_info = edge(0, 1);
    nan_info.information[7] = f64::NAN;
    let mut self_loop = edge(1, 1);
    self_loop.relative = pose_to_array(&SE3::identity());
    for bad in [indefinite, nan_info, self_loop] {
        assert!(matches!(
            s.on_odometry(&bad, &mut journal).unwrap(),
            Outcome::Rejected(_)
        ));
    }
    assert_eq!(s.report().rejected, 8);
    // Only the two good keyframes reached the journal, and the graph has no edge.
    assert_eq!(journal.len(), 2);
    assert!(s.graph().edges().is_empty());
    assert_eq!(
        s.on_odometry(&edge(0, 1), &mut journal).unwrap(),
        Outcome::Accepted
    );
    assert_eq!(journal.len(), 3);
}

#[test]
fn duplicates_gaps_and_waiting_edges() {
    let (mut s, mut journal) = (state(), Vec::new());
    s.on_keyframe(&keyframe(0), &mut journal).unwrap();
    // The edge to keyframe 1 overtakes it: it waits, then is applied after it.
    assert_eq!(
        s.on_odometry(&edge(0, 1), &mut journal).unwrap(),
        Outcome::Waiting
    );
    assert_eq!(
        s.on_odometry(&edge(0, 1), &mut journal).unwrap(),
        Outcome::Duplicate
    );
    assert_eq!(s.pending(), 1);
    assert_eq!(
        s.on_keyframe(&keyframe(1), &mut journal).unwrap(),
        Outcome::Accepted
    );
    assert_eq!(s.pending(), 0);
    assert!(matches!(journal[2], Entry::Odometry { from: 0, to: 1, .. }));
    // History re-sent after a restart: skipped, not journaled twice.
    assert_eq!(
        s.on_keyframe(&keyframe(1), &mut journal).unwrap(),
        Outcome::Duplicate
    );
    assert_eq!(
        s.on_odometry(&edge(0, 1), &mut journal).unwrap(),
        Outcome::Duplicate
    );
    // Keyframe 2 was lost upstream.
    assert_eq!(
        s.on_keyframe(&keyframe(3), &mut journal).unwrap(),
        Outcome::AcceptedAfterGap {
            expected: 2,
            got: 3
        }
    );
    let r = s.report();
    assert_eq!(
        (r.accepted_keyframes, r.accepted_edges, r.duplicates, r.gaps),
        (3, 1, 3, 1)
    );
    assert_eq!(journal.len(), 4);
}

#[test]
fn optimizes_on_schedule_and_journal_replays_to_the_same_graph() {
    let (mut s, mut journal) = (state(), Vec::new());
    for id in 0..3 {
        s.on_keyframe(&keyframe(id), &mut journal).unwrap();
        if id > 0 {
            s.on_odometry(&edge(id - 1, id), &mut journal).unwrap();
        }
    }
    assert!(
        s.optimization_due(),
        "3 new keyframes with optimize_every = 3"
    );
    let summary = s.optimize().unwrap();
    assert!(summary.final_chi2 < 1e-9 * summary.initial_chi2.max(1.0));
    assert!(!s.optimization_due());
    s.on_keyframe(&keyframe(3), &mut journal).unwrap();
    s.on_odometry(&edge(2, 3), &mut journal).unwrap();
    assert!(!s.optimization_due(), "one new keyframe is not enough");

    // A restarted back-end replays the journal into the same graph.
    let mut replayed = state();
    replayed.replay(&journal);
    assert_eq!(replayed.report().recovered_keyframes, 4);
    assert_eq!(replayed.report().recovered_edges, 3);
    assert_eq!(replayed.graph().keys(), s.graph().keys());
    assert_eq!(replayed.graph().edges().len(), s.graph().edges().len());
    // ... and optimizes it right away (its estimate may be stale).
    assert!(replayed.optimization_due());
    replayed.optimize().unwrap();
    s.optimize().unwrap();
    for (a, b) in replayed.graph().poses().iter().zip(s.graph().poses()) {
        assert!((a.inverse() * b).log().norm() < 1e-6);
    }
    let (id, pose) = replayed.latest_estimate().unwrap();
    assert_eq!(id, 3);
    assert!((pose.inverse() * truth(3)).log().norm() < 1e-3);
}

#[test]
fn a_poisoned_journal_from_an_older_build_is_not_applied() {
    let good = |id: u64| Entry::Keyframe {
        id,
        stamp_ns: 0,
        pose: pose_to_array(&truth(id)),
    };
    let mut nan_edge = Entry::Odometry {
        from: 0,
        to: 1,
        relative: pose_to_array(&(truth(0).inverse() * truth(1))),
        information: upper_from_diagonal([1.0; 6]),
    };
    if let Entry::Odometry { information, .. } = &mut nan_edge {
        information[3] = f64::NAN;
    }
    let zero_quaternion = Entry::Keyframe {
        id: 2,
        stamp_ns: 0,
        pose: [0.0; 7],
    };
    let mut s = state();
    s.replay(&[good(0), good(1), nan_edge, zero_quaternion]);
    let r = s.report();
    assert_eq!(
        (
            r.recovered_keyframes,
            r.recovered_edges,
            r.rejected_from_journal
        ),
        (2, 0, 2)
    );
    assert!(pose_from_array(&pose_to_array(&s.graph().poses()[1])).is_ok());
}

/// A robot flying one lap of a circle (40 keyframes) and 10 more, past its start again:
/// odometry with a small yaw bias (so it drifts), and the truth.
fn lap_truth(id: u64) -> SE3 {
    let a = std::f64::consts::TAU * id as f64 / 40.0;
    SE3::from_parts(
        Translation3::new(10.0 * a.sin(), 10.0 * (1.0 - a.cos()), 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, a),
    )
}

fn lap_step(from: u64) -> SE3 {
    lap_truth(from).inverse()
        * lap_truth(from + 1)
        * SE3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.004),
        )
}

fn lap_information() -> [f64; 21] {
    upper_from_diagonal([1e4, 1e4, 1e4, 1e2, 1e2, 1e2])
}

fn own_loop(a: u64, b: u64, z: SE3) -> doorslam_ipc::LoopClosure {
    doorslam_ipc::LoopClosure {
        robot_a: ROBOT,
        robot_b: ROBOT,
        keyframe_a: a,
        keyframe_b: b,
        relative: pose_to_array(&z),
        information: lap_information(),
        inliers: 60,
        reserved: 0,
    }
}

#[test]
fn own_loop_closures_pass_pcm_into_the_graph_and_undo_the_drift() {
    let (mut s, mut journal) = (state(), Vec::new());
    let mut odometry = SE3::identity();
    for id in 0..50 {
        if id > 0 {
            odometry *= lap_step(id - 1);
        }
        let mut kf = keyframe(id);
        kf.pose = pose_to_array(&odometry);
        s.on_keyframe(&kf, &mut journal).unwrap();
        if id > 0 {
            let mut e = edge(id - 1, id);
            e.relative = pose_to_array(&lap_step(id - 1));
            e.information = lap_information();
            s.on_odometry(&e, &mut journal).unwrap();
        }
    }
    let odometry_error = (lap_truth(49).inverse() * s.graph().poses()[49])
        .translation
        .vector
        .norm();
    // Keyframes 40..=45 see 0..=5 again (true), and 47 "sees" 20 with the pose of 7: a
    // look-alike that verification accepted, consistent with none of the true ones.
    for k in 0..=5u64 {
        let z = lap_truth(40 + k).inverse() * lap_truth(k);
        assert_eq!(
            s.on_closure(&own_loop(40 + k, k, z), &mut journal).unwrap(),
            Outcome::Accepted
        );
    }
    let wrong = lap_truth(47).inverse() * lap_truth(7);
    s.on_closure(&own_loop(47, 20, wrong), &mut journal)
        .unwrap();
    // Again (a resend): a duplicate, not a second candidate.
    assert_eq!(
        s.on_closure(&own_loop(47, 20, wrong), &mut journal)
            .unwrap(),
        Outcome::Duplicate
    );
    let r = s.report();
    assert_eq!((r.intra_closures, r.intra_kept), (7, 6), "{r:?}");
    assert_eq!(r.accepted_closures, 0, "own loops are counted apart");
    let (candidates, in_graph) = s.intra_closures();
    assert_eq!((candidates.len(), in_graph), (7, 6));
    // 49 odometry edges and the 6 kept loops.
    assert_eq!(s.graph().edges().len(), 49 + 6);
    s.optimize().unwrap();
    let optimized_error = (lap_truth(49).inverse() * s.graph().poses()[49])
        .translation
        .vector
        .norm();
    eprintln!(
        "end error: {optimized_error:.4} m with the loops, {odometry_error:.4} m odometry alone"
    );
    // Measured 0.130 m against 1.680 m (ratio 0.08); the bound leaves 3x.
    assert!(
        optimized_error < 0.25 * odometry_error,
        "end error {optimized_error:.3} m with the loops, {odometry_error:.3} m odometry alone"
    );
    // The journal gives a restarted back-end the same graph.
    let mut replayed = state();
    replayed.replay(&journal);
    assert_eq!(replayed.report().intra_kept, 6);
    assert_eq!(replayed.graph().edges().len(), 49 + 6);
    // Without PCM's consistency (a single wrong closure, nothing to check it against), it
    // stays out: a clique of one proves nothing.
    let mut lone = state();
    let mut journal = Vec::new();
    for id in 0..50 {
        lone.on_keyframe(&keyframe(id), &mut journal).unwrap();
        if id > 0 {
            lone.on_odometry(&edge(id - 1, id), &mut journal).unwrap();
        }
    }
    lone.on_closure(&own_loop(47, 20, wrong), &mut journal)
        .unwrap();
    assert_eq!(lone.report().intra_kept, 0);
    assert_eq!(lone.graph().edges().len(), 49);
}

/// A robot circling its lap 26 times with a true closure from every keyframe to the one a
/// lap before (1,000 candidates, all mutually consistent): PCM's window bounds each check,
/// every true closure stays in the graph (frozen kept once it leaves the window), and a
/// wrong one arriving after the window filled is still rejected, then frozen as rejected.
#[test]
fn own_loop_pcm_is_bounded_by_its_window_and_keeps_every_true_closure() {
    const LAP: u64 = 40;
    const WINDOW: usize = 64;
    let mut s = state().with_intra_pcm(0.99, 2, WINDOW).unwrap();
    let mut journal = Vec::new();
    let mut odometry = SE3::identity();
    let (mut slowest, mut total) = (0.0f64, 0.0f64);
    let mut true_closures = 0usize;
    let last = LAP + 1000 + 2 * WINDOW as u64;
    for id in 0..last {
        if id > 0 {
            odometry *= lap_step(id - 1);
        }
        let mut kf = keyframe(id);
        kf.pose = pose_to_array(&odometry);
        s.on_keyframe(&kf, &mut journal).unwrap();
        if id > 0 {
            let mut e = edge(id - 1, id);
            e.relative = pose_to_array(&lap_step(id - 1));
            e.information = lap_information();
            s.on_odometry(&e, &mut journal).unwrap();
        }
        if id < LAP {
            continue;
        }
        let start = std::time::Instant::now();
        let z = lap_truth(id).inverse() * lap_truth(id - LAP);
        assert_eq!(
            s.on_closure(&own_loop(id, id - LAP, z), &mut journal)
                .unwrap(),
            Outcome::Accepted
        );
        true_closures += 1;
        if id == LAP + 1000 {
            // The window is full long since: a look-alike (the place 5 keyframes further
            // on, measured as if it were the one a lap before).
            let wrong = lap_truth(id).inverse() * lap_truth(id - LAP);
            s.on_closure(&own_loop(id, id - LAP + 5, wrong), &mut journal)
                .unwrap();
            let r = s.report();
            assert_eq!(r.intra_kept, true_closures, "{r:?}");
        }
        let dt = start.elapsed().as_secs_f64();
        slowest = slowest.max(dt);
        total += dt;
    }
    let r = s.report();
    eprintln!(
        "{} candidates: slowest check {:.1} ms, mean {:.2} ms; {r:?}",
        r.intra_closures,
        slowest * 1e3,
        total * 1e3 / true_closures as f64
    );
    assert_eq!(r.intra_closures, true_closures + 1);
    assert_eq!(
        r.intra_kept, true_closures,
        "every true closure in the graph: {r:?}"
    );
    assert_eq!(r.intra_retracted, 0, "{r:?}");
    // The wrong one left the window rejected; the window holds the newest candidates.
    assert_eq!(r.intra_frozen_rejected, 1, "{r:?}");
    assert_eq!(r.intra_frozen_kept, true_closures - WINDOW, "{r:?}");
    assert_eq!(s.intra_closures().0.len(), WINDOW);
    assert_eq!(s.graph().edges().len(), (last - 1) as usize + true_closures);
    // Unbounded, a check took seconds after a few hundred candidates (the soak's stall);
    // with the window, measured well under 0.1 s each on this 2-core machine under load:
    // 1 s leaves room for a slow CI host.
    assert!(slowest < 1.0, "slowest check {slowest:.3} s");
    // A restart replays every candidate at once: judged a window at a time, the same ones
    // kept.
    let mut replayed = state().with_intra_pcm(0.99, 2, WINDOW).unwrap();
    let start = std::time::Instant::now();
    replayed.replay(&journal);
    eprintln!("replay: {:.2} s", start.elapsed().as_secs_f64());
    let rr = replayed.report();
    assert_eq!(rr.intra_kept, true_closures, "{rr:?}");
    assert_eq!(rr.intra_frozen_rejected, 1, "{rr:?}");
    assert_eq!(replayed.graph().edges().len(), s.graph().edges().len());
}
