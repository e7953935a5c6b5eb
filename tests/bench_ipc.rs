//! `doorslam bench ipc --json` runs every transport across two real processes and
//! reports one JSON object of the documented shape. Figures are machine-dependent and
//! only reported; what is checked is the shape, the data integrity, and the zero-copy
//! verdicts, which follow from how each transport works.
//!
//! Loopback and shared memory only; service names carry the bench process's pid.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

const TRANSPORTS: [&str; 6] = [
    "iceoryx2_poll",
    "iceoryx2_event",
    "eventfd_floor",
    "unix_dgram_floor",
    "zenoh_shm",
    "unix_socket",
];
const RESOLUTIONS: [&str; 2] = ["752x480", "1280x720"];
const LIMIT: Duration = Duration::from_secs(60);

/// Runs the bench with a hard time limit; returns (success, stdout, stderr).
fn run_bench() -> (bool, String, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_doorslam"))
        .args([
            "bench",
            "ipc",
            "--json",
            "--seconds-per-case",
            "0.3",
            "--rounds",
            "2",
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start doorslam bench ipc");
    // Drain both pipes on threads so a full pipe cannot stall the bench.
    let mut out = child.stdout.take().unwrap();
    let mut err = child.stderr.take().unwrap();
    let out_t = std::thread::spawn(move || {
        let mut s = String::new();
        out.read_to_string(&mut s).map(|_| s)
    });
    let err_t = std::thread::spawn(move || {
        let mut s = String::new();
        err.read_to_string(&mut s).map(|_| s)
    });
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            panic!("doorslam bench ipc took longer than {LIMIT:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let stdout = out_t.join().unwrap().unwrap();
    let stderr = err_t.join().unwrap().unwrap();
    (status.success(), stdout, stderr)
}

fn is_num_or_null(v: &Value) -> bool {
    v.is_number() || v.is_null()
}

#[test]
fn bench_ipc_reports_every_transport_with_zero_copy_verdicts() {
    let (ok, stdout, stderr) = run_bench();
    assert!(ok, "bench failed\nstdout:\n{stdout}\nstderr:\n{stderr}");

    // Exactly one JSON object on stdout.
    let mut values = serde_json::Deserializer::from_str(&stdout).into_iter::<Value>();
    let report = values.next().expect("one JSON value").expect("valid JSON");
    assert!(
        values.next().is_none(),
        "more than one JSON value on stdout"
    );
    assert!(report.is_object(), "stdout is not a JSON object");

    let machine = &report["machine"];
    assert!(machine.is_object(), "machine: {machine}");
    assert!(machine["logical_cpus"].as_u64().unwrap() >= 1);

    let results = report["results"].as_array().expect("results array");
    assert_eq!(results.len(), TRANSPORTS.len() * RESOLUTIONS.len());
    for res in RESOLUTIONS {
        for t in TRANSPORTS {
            let rows: Vec<&Value> = results
                .iter()
                .filter(|r| r["transport"] == t && r["resolution"] == res)
                .collect();
            assert_eq!(rows.len(), 1, "{t} {res} rows");
            let r = rows[0];
            assert!(r["error"].is_null(), "{t} {res}: {}", r["error"]);
            for key in [
                "p50_us",
                "p99_us",
                "pairs_per_s",
                "cpu_us_per_frame_30hz",
                "cpu_percent_30hz",
            ] {
                assert!(is_num_or_null(&r[key]), "{t} {res} {key}: {}", r[key]);
            }
            assert!(r["zero_copy"].is_boolean() || r["zero_copy"].is_null());
            let samples = r["samples"].as_u64().expect("samples");
            assert!(samples > 0, "{t} {res}: no latency samples");
            assert!(r["drops"].as_u64().is_some(), "{t} {res}: drops");
            let (p50, p99) = (r["p50_us"].as_f64().unwrap(), r["p99_us"].as_f64().unwrap());
            assert!((0.0..=p99).contains(&p50), "{t} {res}: p50 {p50} p99 {p99}");
            // Two rounds ran; each figure is the lower median (the smaller of two).
            assert_eq!(r["rounds"], 2, "{t} {res}");
            let rounds: Vec<f64> = r["p99_us_rounds"]
                .as_array()
                .expect("p99_us_rounds")
                .iter()
                .map(|v| v.as_f64().expect("round p99"))
                .collect();
            assert_eq!(rounds.len(), 2, "{t} {res}");
            assert_eq!(
                p99,
                rounds[0].min(rounds[1]),
                "{t} {res}: median of {rounds:?}"
            );
            assert!(r["cpu_us_per_frame_30hz"].as_f64().unwrap() > 0.0);
            assert_eq!(r["checksum_errors"], 0, "{t} {res}: corrupted pairs");
            if t.ends_with("_floor") {
                assert!(r["pairs_per_s"].is_null() && r["zero_copy"].is_null());
            } else {
                assert!(r["pairs_per_s"].as_f64().unwrap() > 0.0, "{t} {res}");
            }
        }
        let row = |t: &str| {
            results
                .iter()
                .find(|r| r["transport"] == t && r["resolution"] == res)
                .unwrap()
        };
        // Established in both processes from /proc/self/maps, not asserted by the bench.
        assert_eq!(row("iceoryx2_poll")["zero_copy"], true, "{res}");
        assert_eq!(row("iceoryx2_event")["zero_copy"], true, "{res}");
        assert_eq!(row("unix_socket")["zero_copy"], false, "{res}");
    }
}
