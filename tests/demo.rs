//! Acceptance of the end-to-end demo (issues 22, 31 and 33): `doorslam demo` with a small
//! team at drone speed as separate processes, every robot a host of its own (network
//! namespaces: needs root, as CI runs), and what its report says. One world is rendered
//! and flown twice (`--world`): plainly, then with a kill and random loss. The chaos run
//! (both robots killed, the team's solver first, and random loss) is a test of its own.
//! - every robot ends in the team's frame, its error there bounded (bounds below, from
//!   measured runs), and the team's estimate beats the odometry alone (`team_gain`);
//! - no false (aliased or wrong) closure survives PCM;
//! - the flights are the scenario: every robot re-visits places of the other and its own;
//! - the CPU figures are possible (at most the machine's cores over the run), per process;
//! - the ledgers' bytes match what the team links published;
//! - killing robots' processes mid-run (`--kill b@25`; the chaos run `--kill a@25 --kill
//!   b@40`): each killed robot restarts from its journal and is back in the team's frame,
//!   no false closure is kept, `--drop 0.3` loses about the asked share of the packets
//!   between robots, and the summary (`kills[]`, `drop`, the timeline) and report.md list
//!   every fault.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

/// The test's flights: 2 robots, 60 s each at 5 m/s (the default speed).
const ROBOTS: usize = 2;
const DURATION_S: &str = "60";
/// Bounds of every robot's team estimate in the team's frame (metres), and of the team's
/// gain over odometry alone, from runs of this test's configuration with the merged wave-4
/// pieces on 2026-12-02 (`doorslam demo --robots 2 --settle-s 40 --duration-s 60`, then the
/// same world with `--kill b@25 --drop 0.3`, five runs): team frame 0.06-0.094 m for both
/// robots, `team_gain` 1.65 plain and 48-57 after the kill (the restarted robot's odometry
/// is a new segment). The ATE bound is ~5x the largest (run-to-run scatter and VO tuning
/// stay inside it; a lost merge or a false closure costs metres); the gain bound is the
/// claim itself: the team beats odometry alone.
const ATE_BOUND_M: f64 = 0.5;
const KILL_ATE_BOUND_M: f64 = 0.5;
/// The chaos run's kills (robot, flight seconds): the team's solver a first, then b, as in
/// BENCHMARKS' 3-robot chaos run.
const CHAOS_KILLS: [(&str, f64); 2] = [("a", 25.0), ("b", 40.0)];
/// Bound of every robot's error in the team's frame after the chaos run (metres): see
/// BENCHMARKS "The chaos run, repeated" for the measured runs it comes from.
const CHAOS_ATE_BOUND_M: f64 = 0.5;
/// Most seconds at base (the demo stops waiting once the team has converged and is
/// quiet). A robot restarted after a kill may need the meeting at base to merge again.
/// On Zenoh's multicast scouting alone, a team-link session under 30 % loss took 12-48 s
/// to form (the kill run that failed in CI and here on 2026-12-05: b in range again for
/// 17 s in flight with no session, the session 29.5 s into the base, too late for a 40 s
/// settle); with the roster's addresses dialled too (the demo's `connect`), 1.4-2.8 s,
/// and both fault runs settled 6-8 s into the base. The faulty runs keep 90 s for the
/// tail.
const SETTLE_S: &str = "40";
const FAULT_SETTLE_S: &str = "90";
const MIN_TEAM_GAIN: f64 = 1.0;
/// Random loss asked for in the second run, and how far the measured share may be from
/// it (thousands of packets: the binomial spread is ~1 %).
const DROP: f64 = 0.3;
const DROP_TOLERANCE: f64 = 0.05;

/// One demo at a time: each is a team of processes sized for the machine (its CPU
/// figures are checked against the cores); two at once on 2 cores (the chaos run beside
/// the kill run, in CI on 2026-12-05) add a load no robot of either run was sized for.
static ONE_DEMO_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// A test's run folders: removed when the test passes, kept (and named on stderr) when it
/// fails, so that a failed run's logs, status files and estimates can be looked at.
struct RunDir(Option<tempfile::TempDir>);

impl RunDir {
    fn new() -> Self {
        Self(Some(tempfile::tempdir().unwrap()))
    }

    fn path(&self) -> &Path {
        self.0.as_ref().map(|d| d.path()).unwrap()
    }
}

impl Drop for RunDir {
    fn drop(&mut self) {
        if std::thread::panicking() {
            if let Some(dir) = self.0.take() {
                eprintln!(
                    "the failed test's run folders are kept: {}",
                    dir.keep().display()
                );
            }
        }
    }
}

/// Runs `doorslam demo` with the test's team, at most `settle_s` at base, and `extra`.
fn demo(out: &Path, settle_s: &str, extra: &[&str]) -> Value {
    assert!(
        unsafe { libc::geteuid() } == 0,
        "this test needs root: every robot of the demo is a network namespace (run the tests as root, as CI does)"
    );
    let robots = ROBOTS.to_string();
    let run = Command::new(env!("CARGO_BIN_EXE_doorslam"))
        .args([
            "demo",
            "--robots",
            &robots,
            "--settle-s",
            settle_s,
            "--json",
            "--out",
        ])
        .arg(out)
        .args(extra)
        .env("RUST_LOG", "info,zenoh=warn")
        .output()
        .expect("doorslam demo runs");
    let logs = |r: &str| std::fs::read_to_string(out.join(r).join("robot.log")).unwrap_or_default();
    assert!(
        run.status.success(),
        "demo failed: {}\n--- a ---\n{}\n--- b ---\n{}",
        String::from_utf8_lossy(&run.stderr),
        logs("a"),
        logs("b")
    );
    let summary: Value = serde_json::from_slice(&run.stdout).expect("summary on stdout");
    for file in [
        "report.md",
        "summary.json",
        "trajectories.png",
        "trajectories.svg",
        "error.png",
        "bytes.svg",
        "run.mcap",
    ] {
        assert!(
            out.join(file).is_file(),
            "{file} missing from the report folder"
        );
    }
    // The run record, read by decoders that are not ours: every robot's last team path
    // is its team_estimate.tum (when the set-up's venv has them).
    let python = doorslam_ros2::reference_python(&["mcap", "mcap_ros2"]);
    if let Ok(python) = &python {
        let check = std::process::Command::new(python)
            .arg(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/tests/ros2/check_mcap.py"
            ))
            .arg(out.join("run.mcap"))
            .arg(out)
            .output()
            .unwrap();
        assert!(
            check.status.success(),
            "run.mcap: {}{}",
            String::from_utf8_lossy(&check.stdout),
            String::from_utf8_lossy(&check.stderr)
        );
    } else if let Err(why) = &python {
        println!("run.mcap not decoded: {why}");
    }
    // Today's fields stay, the new ones are there.
    for field in [
        "robots",
        "frames",
        "mode",
        "source",
        "per_robot",
        "team_ate_m",
        "centralized_ate_m",
        "converged_at_base",
        "closures",
        "bandwidth",
        "timeline",
        "durations",
        "plots",
        "team_gain",
        "drop",
        "kill",
        "realtime",
        "cpu",
        "scenario",
        "security",
    ] {
        assert!(summary.get(field).is_some(), "summary.json lacks {field}");
    }
    summary
}

/// Bytes each robot's team link handed to Zenoh (status.json) equal the payload its
/// ledger counts as sent (for robots that ran once: a restarted link's counter starts
/// again while its ledger continues).
fn ledgers_match_published(out: &Path, robots: &[&str]) {
    for &r in robots {
        let status: Value = serde_json::from_str(
            &std::fs::read_to_string(out.join(r).join("status.json")).unwrap(),
        )
        .unwrap();
        let ledger =
            doorslam_team::ledger::LedgerFile::read(&out.join(r).join("ledger.json")).unwrap();
        let sent: u64 = ledger
            .traffic
            .iter()
            .filter(|t| t.direction == doorslam_team::ledger::Direction::Sent)
            .map(|t| t.counts.payload_bytes)
            .sum();
        // Both counts run over every start of the link (a killed robot's, or a team
        // service `up` restarted): the link's own count continues from the ledger's file.
        let failures = doorslam_hil::demo::report::service_failures(&out.join(r).join("robot.log"));
        assert_eq!(
            status["published_bytes"].as_u64().unwrap(),
            sent,
            "robot {r}: the ledger must count exactly what was published (link starts {}, failures {failures:?})",
            status["link_starts"]
        );
        assert_eq!(ledger.link.published_bytes, sent, "robot {r}");
        assert!(ledger.link.starts >= 1, "robot {r}");
    }
}

/// Every robot in the team's frame within `bound`, the team better than odometry alone
/// by at least `MIN_TEAM_GAIN`, no false closure kept.
fn one_map(s: &Value, bound: f64) {
    for r in ["a", "b"] {
        let x = &s["per_robot"][r];
        assert!(x["keyframes"].as_u64().unwrap() > 10, "{r}: {x}");
        assert_eq!(
            x["in_team_frame"], true,
            "{r} is not in the team's frame: {x}"
        );
        let ate = x["ate_team_frame_m"].as_f64().unwrap_or(f64::INFINITY);
        assert!(ate < bound, "{r}: ATE in the team frame {ate} m: {x}");
    }
    assert_eq!(s["robots_in_team_frame"], ROBOTS);
    let gain = s["team_gain"].as_f64().unwrap_or(0.0);
    assert!(gain >= MIN_TEAM_GAIN, "team_gain {gain}");
    let c = &s["closures"];
    assert!(
        c["true_accepted"].as_u64().unwrap() > 0,
        "no true closure kept: {c}"
    );
    assert_eq!(c["false_accepted"], 0, "a false closure survived PCM: {c}");
}

/// CPU per robot and process is measured and possible: above zero, at most the machine's
/// cores over the run's wall time.
fn honest_cpu(s: &Value) {
    let d = &s["durations"];
    let cpu = d["robots_cpu_s"].as_f64().unwrap();
    let cores = s["cpu"]["cores"].as_f64().unwrap();
    let wall = d["flight_s"].as_f64().unwrap() + d["settle_s"].as_f64().unwrap() + 30.0;
    assert!(
        cpu > 0.0 && cpu <= cores * wall,
        "robots_cpu_s {cpu} on {cores} cores in about {wall} s"
    );
    for r in ["a", "b"] {
        let x = &s["cpu"]["per_robot"][r];
        assert!(x["total_s"].as_f64().unwrap() > 0.0, "{r}: {x}");
        assert!(
            x["per_process"]["frontend"].as_f64().unwrap() > 0.0,
            "{r}: {x}"
        );
        let rt = &s["realtime"]["per_robot"][r];
        assert!(rt["camera_published"].as_u64().unwrap() > 0, "{r}: {rt}");
        assert!(rt["vo_frames"].as_u64().unwrap() > 0, "{r}: {rt}");
    }
    // The verdict says what `kept_up` says (a run on a machine too small says so).
    let verdict = s["realtime"]["verdict"].as_str().unwrap();
    assert_eq!(
        verdict.starts_with("real time:"),
        s["realtime"]["kept_up"] == true,
        "{verdict}"
    );
    assert!(
        verdict.starts_with("real time:") || verdict.starts_with("NOT real time"),
        "{verdict}"
    );
}

#[test]
fn two_robots_build_one_map_and_a_killed_robot_rejoins_on_a_lossy_radio() {
    let _one = ONE_DEMO_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = RunDir::new();
    let out = dir.path().join("run");
    let s = demo(&out, SETTLE_S, &["--duration-s", DURATION_S]);
    assert_eq!(s["mode"], "netns");
    assert!(s["drop"].is_null() && s["kill"].is_null());
    one_map(&s, ATE_BOUND_M);
    honest_cpu(&s);
    // The scenario: each robot flies over places the other saw before, and its own.
    let sc = &s["scenario"];
    assert_eq!(sc["plan"], "sectors");
    assert!(
        sc["revisits"]["a"]["b"].as_u64().unwrap() + sc["revisits"]["b"]["a"].as_u64().unwrap()
            >= 2,
        "{sc}"
    );
    for r in ["a", "b"] {
        assert!(sc["revisits"][r][r].as_u64().unwrap() >= 1, "{sc}");
        assert!(s["per_robot"][r]["speed_mps"].as_f64().unwrap() >= 4.9);
    }
    assert!(sc["meetings_in_flight"].as_u64().unwrap() >= 1, "{sc}");
    ledgers_match_published(&out, &["a", "b"]);
    // A healthy run: no service failed or panicked, every team link started once.
    for r in ["a", "b"] {
        let x = &s["per_robot"][r];
        assert_eq!(
            x["service_failures"],
            serde_json::json!([]),
            "robot {r}: {x}"
        );
        assert_eq!(x["team_link_starts"], 1, "robot {r}: {x}");
    }
    // Secure by default: the robots met over mutual TLS with the access control, on the
    // team's certificates the demo issued (the closures above went over it); each robot
    // dials the others' addresses as well as scouting for them (a lossy radio's meetings).
    assert_eq!(s["security"]["tls"], true, "{}", s["security"]);
    assert!(out.join("certs/ca.pem").is_file());
    for r in ["a", "b"] {
        let toml = std::fs::read_to_string(out.join(r).join("robot.toml")).unwrap();
        assert!(
            toml.contains("[team.tls]")
                && toml.contains("listen = [\"tls/")
                && toml.contains("connect = [\"tls/"),
            "robot {r}: {toml}"
        );
    }
    // The report folder is what `doorslam bw --json` reads.
    let bw = Command::new(env!("CARGO_BIN_EXE_doorslam"))
        .args(["bw", "--json"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(bw.status.success());
    let bw: Value = serde_json::from_slice(&bw.stdout).unwrap();
    assert!(bw["per_kind"]["descriptor"]["count"].as_u64().unwrap() > 0);

    // The same world again, robot b killed mid-flight, 30 % of the packets lost.
    let again = dir.path().join("kill");
    let world = out.join("world");
    let drop = DROP.to_string();
    let s = demo(
        &again,
        FAULT_SETTLE_S,
        &[
            "--world",
            world.to_str().unwrap(),
            "--kill",
            "b@25",
            "--drop",
            &drop,
        ],
    );
    faults_survived(&again, &s, &[("b", 25.0)], KILL_ATE_BOUND_M);
    ledgers_match_published(&again, &["a", "b"]);
}

/// The chaos run of issue #33: both robots killed mid-flight, the team's solver (a, the
/// lowest id) first, each restarted, 30 % of the packets lost. Four causes of failure were
/// found in repeated runs and mended (BENCHMARKS, "Why a robot sat beside the team" and
/// "The chaos run in CI"): the settle ended with estimates still on the radio; a kill lost
/// the odometry edge into a keyframe; a restarted robot refused the solver's route that
/// came before its closure with the solver; a meeting at base cut after a second counted
/// as the team's meeting. In CI since 2026-12-05, after 4 of 4 runs with every mend.
#[test]
fn two_robots_keep_one_map_through_a_chaos_run() {
    let _one = ONE_DEMO_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = RunDir::new();
    let out = dir.path().join("chaos");
    let drop = DROP.to_string();
    let kills: Vec<String> = CHAOS_KILLS
        .iter()
        .map(|(r, t)| format!("{r}@{t}"))
        .collect();
    let s = demo(
        &out,
        FAULT_SETTLE_S,
        &[
            "--duration-s",
            DURATION_S,
            "--kill",
            &kills[0],
            "--kill",
            &kills[1],
            "--drop",
            &drop,
        ],
    );
    faults_survived(&out, &s, &CHAOS_KILLS, CHAOS_ATE_BOUND_M);
    ledgers_match_published(&out, &["a", "b"]);
}

/// A faulty run's summary and report against the `kills` asked (robot, flight seconds):
/// every fault listed, every killed robot restarted from its journal and back in the
/// team's frame, the asked share of packets lost, and the map kept (`one_map`: error in
/// the team frame below `bound`, no false closure kept).
fn faults_survived(out: &Path, s: &Value, kills_asked: &[(&str, f64)], bound: f64) {
    // The figures first, so a failed run says them too.
    for r in ["a", "b"] {
        let x = &s["per_robot"][r];
        println!(
            "{r}: team frame {} (ATE {} m; own alignment {} m), anchor {}, converged {}, starts {}, team link starts {}, service failures {}, present at end {}, presence mended {}, unknown_peer drops {}",
            x["in_team_frame"],
            x["ate_team_frame_m"],
            x["ate_team_m"],
            x["anchor"],
            x["converged"],
            x["starts"],
            x["team_link_starts"],
            x["service_failures"],
            x["present_at_end"],
            x["presence"],
            x["unknown_peer_drops"]
        );
    }
    println!(
        "converged at base {} after {} s at base",
        s["converged_at_base"], s["durations"]["settle_s"]
    );
    for e in s["timeline"].as_array().unwrap() {
        if e["event"]
            .as_str()
            .is_some_and(|e| e.starts_with("at base"))
        {
            println!("{} s: {}", e["t_s"], e["event"]);
        }
    }
    let timeline = s["timeline"].as_array().unwrap();
    let events_of = |robot: &str, what: &str| {
        timeline
            .iter()
            .filter(|e| {
                e["event"].as_str().unwrap_or("").starts_with(what)
                    && e["robots"]
                        .as_array()
                        .is_some_and(|r| r.len() == 1 && r[0] == robot)
            })
            .count()
    };
    let kills = s["kills"].as_array().unwrap();
    assert_eq!(kills.len(), kills_asked.len(), "kills: {kills:?}");
    assert_eq!(s["kill"], kills[0], "kill is the first of kills");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    for ((robot, at_s), k) in kills_asked.iter().zip(kills) {
        assert_eq!(k["robot"], *robot, "{k}");
        assert_eq!(k["at_s"], *at_s, "{k}");
        assert_eq!(k["in_team_frame"], true, "{k}");
        assert_eq!(events_of(robot, "killed"), 1, "{robot}: {timeline:?}");
        assert_eq!(events_of(robot, "restarted"), 1, "{robot}: {timeline:?}");
        assert_eq!(s["per_robot"][robot]["starts"], 2, "{robot}");
        // The restarted robot recovered its journal.
        let backend: Value = serde_json::from_str(
            &std::fs::read_to_string(out.join(robot).join("backend.json")).unwrap(),
        )
        .unwrap();
        assert!(
            backend["report"]["recovered_keyframes"].as_u64().unwrap() > 0,
            "{robot}: {backend}"
        );
        assert!(
            report.contains(&format!("`--kill {robot}@{at_s}`")),
            "report.md does not list the kill of {robot}"
        );
    }
    let d = &s["drop"];
    let (packets, dropped) = (
        d["packets"].as_u64().unwrap(),
        d["dropped"].as_u64().unwrap(),
    );
    let share = dropped as f64 / packets.max(1) as f64;
    assert!(
        packets > 100 && (share - DROP).abs() < DROP_TOLERANCE,
        "asked to drop {DROP}, dropped {dropped} of {packets}: {d}"
    );
    assert!(report.contains(&format!("`--drop {DROP}`")), "report.md");
    one_map(s, bound);
    let c = &s["closures"];
    println!(
        "faults {kills_asked:?}: team-frame ATE {} m (a {} m, b {} m), closures true kept {} / rejected {}, false kept {}, dropped {dropped} of {packets}",
        s["team_ate_m"],
        s["per_robot"]["a"]["ate_team_frame_m"],
        s["per_robot"]["b"]["ate_team_frame_m"],
        c["true_accepted"],
        c["true_rejected"],
        c["false_accepted"]
    );
}

#[test]
fn bad_demo_flags_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let run = |args: &[&str]| {
        let r = Command::new(env!("CARGO_BIN_EXE_doorslam"))
            .arg("demo")
            .args(args)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(!r.status.success(), "{args:?} was accepted");
        String::from_utf8_lossy(&r.stderr).into_owned()
    };
    assert!(run(&["--frames", "100", "--duration-s", "10"]).contains("--duration-s"));
    assert!(run(&["--drop", "1.5"]).contains("drop = 1.5"));
    assert!(run(&["--speed-mps", "40"]).contains("speed_mps = 40"));
    let twice = run(&["--kill", "b@10", "--kill", "b@20"]);
    assert!(twice.contains("robot b is killed twice"), "{twice}");
    let missing = dir.path().join("no-world");
    let err = run(&["--world", missing.to_str().unwrap()]);
    assert!(err.contains("no-world"), "{err}");
    // A world with another team size is refused by name.
    let world = dir.path().join("w");
    let sim = Command::new(env!("CARGO_BIN_EXE_doorslam"))
        .args([
            "sim",
            "world",
            "--plan",
            "sectors",
            "--robots",
            "3",
            "--frames",
            "3",
            "--resolution",
            "32x24",
            "--out",
        ])
        .arg(&world)
        .output()
        .unwrap();
    assert!(
        sim.status.success(),
        "{}",
        String::from_utf8_lossy(&sim.stderr)
    );
    let err = run(&["--robots", "2", "--world", world.to_str().unwrap()]);
    assert!(
        err.contains("world.txt") && err.contains("3 robots"),
        "{err}"
    );
    // Bad events in a world are named with their line.
    std::fs::write(
        world.join("events.csv"),
        "time_s,event,robot_a,robot_b\n1.0,enter,a,q\n",
    )
    .unwrap();
    let err = run(&["--robots", "3", "--world", world.to_str().unwrap()]);
    assert!(
        err.contains("events.csv") && err.contains("line 2"),
        "{err}"
    );
}
