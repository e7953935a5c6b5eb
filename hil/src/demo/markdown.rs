//! `report.md`: the summary's figures for people, in the order a reader asks: did the
//! team beat each robot alone, on what flights, was the run honest (real time, CPU),
//! what did the closures and the radio do.

use std::fmt::Write as _;

use super::report::{
    ClosureSummary, Summary, ALIAS_FRAMES, OWN_LOOP_MIN_GAP_S, TRUE_ROTATION_DEG,
    TRUE_TRANSLATION_M,
};

fn m(v: Option<f64>) -> String {
    v.map_or("—".into(), |x| format!("{x:.2}"))
}

fn yes(b: bool) -> &'static str {
    if b {
        "yes"
    } else {
        "no"
    }
}

/// The closures table of one kind.
fn closures_table(t: &mut String, c: &ClosureSummary) {
    let _ = writeln!(t, "| | kept | rejected |\n|---|---|---|");
    let _ = writeln!(t, "| true | {} | {} |", c.true_accepted, c.true_rejected);
    let _ = writeln!(t, "| false | {} | {} |", c.false_accepted, c.false_rejected);
    let _ = writeln!(
        t,
        "| of which aliased | {} | {} |\n",
        c.aliased_accepted,
        c.aliased - c.aliased_accepted
    );
}

/// `report.md` of a summary and the bandwidth table.
pub fn report(s: &Summary, bw_table: &str) -> String {
    let mut t = String::new();
    let _ = writeln!(t, "# doorslam demo\n");
    let _ = writeln!(
        t,
        "{} robots, {} frames each, {}; robots as {}. Total {:.0} s (rendering {:.0} s, flight {:.0} s, at base {:.0} s, report {:.1} s).\n",
        s.robots,
        s.frames,
        s.source,
        if s.mode == "netns" {
            "hosts of their own (network namespaces on a bridge, radio range by nftables)"
        } else {
            "processes on the loopback (not root: no namespaces, always in range)"
        },
        s.durations.total_s,
        s.durations.render_s,
        s.durations.flight_s,
        s.durations.settle_s,
        s.durations.report_s,
    );
    let _ = writeln!(
        t,
        "Team link: {}{}.\n",
        s.security.mode,
        if s.security.tls {
            format!(
                " (team CA and robot certificates in `{}`, {} validity; robots {} each admitted only as itself)",
                s.security.certificates.as_deref().unwrap_or("certs/"),
                s.security.validity.as_deref().unwrap_or("dated"),
                s.security.roster.join(", ")
            )
        } else {
            String::new()
        }
    );
    let _ = writeln!(t, "**{}.**\n", s.realtime.verdict);
    if s.cpu.machine_shared == Some(true) {
        let _ = writeln!(
            t,
            "**The machine was shared**: other work used {:.0} of its {:.0} CPU seconds during the flight; timings of this run are not the system's.\n",
            s.cpu.flight_others_s.unwrap_or(0.0),
            s.cpu.flight_wall_s * s.cpu.cores as f64
        );
    }
    let mean_vo = {
        let v: Vec<f64> = s.per_robot.values().filter_map(|x| x.ate_vo_m).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let _ = writeln!(
        t,
        "## What the team bought\n\nTeam gain **{}**: the robots' odometry alone has a mean ATE of {} m, the team's estimate {} m in one frame for {} of {} robots (ATE, RMSE of keyframe positions after one SE(3) alignment for the whole team).\n",
        s.team_gain.map_or("—".into(), |g| format!("{g:.2}")),
        m(mean_vo),
        m(s.team_ate_m),
        s.robots_in_team_frame,
        s.robots
    );
    let _ = writeln!(t, "![trajectories](trajectories.png)\n");

    let sc = &s.scenario;
    let _ = writeln!(t, "## The flights\n");
    let _ = writeln!(
        t,
        "Plan `{}`{}{}. From ground truth: each robot's stretches of flight over places another robot saw before, over its own places again (at least 20 s later), and crossings of the others' routes in the same direction (before or after). The simulator lists {} overlap and {} aliased candidates between robots ({} and {} of robots with themselves); pairs came into radio range {} times during the flight.\n",
        sc.plan,
        sc.speed_mps.map_or(String::new(), |v| format!(", slowest drone {v:.1} m/s")),
        sc.radio_range_m.map_or(String::new(), |v| format!(", radio range {v:.0} m")),
        sc.overlap_candidates,
        sc.aliased_candidates,
        sc.own_overlap_candidates,
        sc.own_aliased_candidates,
        sc.meetings_in_flight
    );
    let _ = writeln!(
        t,
        "| robot | route | distance (m) | speed (m/s) | over others' places | over its own | crossings |\n|---|---|---|---|---|---|---|"
    );
    for (r, x) in &s.per_robot {
        let others: Vec<String> = sc
            .revisits
            .get(r)
            .map(|row| {
                row.iter()
                    .filter(|(q, c)| *q != r && **c > 0)
                    .map(|(q, c)| format!("{q} {c}"))
                    .collect()
            })
            .unwrap_or_default();
        let own = sc
            .revisits
            .get(r)
            .and_then(|row| row.get(r))
            .copied()
            .unwrap_or(0);
        let _ = writeln!(
            t,
            "| {r} | {} | {:.0} | {:.2} | {} | {own} | {} |",
            sc.roles.get(r).map_or("—", String::as_str),
            x.distance_m,
            x.speed_mps,
            if others.is_empty() {
                "—".into()
            } else {
                others.join(", ")
            },
            sc.crossings.get(r).copied().unwrap_or(0)
        );
    }
    let _ = writeln!(t);

    let _ = writeln!(
        t,
        "## Trajectory error (ATE, RMSE of keyframe positions, m)\n"
    );
    let _ = writeln!(
        t,
        "| robot | keyframes | odometry alone | team estimate | team estimate, team frame | in the team frame | centralized oracle, team frame | anchored to | converged |"
    );
    let _ = writeln!(t, "|---|---|---|---|---|---|---|---|---|");
    for (r, x) in &s.per_robot {
        let _ = writeln!(
            t,
            "| {r} | {} | {} | {} | {} | {} | {} | {} | {} |",
            x.keyframes,
            m(x.ate_vo_m),
            m(x.ate_team_m),
            m(x.ate_team_frame_m),
            yes(x.in_team_frame),
            m(x.ate_centralized_m),
            if x.anchored { x.anchor.as_str() } else { "—" },
            yes(x.converged)
        );
    }
    let _ = writeln!(
        t,
        "| team | | {} (mean) | | {} | {} of {} | {} | | {} |\n",
        m(mean_vo),
        m(s.team_ate_m),
        s.robots_in_team_frame,
        s.robots,
        m(s.centralized_ate_m),
        yes(s.converged_at_base)
    );
    let _ = writeln!(
        t,
        "Odometry alone and team estimate: each robot aligned on its own (SE(3)). Team frame: one alignment for every robot the distributed back-end put in the team's frame — what a shared map needs. Oracle: every robot's graph merged, the same PCM, Levenberg-Marquardt.\n"
    );
    let _ = writeln!(t, "![error over time](error.png)\n");

    let c = &s.closures;
    let _ = writeln!(t, "## Loop closures against the simulator's truth\n");
    let _ = writeln!(
        t,
        "{} inter-robot closures verified (PnP-RANSAC): {} true, {} false ({} at aliased look-alikes). PCM inside the distributed back-end kept {} and left out {}.\n",
        c.total, c.true_closures, c.false_closures, c.aliased, c.accepted, c.rejected
    );
    closures_table(&mut t, c);
    let o = &s.own_closures;
    let _ = writeln!(
        t,
        "Each robot with its own earlier keyframes (edges between keyframes at least {OWN_LOOP_MIN_GAP_S} s apart): {} closures, {} true, {} false ({} at aliased look-alikes).\n",
        o.total, o.true_closures, o.false_closures, o.aliased
    );
    if o.total > 0 {
        closures_table(&mut t, o);
    }
    let _ = writeln!(
        t,
        "True: the measurement agrees with the ground-truth relative pose within {TRUE_TRANSLATION_M} m and {TRUE_ROTATION_DEG}°. Aliased: within {ALIAS_FRAMES} frames of a pair `closures.csv` (`revisits.csv`) lists as two copies of one building.\n"
    );

    let _ = writeln!(t, "## Faults\n");
    match &s.drop {
        Some(d) => {
            let _ = writeln!(
                t,
                "- `--drop {}`: every robot dropped each packet from another robot with probability {} (nftables): {} of {} packets lost ({:.1} %).",
                d.probability,
                d.probability,
                d.dropped,
                d.packets,
                100.0 * d.dropped as f64 / d.packets.max(1) as f64
            );
        }
        None => {
            let _ = writeln!(t, "- no random loss between robots (`--drop`)");
        }
    }
    if s.kills.is_empty() {
        let _ = writeln!(t, "- no robot killed (`--kill`)");
    }
    for k in &s.kills {
        let _ = writeln!(
            t,
            "- `--kill {}@{}`: every process of robot {} SIGKILLed at {} s of flight, restarted {} s later; {}.",
            k.robot,
            k.at_s,
            k.robot,
            k.at_s,
            k.restart_after_s,
            if k.in_team_frame {
                "back in the team's frame at the end"
            } else {
                "**not back in the team's frame at the end**"
            }
        );
    }
    // Failures nobody asked for: a service that exited or panicked and was restarted.
    for (r, x) in &s.per_robot {
        for line in &x.service_failures {
            let _ = writeln!(t, "- **robot {r}, not asked for**: `{line}`");
        }
    }
    let _ = writeln!(t);

    let _ = writeln!(t, "## Real time and CPU\n");
    let _ = writeln!(
        t,
        "| robot | frames | camera published | camera skipped | camera late p90 (ms) | VO frames | VO missed | VO ms/frame median / p90 | VO CPU ms/frame | kept up | CPU s | CPU per process (s) |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    let opt = |v: Option<u64>| v.map_or("—".into(), |x| x.to_string());
    for (r, x) in &s.realtime.per_robot {
        let cpu = s.cpu.per_robot.get(r);
        let per: Vec<String> = cpu
            .map(|c| {
                c.per_process
                    .iter()
                    .map(|(p, v)| format!("{p} {v:.1}"))
                    .collect()
            })
            .unwrap_or_default();
        let _ = writeln!(
            t,
            "| {r} | {} | {} | {} | {} | {} | {} | {} / {} | {} | {} | {:.1} | {} |",
            x.frames,
            opt(x.camera_published),
            opt(x.camera_skipped),
            m(x.camera_late_ms_p90),
            opt(x.vo_frames),
            opt(x.vo_missed),
            m(x.vo_ms_median),
            m(x.vo_ms_p90),
            m(x.vo_cpu_ms_median),
            yes(x.kept_up),
            cpu.map_or(0.0, |c| c.total_s),
            per.join(", ")
        );
    }
    let busy = s
        .cpu
        .flight_machine_busy_s
        .map_or("—".into(), |b| format!("{b:.0}"));
    let _ = writeln!(
        t,
        "\nThe robots' processes used {:.0} CPU seconds in all (measured per process: `/proc/<pid>/stat`, exact for robots that stopped normally); rendering used {:.0}. During the {:.0} s of flight the machine's {} cores were busy {busy} CPU seconds: robots {:.0}, the demo {:.0}, other work {}.\n",
        s.cpu.robots_s,
        s.cpu.render_s,
        s.cpu.flight_wall_s,
        s.cpu.cores,
        s.cpu.flight_robots_s,
        s.cpu.flight_demo_s,
        s.cpu
            .flight_others_s
            .map_or("—".into(), |o| format!("{o:.0}"))
    );

    let _ = writeln!(
        t,
        "## Bandwidth (paper Table II layout, `doorslam bw`)\n\n```\n{bw_table}\n```\n"
    );
    let _ = writeln!(t, "![bytes over time](bytes.png)\n");
    let _ = writeln!(
        t,
        "## Timeline\n\n| flight time (s) | event | robots |\n|---|---|---|"
    );
    for e in &s.timeline {
        let _ = writeln!(
            t,
            "| {:.1} | {} | {} |",
            e.t_s,
            e.event,
            e.robots.join(", ")
        );
    }
    let _ = writeln!(
        t,
        "\nFiles: `summary.json` (these figures), `<robot>/` (robot.toml, robot.log, camera.json, frontend.json, ledger.json, status.json, backend.json, odometry.tum, team_estimate.tum, graph.g2o, keyframes.csv, the journal, team.own), `world/` (the rendered flights and their truth; `--world` flies it again). `doorslam bw --json <this folder>` reads the ledgers."
    );
    t
}
