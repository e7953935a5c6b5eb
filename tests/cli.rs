//! The `doorslam` binary as a user meets it: help, unfinished commands, config errors,
//! the camera service without a camera, and the demo.

use std::process::{Command, Output};

fn doorslam(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_doorslam"))
        .args(args)
        .env(
            "DOORSLAM_DATA",
            concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"),
        )
        .output()
        .expect("run doorslam")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

const SUBCOMMANDS: [&str; 10] = [
    "service", "up", "pgo", "pcm", "dpgo", "eval", "sim", "replay", "bw", "demo",
];

#[test]
fn help_lists_every_subcommand() {
    let out = doorslam(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for sub in SUBCOMMANDS {
        assert!(
            help.lines().any(|l| l.trim_start().starts_with(sub)),
            "--help lacks {sub}:\n{help}"
        );
    }
}

#[test]
fn unfinished_commands_fail_clearly_without_panicking() {
    let pending = [
        (vec!["up"], "#11"),
        (vec!["pgo", "graph.g2o", "--json"], "#12"),
        (vec!["pcm", "graph.g2o"], "#10"),
        (vec!["dpgo"], "distributed back-end"),
        (vec!["eval", "ate", "a.txt", "b.txt"], "#12"),
        (vec!["sim", "world"], "#6"),
        (vec!["replay", "dir"], "#6"),
        (vec!["bw"], "team-link"),
        (vec!["service", "backend"], "#11"),
        (vec!["service", "frontend"], "front-end"),
        (vec!["service", "place-recognition"], "place-recognition"),
        (vec!["service", "team"], "team-link"),
    ];
    for (args, issue) in pending {
        let out = doorslam(&args);
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(
            err.contains("not built yet") && err.contains(issue),
            "{args:?}: {err}"
        );
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}

#[test]
fn camera_service_without_a_camera_points_at_replay() {
    if std::path::Path::new("/dev/video0").exists() {
        // A machine with a camera takes the capture path; this test is about the other case.
        eprintln!("/dev/video0 present: testing the error with a device that is not");
        let dir = tempfile::tempdir().unwrap();
        let cfg = dir.path().join("robot.toml");
        std::fs::write(&cfg, "[camera]\nleft = \"/dev/video97\"\n").unwrap();
        let out = doorslam(&["service", "camera", "--config", cfg.to_str().unwrap()]);
        assert!(
            stderr(&out).contains("no camera found at /dev/video97"),
            "{}",
            stderr(&out)
        );
        return;
    }
    let out = doorslam(&["service", "camera"]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("no camera found at /dev/video0") && err.contains("use replay"),
        "{err}"
    );
}

#[test]
fn config_errors_name_the_file_and_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("robot.toml");
    std::fs::write(&cfg, "[robot]\nid = \"a\"\n[camera]\nwidht = 752\n").unwrap();
    let err = stderr(&doorslam(&[
        "service",
        "camera",
        "--config",
        cfg.to_str().unwrap(),
    ]));
    assert!(err.contains("robot.toml") && err.contains("widht"), "{err}");

    std::fs::write(&cfg, "[robot]\nid = \"Robot One\"\n").unwrap();
    let err = stderr(&doorslam(&[
        "service",
        "camera",
        "--config",
        cfg.to_str().unwrap(),
    ]));
    assert!(err.contains("robot.id"), "{err}");

    let err = stderr(&doorslam(&[
        "service",
        "camera",
        "--config",
        "/nonexistent/robot.toml",
    ]));
    assert!(err.contains("/nonexistent/robot.toml"), "{err}");
}

#[test]
fn example_robot_config_is_valid() {
    let cfg = concat!(env!("CARGO_MANIFEST_DIR"), "/deploy/robot.toml");
    let text = std::fs::read_to_string(cfg).unwrap();
    let parsed: doorslam::config::RobotConfig = toml::from_str(&text).unwrap();
    parsed.validate().unwrap();
}

#[test]
fn demo_checks_the_whole_stack_on_real_data() {
    let out = doorslam(&["demo"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", stderr(&out));
    for lib in ["opencv", "iceoryx2", "onnxruntime", "zenoh", "faer", "v4l"] {
        assert!(
            stdout
                .lines()
                .any(|l| l.trim_start().starts_with(&format!("ok  {lib}"))),
            "{lib} step missing:\n{stdout}"
        );
    }
    assert!(stdout.contains("all stack checks passed"));
}
