//! The systemd units in deploy/systemd pass `systemd-analyze verify`, with ExecStart
//! pointed at the binary under test (verify checks that the executable exists).

use std::process::Command;

#[test]
fn units_pass_systemd_analyze_verify() {
    let src = concat!(".", "/deploy/systemd");
    let tmp = tempfile::tempdir().unwrap();
    let mut units = Vec::new();
    for entry in std::fs::read_dir(src).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_owned();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.contains("Description="),
            "{} has no Description",
            path.display()
        );
        if text.contains("[Service]") {
            for key in [
                "Type=notify",
                "WatchdogSec=",
                "Restart=on-failure",
                "PartOf=doorslam.target",
            ] {
                assert!(text.contains(key), "{} lacks {key}", path.display());
            }
        }
        let text = text.replace("/usr/local/bin/doorslam", env!("CARGO_BIN_EXE_doorslam"));
        let out = tmp.path().join(&name);
        std::fs::write(&out, text).unwrap();
        units.push(out);
    }
    assert!(units.len() >= 4, "expected the target and three services");
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg("--man=no")
        .args(&units)
        .env("SYSTEMD_LOG_LEVEL", "warning")
        .output()
        .expect(
            "systemd-analyze (Debian package systemd) must be installed: deploy/setup installs it",
        );
    let stderr = String::from_utf8_lossy(&out.stderr);
    // Only our units matter: ignore complaints about units of the host system.
    let ours: Vec<&str> = stderr.lines().filter(|l| l.contains("doorslam")).collect();
    assert!(
        out.status.success() && ours.is_empty(),
        "systemd-analyze verify:\n{stderr}"
    );
}
