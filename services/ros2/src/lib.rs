//! A robot's state as ROS 2 messages, without ROS: the record of a finished run as MCAP
//! ([`record`], `doorslam ros2 record`), the replay of a finished run over Zenoh
//! ([`replay`], `doorslam ros2 replay`) and the live publishers of a running robot
//! ([`live`], `doorslam service ros2`, `[ros2]` of `robot.toml`). Its inputs are the files
//! a back-end leaves in its state folder ([`state`]); the payloads, type hashes and
//! rmw_zenoh's names come from `doorslam-ros2-wire`, the Zenoh side is [`session`].

pub mod live;
pub mod messages;
pub mod record;
pub mod replay;
pub mod session;
pub mod state;

pub use live::Ros2Section;
pub use session::LiveError;
pub use state::RecordError;

use std::path::PathBuf;

/// The set-up's Python (`$DOORSLAM_HOME/venv/bin/python`, default under
/// `~/.cache/doorslam`) when it imports every one of `modules`: what the ROS 2 checks of
/// `tests/ros2/` decode with (decoders that are not ours). `Err` says what is missing.
pub fn reference_python(modules: &[&str]) -> Result<PathBuf, String> {
    let home = std::env::var_os("DOORSLAM_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/doorslam")));
    let python = home
        .map(|h| h.join("venv/bin/python"))
        .filter(|p| p.is_file())
        .ok_or("no set-up venv (run deploy/setup)")?;
    let imports = format!("import {}", modules.join(", "));
    let has = std::process::Command::new(&python)
        .args(["-c", &imports])
        .status()
        .is_ok_and(|s| s.success());
    if has {
        Ok(python)
    } else {
        Err(format!(
            "{} cannot {imports} (run deploy/setup)",
            python.display()
        ))
    }
}
