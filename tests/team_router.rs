//! Router mode of the team link (issue 21): two `doorslam service team` processes that can
//! reach each other only through a `doorslam router` (no multicast, no listening endpoint
//! of their own, each connects only to the router) meet and complete a rendezvous. The
//! whole team runs with TLS and access control (certificates from `doorslam team certs`).
//! Loopback, ports unique per run, every process stopped even when the test fails.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
use common::free_port;

const BIN: &str = env!("CARGO_BIN_EXE_doorslam");

/// Child processes, killed on drop.
struct Procs(Vec<Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn spawn(d: &Path, name: &str, args: &[&str]) -> Child {
    let log = std::fs::File::create(d.join(format!("{name}.log"))).unwrap();
    Command::new(BIN)
        .args(args)
        .env("RUST_LOG", "info,zenoh=warn")
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap()
}

fn logs(d: &Path) -> String {
    ["router", "a", "b"]
        .iter()
        .map(|n| {
            format!(
                "--- {n}\n{}",
                std::fs::read_to_string(d.join(format!("{n}.log"))).unwrap_or_default()
            )
        })
        .collect()
}

fn config(d: &Path, robot: &str, index: u32, team: &str, router: &str) -> PathBuf {
    let path = d.join(format!("{robot}.toml"));
    let certs = d.join("certs");
    std::fs::write(
        &path,
        format!(
            r#"[robot]
id = "{robot}"
index = {index}

[team]
name = "{team}"
mode = "client"
pieces = "standin"
listen = []
connect = ["{router}"]
multicast_scouting = false
lease_ms = 2000
retransmit_ms = 300
write_every_ms = 200
run_dir = "{run}"

[team.standin]
keyframes = 60
keyframe_interval_ms = 20
features_per_keyframe = 50

[team.tls]
ca = "{certs}/ca.pem"
cert = "{certs}/robots/{robot}/cert.pem"
key = "{certs}/robots/{robot}/key.pem"
robots = ["a", "b"]
"#,
            run = d.join("run").display(),
            certs = certs.display(),
        ),
    )
    .unwrap();
    path
}

fn status(d: &Path, robot: &str) -> Option<Value> {
    let text = std::fs::read_to_string(d.join("run").join(robot).join("status.json")).ok()?;
    serde_json::from_str(&text).ok()
}

#[test]
fn two_robots_that_reach_each_other_only_through_a_router_complete_a_rendezvous() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let team = format!("rt{}", std::process::id());
    let certs = d.join("certs");
    let out = Command::new(BIN)
        .args([
            "team",
            "certs",
            "--robots",
            "a,b",
            "--routers",
            "r1",
            "--team",
            &team,
        ])
        .arg("--out")
        .arg(&certs)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let router = format!("tls/127.0.0.1:{}", free_port());
    let mut procs = Procs(Vec::new());
    for (robot, index) in [("a", 0), ("b", 1)] {
        let cfg = config(d, robot, index, &team, &router);
        procs.0.push(spawn(
            d,
            robot,
            &["service", "team", "--config", cfg.to_str().unwrap()],
        ));
    }

    // Without the router they cannot meet: nothing listens on their side.
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(3) {
        for robot in ["a", "b"] {
            let present = status(d, robot)
                .and_then(|s| s["present"].as_array().map(|p| p.len()))
                .unwrap_or(0);
            assert_eq!(
                present,
                0,
                "{robot} met a peer without the router:\n{}",
                logs(d)
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    }

    let r1 = certs.join("routers/r1");
    procs.0.push(spawn(
        d,
        "router",
        &[
            "router",
            "--team",
            &team,
            "--listen",
            &router,
            "--ca",
            certs.join("ca.pem").to_str().unwrap(),
            "--cert",
            r1.join("cert.pem").to_str().unwrap(),
            "--key",
            r1.join("key.pem").to_str().unwrap(),
            "--robots",
            "a,b",
        ],
    ));
    let start = Instant::now();
    loop {
        let delivered = status(d, "b")
            .and_then(|s| {
                s["peers"]["a"]["delivered_descriptors"]
                    .as_array()
                    .map(|a| a.len())
            })
            .unwrap_or(0);
        let done = delivered == 60
            && status(d, "a").is_some_and(|s| {
                s["keyframes_created"] == 60
                    && s["peers"]["b"]["unacknowledged_messages"] == 0
                    && s["peers"]["b"]["stats"]["closures_accepted"].as_u64() > Some(0)
            });
        if done {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "rendezvous through the router incomplete after 60 s (b has {delivered} of a's descriptors):\n{}",
            logs(d)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    for c in &procs.0 {
        unsafe { libc::kill(c.id() as i32, libc::SIGTERM) };
    }
    for c in &mut procs.0 {
        let code = c.wait().unwrap();
        assert!(code.success(), "a process exited with {code}:\n{}", logs(d));
    }
    procs.0.clear();
    let sb = status(d, "b").unwrap();
    assert_eq!(sb["peers"]["a"]["stats"]["descriptors_delivered"], 60);
    assert_eq!(sb["peers"]["a"]["stats"]["descriptors_redelivered"], 0);
    // The ledgers were kept with TLS framing.
    let ledger: Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/a/ledger.json")).unwrap())
            .unwrap();
    use doorslam_team::ledger::{TLS_RECORD_BYTES, ZENOH_FRAMING_BYTES};
    assert_eq!(
        ledger["framing"]["overhead_bytes_per_message"],
        ZENOH_FRAMING_BYTES + TLS_RECORD_BYTES
    );
    assert!(logs(d).contains("router up"), "{}", logs(d));
}
