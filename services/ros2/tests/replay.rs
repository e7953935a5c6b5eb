//! `doorslam ros2 replay` of the small run folder (`tests/ros2/run/`), checked from the
//! outside: `tests/ros2/check_live.py` (eclipse-zenoh, rosbags' decoder, xxhash) listens
//! on a free loopback port, the replay connects to it and publishes; the script checks the
//! liveliness tokens, key expressions and attachments against rmw_zenoh's format, decodes
//! every payload, and compares each robot's last team path with its `team_estimate.tum`.
//! Skipped, with the reason printed, when the set-up's venv lacks those packages.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use doorslam_ros2::record::run_messages;
use doorslam_ros2::reference_python;
use doorslam_ros2::replay::{replay, ReplayOptions};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
fn a_replay_is_what_rmw_zenoh_publishes() {
    let python = match reference_python(&["zenoh", "rosbags", "xxhash"]) {
        Ok(p) => p,
        Err(why) => {
            println!("skipped: {why}");
            return;
        }
    };
    let run = repo().join("tests/ros2/run");
    let expect = run_messages(&run).unwrap().samples.len();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let mut child = Command::new(&python)
        .arg(repo().join("tests/ros2/check_live.py"))
        .args(["--listen", &endpoint, "--run-dir"])
        .arg(&run)
        .args(["--expect", &expect.to_string(), "--timeout-s", "30"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready", "the checker did not start");

    let options = ReplayOptions {
        connect: vec![endpoint],
        multicast_scouting: false,
        // The fixture's 5 s of run in 0.1 s.
        rate: 50.0,
        warmup: Duration::from_millis(1500),
        linger: Duration::from_millis(500),
        ..ReplayOptions::default()
    };
    let summary = replay(&run, &options, &AtomicBool::new(false)).unwrap();
    assert_eq!(summary.samples.values().sum::<u64>(), expect as u64);

    // Bounded wait for the checker, killed past it.
    let t = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > Duration::from_secs(40) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("check_live.py did not finish in 40 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut rest).unwrap();
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    assert!(status.success(), "{rest}{err}");
    assert!(rest.contains("ok:"), "{rest}{err}");
    println!("{}", rest.trim());
}

#[test]
fn a_bad_rate_is_refused() {
    let run = repo().join("tests/ros2/run");
    let options = ReplayOptions {
        rate: 0.0,
        ..ReplayOptions::default()
    };
    let e = replay(&run, &options, &AtomicBool::new(false))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--rate 0"), "{e}");
}
