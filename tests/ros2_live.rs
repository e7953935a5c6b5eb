//! The live ROS 2 publishers of a running robot, checked from the outside (issue #32's
//! acceptance): `doorslam up` runs a robot (camera replay → sim-keyframes → back-end) with
//! `[ros2] enabled`, so `up` adds the `ros2` service, whose session connects to
//! `tests/ros2/check_live.py --live` (eclipse-zenoh, rosbags' decoder, xxhash) listening on
//! a free loopback port. Once the replay has ended and the back-end's team estimate stopped
//! changing, the checker checks the tokens, keys and attachments against rmw_zenoh's
//! format, decodes every sample, wants every topic several times and the last team path
//! equal to `team_estimate.tum`. Skipped, with the reason printed, without the set-up's
//! venv. Unique robot id (iceoryx2 service names), port and folder; every wait bounded.

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{free_port, signal, wait_exit, Guard, LogReader};

const BIN: &str = env!("CARGO_BIN_EXE_doorslam");

/// A KITTI-layout sequence: noise images at 10 Hz, poses along a gentle curve.
fn write_dataset(dir: &Path, frames: usize) {
    common::write_noise_dataset(dir, frames, 0.1, |k| {
        (0.5 * k as f64, 0.002 * (k * k) as f64)
    });
}

/// Waits until `file` exists and has not changed for `quiet`.
fn wait_settled(file: &Path, quiet: Duration, limit: Duration) {
    let deadline = Instant::now() + limit;
    let (mut last, mut since) = (None, Instant::now());
    loop {
        let now = std::fs::read(file).ok();
        if now.is_some() && now == last && since.elapsed() >= quiet {
            return;
        }
        if now != last {
            (last, since) = (now, Instant::now());
        }
        assert!(
            Instant::now() < deadline,
            "{} did not settle within {limit:?}",
            file.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_running_robot_publishes_what_rmw_zenoh_publishes() {
    let python = match doorslam_ros2::reference_python(&["zenoh", "rosbags", "xxhash"]) {
        Ok(p) => p,
        Err(why) => {
            println!("skipped: {why}");
            return;
        }
    };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("seq");
    write_dataset(&data, 60);
    let robot = format!("rlive{}", std::process::id());
    let state = tmp.path().join("state");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());

    let mut checker = Guard(
        Command::new(&python)
            .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/ros2/check_live.py"))
            .args(["--listen", &endpoint, "--run-dir"])
            .arg(&state)
            .args(["--live", "--min-per-topic", "3", "--timeout-s", "50"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let mut stdout = BufReader::new(checker.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready", "the checker did not start");

    let config = tmp.path().join("robot.toml");
    std::fs::write(
        &config,
        format!(
            "[robot]\nid = \"{robot}\"\n[camera]\nsource = \"replay\"\n[camera.replay]\npath = \"{}\"\nrate = 1.0\n\
             [backend]\nstate_dir = \"{}\"\noptimize_every = 3\nwrite_every_s = 0.3\n[sim_keyframes]\nevery = 3\n\
             [up]\nservices = [\"backend\", \"sim-keyframes\", \"camera\"]\n\
             [ros2]\nenabled = true\nrate_hz = 10.0\nconnect = [\"{endpoint}\"]\n",
            data.display(),
            state.display()
        ),
    )
    .unwrap();
    let mut up = Guard(
        Command::new(BIN)
            .args(["up", "--config", config.to_str().unwrap()])
            .env("RUST_LOG", "info")
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let log = LogReader::new(&mut up);
    log.wait_for(
        &["[up] started ros2", "ros2: publishing", "replay: finished"],
        Duration::from_secs(40),
    );
    // The back-end's last rewrites, then a second of publishing the settled state.
    wait_settled(
        &state.join(&robot).join("team_estimate.tum"),
        Duration::from_secs(1),
        Duration::from_secs(20),
    );
    std::thread::sleep(Duration::from_millis(500));
    writeln!(checker.stdin.take().unwrap(), "stop").unwrap();
    let status = wait_exit(&mut checker, Duration::from_secs(20));
    let mut out = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut out).unwrap();
    let mut err = String::new();
    std::io::Read::read_to_string(&mut checker.stderr.take().unwrap(), &mut err).unwrap();

    signal(&up, libc::SIGINT);
    let up_status = wait_exit(&mut up, Duration::from_secs(20));
    let log = log.finish();
    assert!(status.success(), "{out}{err}\n--- robot log:\n{log}");
    assert!(out.contains("ok:"), "{out}{err}");
    assert!(
        up_status.success(),
        "doorslam up failed ({up_status}):\n{log}"
    );
    assert!(log.contains("ros2: stopped"), "{log}");
    println!("{}", out.trim());
}

#[test]
fn the_ros2_service_refuses_to_run_when_off_and_bad_keys_name_themselves() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |toml: &str| {
        let config = tmp.path().join("robot.toml");
        std::fs::write(&config, toml).unwrap();
        let out = Command::new(BIN)
            .args(["service", "ros2", "--config", config.to_str().unwrap()])
            .output()
            .unwrap();
        assert!(!out.status.success(), "{toml}: ran");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = run("[robot]\nid = \"a\"\n");
    assert!(e.contains("ros2.enabled = false"), "{e}");
    let e = run("[ros2]\nenabled = true\nrate_hz = 0.0\n");
    assert!(e.contains("ros2.rate_hz"), "{e}");
    let e = run("[ros2]\ndomain_id = 300\n");
    assert!(e.contains("ros2.domain_id"), "{e}");
    let e = run("[robot]\nid = \"robot-1\"\n[ros2]\nenabled = true\n");
    assert!(e.contains("ros2.namespace"), "{e}");
    let e = run("[up]\nservices = [\"backend\", \"ros2\"]\n");
    assert!(e.contains("up.services lists ros2"), "{e}");
    let e = run("[ros2]\nenable = true\n");
    assert!(e.contains("enable"), "{e}");
}
