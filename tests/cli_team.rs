//! The team link's security as a user meets it: `doorslam team certs`, `[team.tls]`
//! errors naming the file, the warning of an open link, `doorslam router`'s flags.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

const BIN: &str = env!("CARGO_BIN_EXE_doorslam");

fn doorslam(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().expect("run doorslam")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn certs(out: &Path, robots: &str) -> Output {
    doorslam(&[
        "team",
        "certs",
        "--out",
        out.to_str().unwrap(),
        "--robots",
        robots,
        "--team",
        "t1",
        "--days",
        "10",
    ])
}

#[test]
fn help_lists_team_and_router() {
    let out = doorslam(&["--help"]);
    let help = String::from_utf8_lossy(&out.stdout);
    for sub in ["team", "router"] {
        assert!(
            help.lines().any(|l| l.trim_start().starts_with(sub)),
            "--help lacks {sub}:\n{help}"
        );
    }
}

#[test]
fn team_certs_writes_a_ca_and_a_certificate_per_robot_and_refuses_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("certs");
    let o = certs(&out, "a,b");
    assert!(o.status.success(), "{}", stderr(&o));
    for f in [
        "ca.pem",
        "ca.key",
        "robots/a/cert.pem",
        "robots/a/key.pem",
        "robots/b/cert.pem",
        "robots/b/key.pem",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("[team.tls]") && stdout.contains(r#"robots = ["a", "b"]"#),
        "{stdout}"
    );
    // A robot added later joins the same CA and the printed roster.
    let o = certs(&out, "c");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains(r#"robots = ["a", "b", "c"]"#));
    // Never overwritten; bad ids named.
    let o = certs(&out, "a");
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("robots/a/cert.pem") && stderr(&o).contains("exists"));
    let o = certs(&out, "Robot One");
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("Robot One"), "{}", stderr(&o));
}

/// A robot whose team link runs with the stand-in pieces: these tests are about the link
/// (TLS, logs), not the robot's camera or calibration.
fn robot_config(dir: &Path, body: &str) -> String {
    let cfg = dir.join("robot.toml");
    std::fs::write(
        &cfg,
        format!(
            "[robot]\nid = \"a\"\n[team]\nname = \"t1\"\nmulticast_scouting = false\npieces = \"standin\"\nrun_dir = \"{}\"\n{body}",
            dir.join("run").display()
        ),
    )
    .unwrap();
    cfg.to_str().unwrap().to_string()
}

#[test]
fn a_bad_tls_file_stops_the_team_service_with_its_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("certs");
    assert!(certs(&out, "a,b").status.success());
    let tls = |cert: &str, key: &str| {
        format!(
            "listen = [\"tls/127.0.0.1:0\"]\n[team.tls]\nca = \"{c}/ca.pem\"\ncert = \"{cert}\"\nkey = \"{key}\"\nrobots = [\"a\", \"b\"]\n",
            c = out.display()
        )
    };
    let garbage = d.join("garbage.pem");
    std::fs::write(&garbage, "not a certificate").unwrap();
    let a_key = out.join("robots/a/key.pem");
    let b = out.join("robots/b");
    for (cert, key, expect) in [
        (
            garbage.clone(),
            a_key.clone(),
            vec!["garbage.pem", "not PEM"],
        ),
        (
            d.join("missing.pem"),
            a_key.clone(),
            vec!["missing.pem", "No such file"],
        ),
        (
            b.join("cert.pem"),
            b.join("key.pem"),
            vec!["robots/b/cert.pem", "common name \"b\""],
        ),
        (
            out.join("robots/a/cert.pem"),
            b.join("key.pem"),
            vec!["robots/b/key.pem", "not the private key"],
        ),
    ] {
        let cfg = robot_config(d, &tls(cert.to_str().unwrap(), key.to_str().unwrap()));
        let o = doorslam(&["service", "team", "--config", &cfg]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{err}");
        for e in expect {
            assert!(err.contains(e), "expected {e:?} in: {err}");
        }
        assert!(!err.contains("panicked"), "{err}");
    }
    // A tcp/ endpoint with [team.tls]: named.
    let cfg = robot_config(
        d,
        &tls(
            out.join("robots/a/cert.pem").to_str().unwrap(),
            a_key.to_str().unwrap(),
        )
        .replace("tls/127.0.0.1:0", "tcp/127.0.0.1:0"),
    );
    let o = doorslam(&["service", "team", "--config", &cfg]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("tcp/127.0.0.1:0"), "{}", stderr(&o));
    // A roster entry that is not a robot id: named.
    let cfg = robot_config(
        d,
        &tls(
            out.join("robots/a/cert.pem").to_str().unwrap(),
            a_key.to_str().unwrap(),
        )
        .replace("[\"a\", \"b\"]", "[\"a\", \"B!\"]"),
    );
    let o = doorslam(&["service", "team", "--config", &cfg]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("B!"), "{}", stderr(&o));
}

#[test]
fn an_open_team_link_says_so_in_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = robot_config(dir.path(), "listen = [\"tcp/127.0.0.1:0\"]\n");
    let log = dir.path().join("team.log");
    let mut child = Command::new(BIN)
        .args(["service", "team", "--config", &cfg])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let start = std::time::Instant::now();
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains("link open")
    {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    assert!(child.wait().unwrap().success());
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("team link is open"), "{text}");
}

#[test]
fn router_flags_are_checked_by_name() {
    let o = doorslam(&["router", "--ca", "/x/ca.pem", "--robots", "a"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("--cert is missing"), "{}", stderr(&o));
    let o = doorslam(&["router", "--config", "/nonexistent/router.toml"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("/nonexistent/router.toml"));
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("certs");
    assert!(certs(&out, "a").status.success());
    // A robot's certificate where the router's should be.
    let o = doorslam(&[
        "router",
        "--team",
        "t1",
        "--listen",
        "tls/127.0.0.1:0",
        "--ca",
        out.join("ca.pem").to_str().unwrap(),
        "--cert",
        out.join("robots/a/cert.pem").to_str().unwrap(),
        "--key",
        out.join("robots/a/key.pem").to_str().unwrap(),
        "--robots",
        "a",
    ]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(
        err.contains("robots/a/cert.pem") && err.contains("doorslam.router"),
        "{err}"
    );
}

#[test]
fn example_router_config_parses() {
    let text = std::fs::read_to_string(concat!(".", "/deploy/router.toml")).unwrap();
    let parsed: doorslam_team::router::RouterFile = toml::from_str(&text).unwrap();
    let tls = parsed.router.tls.expect("[router.tls]");
    assert_eq!(tls.roster().unwrap().len(), 3);
    assert!(parsed.router.listen.iter().all(|e| e.starts_with("tls/")));
}

/// `doorslam team delivery-bench --json`: one report per layer with the documented fields
/// (a short run without a cut, ~4 s), and bad flags named.
#[test]
fn delivery_bench_reports_both_layers_and_names_bad_flags() {
    let out = doorslam(&[
        "team",
        "delivery-bench",
        "--messages",
        "20",
        "--rate-hz",
        "20",
        "--cut-s",
        "0",
        "--json",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let runs = v["runs"].as_array().expect("runs");
    let layers: Vec<&str> = runs.iter().filter_map(|r| r["layer"].as_str()).collect();
    assert_eq!(layers, ["acks", "zenoh-ext"]);
    for r in runs {
        for field in [
            "messages",
            "delivered",
            "missing",
            "duplicates",
            "out_of_order",
            "reported_missed",
            "resends",
            "payload_bytes",
            "bytes_a_to_b",
            "bytes_b_to_a",
            "overhead_ratio",
            "recovered_after_s",
            "time_s",
        ] {
            assert!(r.get(field).is_some(), "{field} missing: {r}");
        }
        // zenoh-ext may lose the first message to discovery (BENCHMARKS.md, "The delivery
        // contract against zenoh-ext's"); the acknowledgements never do.
        let least = if r["layer"] == "acks" { 20 } else { 19 };
        assert!(r["delivered"].as_u64().unwrap() >= least, "{r}");
        assert!(r["bytes_a_to_b"].as_u64().unwrap() > r["payload_bytes"].as_u64().unwrap());
    }
    for (flag, value) in [
        ("--descriptors", "0"),
        ("--cut-s", "-1"),
        ("--cache", "0"),
        ("--messages", "10000000"),
        ("--rate-hz", "0"),
    ] {
        let out = doorslam(&["team", "delivery-bench", &format!("{flag}={value}")]);
        assert!(!out.status.success());
        assert!(stderr(&out).contains(flag), "{flag}: {}", stderr(&out));
    }
}
