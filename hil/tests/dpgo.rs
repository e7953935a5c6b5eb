//! The distributed back-end on teams with interior poses: DOOR-SLAM's KITTI 00 split made
//! from the developer set's single-robot KITTI 00 graph (`doorslam sim split`), where each
//! robot's 908 poses condense onto a few dozen separators. The condensed method must end
//! at the centralized optimum there, not near it; and `converged` must come from the
//! team's solver.
//!
//! Data: `shared/data/pose_graphs/dpgo/kitti_00.g2o` beside the repository (or
//! `$DOORSLAM_DATA`).

use std::path::PathBuf;

use doorslam_backend::distributed::runner::{run, run_over, RunOptions, RunReport};
use doorslam_backend::distributed::{AgentOptions, Method};
use doorslam_backend::{read_g2o, PoseGraph, UnknownTags};
use doorslam_geometry::SE3;
use doorslam_hil::dpgo::{split_into_team, LinkOptions, SessionLink};

fn data() -> PathBuf {
    std::env::var_os("DOORSLAM_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"))
}

/// KITTI 00 (4541 poses, 136 loop closures across the blocks) as five robots.
fn kitti_split() -> PoseGraph<SE3> {
    let path = data().join("pose_graphs/dpgo/kitti_00.g2o");
    let file =
        read_g2o(&path, UnknownTags::Error).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    split_into_team(&file.graph, 5).unwrap()
}

fn play(agent: AgentOptions) -> RunReport {
    let r = run(
        &kitti_split(),
        &RunOptions {
            agent,
            ..RunOptions::default()
        },
    )
    .unwrap();
    println!(
        "converged {} ({}), rounds {}, χ² gap {:.3e}, ATE to centralized {:.4} m, bytes {} / {} centralized",
        r.converged, r.stop_reason, r.iterations, r.chi2_gap, r.ate_to_centralized, r.bytes, r.bytes_centralized
    );
    r
}

/// Measured (2026-12-02): χ² gap 4.1e-6, ATE to the centralized estimate 2.3 mm, bytes
/// 0.18 of centralized. Condensed once at the odometry (the scheme before), the same run
/// ends 5.8e-5 above the optimum and 0.145 m from it: the bounds (5x and 4x the measured)
/// fail without relinearizing.
#[test]
fn a_team_with_interior_poses_ends_at_the_centralized_optimum() {
    let r = play(AgentOptions::default());
    assert!(r.converged, "{}", r.stop_reason);
    assert!(r.chi2_gap.abs() <= 2e-5, "χ² gap {:.3e}", r.chi2_gap);
    assert!(r.ate_to_centralized <= 0.01, "ATE {}", r.ate_to_centralized);
    assert!(r.bytes as f64 <= 0.25 * r.bytes_centralized as f64);
}

#[test]
fn a_solver_stopped_on_its_iteration_limit_is_not_converged() {
    let mut agent = AgentOptions::default();
    agent.solver.max_iterations = 1;
    let r = play(agent);
    assert!(!r.converged);
    assert_eq!(r.stop_reason, "max_iterations");
}

/// DGS's linear stages over the team link: every robot solves at once on estimates a round
/// old (block Jacobi). With full steps two robots tied by closures swap places every
/// round (c and d by ~350 m on this split) and the second stage makes no progress; half
/// steps (`async_gamma`, the default over the link) meet in the middle. Measured
/// (2026-12-06): 100 rounds after the last robot left the rotation stage, χ² fell from
/// 4.8e6 to 6.5e3 (÷ 740) with half steps and from 4.1e6 to 1.9e6 (÷ 2) with full ones.
#[test]
fn dgs_over_the_team_link_does_not_swap_robots_every_round() {
    let graph = kitti_split();
    // χ² when every robot is in the second stage, and 100 rounds later.
    let progress = |async_gamma: f64, damp_on_reversal: bool| -> (f64, f64) {
        let options = RunOptions {
            agent: AgentOptions {
                method: Method::Dgs,
                link_delivers: true,
                async_gamma,
                damp_on_reversal,
                // The second stage runs its 100 rounds, whatever its change.
                max_stage: std::time::Duration::from_secs(1000),
                ..AgentOptions::default()
            },
            max_rounds: 160,
            trace_every: Some(1),
            ..RunOptions::default()
        };
        let mut link = SessionLink::new(LinkOptions::default());
        let r = run_over(&graph, &options, Some(&mut link)).unwrap();
        // Past the rotation stage: in the pose stage, or already refining.
        let in_pose = |t: &&doorslam_backend::distributed::runner::TracePoint| {
            !t.stages.contains_key("rotation") && !t.stages.is_empty()
        };
        let start = r
            .trace
            .iter()
            .find(in_pose)
            .expect("every robot leaves the rotation stage");
        let end = r
            .trace
            .iter()
            .find(|t| t.round == start.round + 100)
            .expect("100 rounds in the second stage");
        assert!(in_pose(&end), "{:?}", end.stages);
        println!(
            "async γ {async_gamma} (only after a reversal: {damp_on_reversal}): χ² {:.3e} at round {} (all in stage 2), {:.3e} 100 rounds later",
            start.chi2, start.round, end.chi2
        );
        (start.chi2, end.chi2)
    };
    let (start, end) = progress(AgentOptions::default().async_gamma, false);
    assert!(end < start / 100.0, "half steps: {start:.3e} -> {end:.3e}");
    let (start, end) = progress(AgentOptions::default().async_gamma, true);
    assert!(
        end < start / 100.0,
        "half steps once a step reversed: {start:.3e} -> {end:.3e}"
    );
    let (start, end) = progress(1.0, false);
    assert!(
        end > start / 10.0,
        "full steps no longer swap: {start:.3e} -> {end:.3e}"
    );
}

/// distributed_mapper's 9-robot team (every pose a separator): DGS over the team link for
/// 500 rounds. Half steps on every step (`damp_on_reversal` false, the default) slow a
/// team where no two robots swap; damped only once a step of the stage reversed the one
/// before it, the robots keep full steps until they overshoot. Measured (2026-12-06,
/// `doorslam dpgo example_9robots/*.g2o --method dgs [--damp-on-reversal]`): χ² gap
/// 0.851 % against 0.332 % (converged at round 479). Not the default: on the held-out
/// 16- and 25-robot teams it ends further off (BENCHMARKS.md, "Damped only after a
/// reversal").
#[test]
fn dgs_damped_only_after_a_reversal_keeps_full_steps_on_example_9robots() {
    let dir = data().join("multi_robot/distributed_mapper/example_9robots");
    let files: Vec<PathBuf> = (0..9).map(|r| dir.join(format!("{r}.g2o"))).collect();
    let (graph, _) = doorslam_backend::g2o::merge_g2o_files(
        &files,
        doorslam_backend::g2o::ReadOptions {
            unknown: UnknownTags::Error,
            information: Default::default(),
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    let gap = |damp_on_reversal: bool| -> f64 {
        let options = RunOptions {
            agent: AgentOptions {
                method: Method::Dgs,
                link_delivers: true,
                damp_on_reversal,
                ..AgentOptions::default()
            },
            max_rounds: 500,
            ..RunOptions::default()
        };
        let mut link = SessionLink::new(LinkOptions::default());
        let r = run_over(&graph, &options, Some(&mut link)).unwrap();
        println!(
            "only after a reversal {damp_on_reversal}: {} rounds, χ² gap {:.3e} ({})",
            r.iterations, r.chi2_gap, r.stop_reason
        );
        r.chi2_gap
    };
    let (always, after_reversal) = (gap(false), gap(true));
    assert!(
        after_reversal < 0.6 * always,
        "damped only after a reversal {after_reversal:.3e}, always {always:.3e}"
    );
}
