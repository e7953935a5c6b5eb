//! The on-robot pipeline as separate processes over iceoryx2: camera (dataset replay) ->
//! sim-keyframes -> backend, started by `doorslam up`; and a back-end killed mid-run that
//! resumes from its journal. Each test uses its own robot id (iceoryx2 service names) and
//! temporary folder, and bounds every wait.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use doorslam_ipc::{
    create_node, Feature, Keyframe, KeyframeSource, OdometryEdge, Sender, Topic,
    MAX_KEYFRAME_FEATURES,
};

mod common;
use common::{signal, wait_exit, Guard, LogReader};

const BIN: &str = env!("CARGO_BIN_EXE_doorslam");

/// A KITTI-layout sequence: noise images, times at 100 Hz, poses along a line.
fn write_dataset(dir: &Path, frames: usize) {
    common::write_noise_dataset(dir, frames, 0.01, |k| (0.1 * k as f64, 0.0));
}

/// Keyframe ids and the number of odometry edges in a back-end journal.
fn keyframe_ids(journal: &Path) -> (Vec<u64>, usize) {
    let (ids, edges) = common::journaled(journal);
    (ids, edges.len())
}

/// `robot.toml` in `dir` for one robot: replay of `data` in real time, sim-keyframes every
/// `every` frames, the back-end's state under `dir/state`, and `up` starting all three.
/// Returns it and the path of the back-end's journal.
fn write_robot(dir: &Path, robot: &str, data: &Path, every: u64) -> (PathBuf, PathBuf) {
    let config = dir.join("robot.toml");
    std::fs::write(
        &config,
        format!(
            "[robot]\nid = \"{robot}\"\n[camera]\nsource = \"replay\"\n[camera.replay]\npath = \"{}\"\nrate = 1.0\n\
             [backend]\nstate_dir = \"{}\"\noptimize_every = 5\n[sim_keyframes]\nevery = {every}\n\
             [up]\nservices = [\"backend\", \"sim-keyframes\", \"camera\"]\n",
            data.display(),
            dir.join("state").display()
        ),
    )
    .unwrap();
    (
        config,
        dir.join("state").join(robot).join("backend.journal"),
    )
}

/// `doorslam up --config CONFIG EXTRA...` with info logs on a piped stderr.
fn start_up(config: &Path, extra: &[&str]) -> Guard {
    Guard(
        Command::new(BIN)
            .args(["up", "--config", config.to_str().unwrap()])
            .args(extra)
            .env("RUST_LOG", "info")
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    )
}

#[test]
fn replay_to_sim_keyframes_to_backend_delivers_every_keyframe_in_order() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("seq");
    write_dataset(&data, 60);
    let robot = format!("pipe{}", std::process::id());
    let (config, journal) = write_robot(tmp.path(), &robot, &data, 3);
    let mut up = start_up(&config, &[]);
    let log = LogReader::new(&mut up);
    // Stop once the replay has ended: `up` stops the services in reverse start order, so
    // sim-keyframes finishes its queue first and the back-end journals everything it was
    // sent before it stops. No guess at how long a loaded machine needs.
    log.wait_for(&["replay: finished"], Duration::from_secs(60));
    signal(&up, libc::SIGINT);
    let status = wait_exit(&mut up, Duration::from_secs(20));
    let log = log.finish();
    assert!(status.success(), "doorslam up failed ({status}):\n{log}");
    assert!(
        log.contains("[camera]") && log.contains("replay: finished"),
        "{log}"
    );
    assert!(
        log.contains("NOT visual odometry"),
        "sim-keyframes must say what it is:\n{log}"
    );

    assert_every_keyframe_in_order(&journal, &log, 10);
}

/// A number logged as `name=<n>` on the line containing `line`.
fn logged(log: &str, line: &str, name: &str) -> usize {
    log.lines()
        .find(|l| l.contains(line))
        .and_then(|l| l.split(&format!("{name}=")).nth(1))
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no {name}= on a {line:?} line in the log:\n{log}"))
}

/// The journal holds every keyframe sim-keyframes published (at least `min`), in order,
/// with one odometry edge between consecutive ones. Keyframe ids follow frame numbers, so
/// they are consecutive from the first one sim-keyframes published, unless frames were
/// dropped before sim-keyframes (frames are lossy by design: a loaded machine may drop
/// some, also before sim-keyframes read its first), which the service counts.
fn assert_every_keyframe_in_order(journal: &Path, log: &str, min: usize) {
    let (ids, edges) = keyframe_ids(journal);
    let published = logged(log, "sim-keyframes: stopped", "keyframes");
    let dropped_frames = logged(log, "sim-keyframes: stopped", "dropped");
    let first = logged(log, "sim-keyframes: stopped", "first_keyframe") as u64;
    assert!(
        published >= min,
        "only {published} keyframes published:\n{log}"
    );
    if dropped_frames == 0 {
        assert_eq!(
            ids,
            (first..first + published as u64).collect::<Vec<_>>(),
            "every keyframe, in order"
        );
    } else {
        assert_eq!(ids.len(), published, "every keyframe");
        assert!(ids.windows(2).all(|w| w[0] < w[1]), "in order: {ids:?}");
    }
    assert_eq!(
        edges,
        published - 1,
        "one odometry edge between consecutive keyframes"
    );
}

fn keyframe(id: u64) -> Box<Keyframe> {
    Box::new(Keyframe {
        robot: 0,
        source: KeyframeSource::SimulatedTruth as u32,
        id,
        frame_seq: id,
        stamp_ns: id * 1_000_000,
        pose: [id as f64, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        n_features: 0,
        reserved: 0,
        features: [Feature::default(); MAX_KEYFRAME_FEATURES],
    })
}

fn odometry(from: u64) -> OdometryEdge {
    OdometryEdge {
        robot: 0,
        reserved: 0,
        from,
        to: from + 1,
        stamp_ns: 0,
        relative: [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        information: doorslam_geometry::information::upper_from_diagonal([
            1e4, 1e4, 1e4, 1e2, 1e2, 1e2,
        ]),
    }
}

/// `robot.toml` in `dir` for a back-end alone (state under `dir/state`); returns it and
/// the path of the journal the back-end will keep.
fn write_backend_robot(dir: &Path, robot: &str) -> (PathBuf, PathBuf) {
    let config = dir.join("robot.toml");
    let state = dir.join("state");
    std::fs::write(
        &config,
        format!(
            "[robot]\nid = \"{robot}\"\n[backend]\nstate_dir = \"{}\"\noptimize_every = 5\n",
            state.display()
        ),
    )
    .unwrap();
    (config, state.join(robot).join("backend.journal"))
}

fn start_backend(config: &Path, log: &Path) -> Guard {
    Guard(
        Command::new(BIN)
            .args(["service", "backend", "--config", config.to_str().unwrap()])
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap(),
    )
}

fn wait_ready(log: &Path) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while !std::fs::read_to_string(log)
        .unwrap_or_default()
        .contains("backend: ready")
    {
        assert!(Instant::now() < deadline, "backend never became ready");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn wait_for(journal: &Path, keyframes: usize, edges: usize) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while keyframe_ids(journal).0.len() < keyframes || keyframe_ids(journal).1 < edges {
        assert!(
            Instant::now() < deadline,
            "journal stuck at {:?}",
            keyframe_ids(journal)
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn backend_killed_mid_run_resumes_with_its_graph() {
    let tmp = tempfile::tempdir().unwrap();
    let robot = format!("kill{}", std::process::id());
    let (config, journal) = write_backend_robot(tmp.path(), &robot);

    let (node, _) = create_node("pipeline-test-frontend").unwrap();
    let kf = Sender::<Keyframe>::new(&node, &robot, Topic::Keyframes).unwrap();
    let odo = Sender::<OdometryEdge>::new(&node, &robot, Topic::Odometry).unwrap();
    let send = |range: std::ops::Range<u64>| {
        for id in range {
            kf.send_copy(&keyframe(id)).unwrap();
            if id > 0 {
                odo.send_copy(&odometry(id - 1)).unwrap();
            }
        }
    };
    let wait_subscribed = |n: usize| {
        let deadline = Instant::now() + Duration::from_secs(20);
        while kf.receivers() != n || odo.receivers() != n {
            assert!(Instant::now() < deadline, "backend did not subscribe");
            std::thread::sleep(Duration::from_millis(20));
        }
    };

    let mut backend = start_backend(&config, &tmp.path().join("first.log"));
    wait_ready(&tmp.path().join("first.log"));
    wait_subscribed(1);
    send(0..25);
    wait_for(&journal, 25, 24);
    backend.kill().unwrap(); // SIGKILL: no chance to clean up
    backend.wait().unwrap();
    // Sent while no back-end runs: they go to the dead subscriber's queue, which the next
    // back-end removes; the publisher's history is what brings them back.
    send(25..40);

    let second_log = tmp.path().join("second.log");
    let mut backend = start_backend(&config, &second_log);
    wait_ready(&second_log);
    // Nothing new is sent: the producer's idle call hands the history to the new back-end.
    let deadline = Instant::now() + Duration::from_secs(20);
    while keyframe_ids(&journal).0.len() < 40 || keyframe_ids(&journal).1 < 39 {
        assert!(
            Instant::now() < deadline,
            "sent during the outage, never journaled: {:?}",
            keyframe_ids(&journal)
        );
        kf.catch_up_receivers().unwrap();
        odo.catch_up_receivers().unwrap();
        std::thread::sleep(Duration::from_millis(50));
    }
    wait_subscribed(1);
    send(40..50);
    wait_for(&journal, 50, 49);
    signal(&backend, libc::SIGTERM);
    let status = wait_exit(&mut backend, Duration::from_secs(10));
    let log = std::fs::read_to_string(&second_log).unwrap();
    assert!(status.success(), "{log}");
    assert!(
        log.contains("keyframes=25") && log.contains("edges=24"),
        "recovery not logged:\n{log}"
    );
    let (ids, edges) = keyframe_ids(&journal);
    assert_eq!(ids, (0..50).collect::<Vec<_>>());
    assert_eq!(edges, 49);
    // The history (keyframes 0..40, edges 0..39) repeats what the first back-end had
    // journaled (25 keyframes, 24 edges): skipped as duplicates, without a gap.
    assert!(
        log.contains("duplicates: 49") && log.contains("gaps: 0"),
        "{log}"
    );
}

/// A consumer that crashes and stays down must not stall its producer for good: once its
/// queue is full the producer waits, finds the dead process's ports and removes them, and
/// carries on (what it sends stays in its history for the next back-end).
#[test]
fn producer_carries_on_when_its_consumer_stays_dead() {
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::Arc;
    let tmp = tempfile::tempdir().unwrap();
    let robot = format!("dead{}", std::process::id());
    let (config, journal) = write_backend_robot(tmp.path(), &robot);
    let log = tmp.path().join("backend.log");
    let mut backend = start_backend(&config, &log);
    wait_ready(&log);

    let (sent, go) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let producer = {
        let (robot, sent, go) = (robot.clone(), sent.clone(), go.clone());
        std::thread::spawn(move || {
            let (node, _) = create_node("pipeline-test-producer").unwrap();
            let kf = Sender::<Keyframe>::new(&node, &robot, Topic::Keyframes).unwrap();
            while kf.receivers() == 0 {
                std::thread::sleep(Duration::from_millis(10));
            }
            for id in 0..400 {
                while id == 5 && go.load(Ordering::Acquire) == 0 {
                    std::thread::sleep(Duration::from_millis(10));
                }
                kf.send_copy(&keyframe(id)).unwrap();
                sent.store(id + 1, Ordering::Release);
            }
            kf.receivers()
        })
    };
    wait_for(&journal, 5, 0);
    backend.kill().unwrap(); // SIGKILL: its ports stay behind, its queue fills up
    backend.wait().unwrap();
    go.store(1, Ordering::Release);
    let deadline = Instant::now() + Duration::from_secs(30);
    while !producer.is_finished() {
        assert!(
            Instant::now() < deadline,
            "producer stalled at {} of 400 on a dead consumer",
            sent.load(Ordering::Acquire)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        producer.join().unwrap(),
        0,
        "the dead consumer's ports were removed"
    );
}

/// The whole robot under `doorslam up`, with the back-end SIGKILLed in the middle of the
/// run: `up` restarts it (as systemd would), it resumes from its journal, the keyframes
/// sent while it was down reach it from the producer's history, and in the end the journal
/// holds every keyframe sim-keyframes published, in order, once.
#[test]
fn backend_crash_under_up_loses_no_keyframe() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("seq");
    write_dataset(&data, 400);
    let robot = format!("crash{}", std::process::id());
    let (config, journal) = write_robot(tmp.path(), &robot, &data, 2);
    let mut up = start_up(&config, &["--restart-delay-s", "0.5"]);
    let log = LogReader::new(&mut up);
    let text = || log.text();

    let deadline = Instant::now() + Duration::from_secs(30);
    while keyframe_ids(&journal).0.len() < 30 {
        assert!(
            Instant::now() < deadline,
            "no keyframes journaled:\n{}",
            text()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let pid: i32 = text()
        .lines()
        .find_map(|l| l.strip_prefix("[up] started backend (pid "))
        .and_then(|rest| rest.trim_end_matches(')').parse().ok())
        .expect("backend pid in up's log");
    // SAFETY: kill(2) of the back-end process `up` started for this test.
    unsafe { libc::kill(pid, libc::SIGKILL) };

    // Wait for the replay to end and the back-end to be back, then stop: sim-keyframes
    // hands its history to the restarted back-end at the latest when it stops (before the
    // back-end, which drains its queue).
    log.wait_for(
        &["replay: finished", "backend: ready", "backend: ready"],
        Duration::from_secs(60),
    );
    signal(&up, libc::SIGINT);
    let status = wait_exit(&mut up, Duration::from_secs(20));
    let log = log.finish();
    assert!(status.success(), "doorslam up failed ({status}):\n{log}");
    assert!(
        log.contains("[up] backend failed (signal: 9") && log.contains("restarting in"),
        "the kill and the restart are logged:\n{log}"
    );
    assert_eq!(
        log.matches("[up] started backend").count(),
        2,
        "restarted once:\n{log}"
    );
    assert!(
        log.contains("backend: recovered graph from journal"),
        "{log}"
    );
    assert_every_keyframe_in_order(&journal, &log, 150);
}

#[test]
fn replay_splits_one_sequence_into_robots() {
    use doorslam_ipc::{Receiver, StereoFrame, FRAME_HAS_TRUTH};
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("seq");
    write_dataset(&data, 20);
    let prefix = format!("split{}", std::process::id());
    let (node, _) = create_node("pipeline-test-replay-subscriber").unwrap();
    let receivers: Vec<Receiver<StereoFrame>> = ["a", "b"]
        .iter()
        .map(|r| Receiver::new(&node, &format!("{prefix}{r}"), Topic::Frames).unwrap())
        .collect();
    // 100 Hz real time: 10 frames per robot in 0.1 s, slow enough for this reader.
    let mut replay = Guard(
        Command::new(BIN)
            .args([
                "replay",
                data.to_str().unwrap(),
                "--robots",
                "2",
                "--robot-prefix",
                &prefix,
                "--rate",
                "1",
                "--wait-s",
                "10",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let mut got: Vec<Vec<(u64, f64)>> = vec![vec![], vec![]];
    let deadline = Instant::now() + Duration::from_secs(20);
    while got.iter().map(Vec::len).sum::<usize>() < 20 && Instant::now() < deadline {
        for (r, rx) in receivers.iter().enumerate() {
            while let Some(s) = rx.try_recv().unwrap() {
                let h = *s.payload().header();
                assert_ne!(
                    h.flags & FRAME_HAS_TRUTH,
                    0,
                    "replayed frames carry the truth of poses.txt"
                );
                assert_eq!((h.width, h.height, h.robot), (64, 48, r as u32));
                got[r].push((h.seq, h.truth_pose[0]));
            }
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    let status = wait_exit(&mut replay, Duration::from_secs(20));
    assert!(status.success());
    // Robot a plays frames 0..10 (x = 0.0 .. 0.9), robot b frames 10..20 (x = 1.0 .. 1.9).
    assert_eq!(
        got[0].iter().map(|g| g.0).collect::<Vec<_>>(),
        (0..10).collect::<Vec<_>>()
    );
    assert_eq!(
        got[1].iter().map(|g| g.0).collect::<Vec<_>>(),
        (0..10).collect::<Vec<_>>()
    );
    assert!(
        (got[0][0].1 - 0.0).abs() < 1e-9 && (got[1][0].1 - 1.0).abs() < 1e-9,
        "{got:?}"
    );
}
