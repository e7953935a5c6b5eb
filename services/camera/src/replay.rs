//! The replay source: a dataset folder played into the robot's frame service, at real
//! time, faster, or as fast as possible, with ground truth in the frame header when known.
//! Frames go out rectified: a dataset that is not rectified on disk (EuRoC) goes through
//! its rectifier (`Dataset::rectifier`), so subscribers use the rectified calibration.

use std::time::{Duration, Instant};

use doorslam_dataset::Dataset;
use doorslam_ipc::{
    create_node, FrameHeader, Lifecycle, Sender, StereoFrame, Topic, FRAME_HAS_TRUTH,
};

use crate::{CameraError, ReplayConfig};

/// What a replay did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReplayReport {
    pub published: u64,
    /// Frames whose time had passed when the replay (re)started (`start_unix_ms`).
    pub skipped: u64,
}

/// What the replay's status file says (`[camera.replay] status_file`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReplayStatus {
    /// Frames in the dataset (or its part).
    pub frames: u64,
    pub published: u64,
    /// Frames skipped because their time had passed by more than a frame period (a
    /// replay that starts late or falls behind: what a camera loses while the machine
    /// cannot keep up).
    pub skipped: u64,
    /// How long after its due time each published frame went out (ms): median, 90th
    /// percentile, largest. 0 without a clock.
    pub late_ms_median: f64,
    pub late_ms_p90: f64,
    pub late_ms_max: f64,
    /// The replay has played its last frame.
    pub finished: bool,
}

impl ReplayStatus {
    fn new(frames: usize, report: &ReplayReport, late_ms: &[f64], finished: bool) -> Self {
        let mut sorted = late_ms.to_vec();
        sorted.sort_by(f64::total_cmp);
        let at = |q: f64| {
            if sorted.is_empty() {
                0.0
            } else {
                sorted[((sorted.len() - 1) as f64 * q).round() as usize]
            }
        };
        ReplayStatus {
            frames: frames as u64,
            published: report.published,
            skipped: report.skipped,
            late_ms_median: at(0.5),
            late_ms_p90: at(0.9),
            late_ms_max: sorted.last().copied().unwrap_or(0.0),
            finished,
        }
    }

    /// Writes the file whole (a temporary file renamed over it: readers never see half).
    fn write(&self, path: &std::path::Path) {
        let tmp = path.with_extension("json.tmp");
        let text = serde_json::to_string_pretty(self).unwrap_or_default();
        if std::fs::write(&tmp, text)
            .and_then(|_| std::fs::rename(&tmp, path))
            .is_err()
        {
            tracing::warn!(path = %path.display(), "replay: cannot write the status file");
        }
    }
}

/// The local instant of a wall-clock time in Unix milliseconds (past or future).
fn instant_of_unix_ms(unix_ms: u64) -> Instant {
    let now_ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64);
    let now = Instant::now();
    if unix_ms <= now_ms {
        now.checked_sub(Duration::from_millis(now_ms - unix_ms))
            .unwrap_or(now)
    } else {
        now + Duration::from_millis(unix_ms - now_ms)
    }
}

/// Plays the dataset once, then returns.
pub fn run(
    config: &ReplayConfig,
    robot: &str,
    robot_index: u32,
) -> Result<ReplayReport, CameraError> {
    let mut dataset = Dataset::open(&config.path)?;
    if let Some(truth) = &config.truth {
        dataset = dataset.with_truth(truth)?;
    }
    if let Some([part, parts]) = config.split {
        dataset = dataset.split(part, parts)?;
    }
    let rectifier = dataset.rectifier()?;
    tracing::info!(path = %config.path.display(), rectified_here = rectifier.is_some(), layout = ?dataset.layout, frames = dataset.len(), truth = dataset.truth.is_some(), rate = config.rate, "replay: dataset opened");
    let (node, _) = create_node("doorslam-camera-replay")?;
    let sender = Sender::<StereoFrame>::new(&node, robot, Topic::Frames)?;
    let mut lifecycle = Lifecycle::new();
    // Frames are lossy by design: wait for someone to listen before playing.
    let deadline = Instant::now() + Duration::from_secs_f64(config.wait_for_subscribers_s);
    while sender.receivers() == 0 && Instant::now() < deadline && lifecycle.keep_going(&node) {
        std::thread::sleep(Duration::from_millis(10));
    }
    if sender.receivers() == 0 {
        tracing::warn!(
            "replay: no subscriber after {} s, playing anyway",
            config.wait_for_subscribers_s
        );
    }
    lifecycle.ready(&format!("replaying {}", config.path.display()));
    let clocked = config.start_unix_ms.is_some() && config.rate > 0.0 && !config.step;
    let start = match config.start_unix_ms {
        Some(ms) if clocked => instant_of_unix_ms(ms),
        _ => Instant::now(),
    };
    // A frame more than this late is skipped on a shared clock (the camera was off).
    let period = match dataset.frames.as_slice() {
        [a, b, ..] => Duration::from_nanos(b.stamp_ns.saturating_sub(a.stamp_ns)),
        _ => Duration::ZERO,
    };
    let t0 = dataset.frames.first().map_or(0, |f| f.stamp_ns);
    let mut report = ReplayReport::default();
    let mut late_ms: Vec<f64> = Vec::new();
    let mut last_status = Instant::now();
    for k in 0..dataset.len() {
        if let Some(path) = &config.status_file {
            if last_status.elapsed() >= Duration::from_secs(1) {
                last_status = Instant::now();
                ReplayStatus::new(dataset.len(), &report, &late_ms, false).write(path);
            }
        }
        if !lifecycle.keep_going(&node) {
            break;
        }
        let f = &dataset.frames[k];
        if config.step {
            let mut line = String::new();
            eprintln!(
                "replay: frame {k} of {} ready, press Enter to publish it",
                dataset.len()
            );
            if std::io::stdin()
                .read_line(&mut line)
                .map_or(true, |n| n == 0)
            {
                break;
            }
        } else if config.rate > 0.0 {
            // The rate is bounded by the config check; a dataset spanning more than
            // Duration's range would simply never be due.
            let due = Duration::try_from_secs_f64(
                f.stamp_ns.saturating_sub(t0) as f64 * 1e-9 / config.rate,
            )
            .unwrap_or(Duration::MAX);
            let now = Instant::now().saturating_duration_since(start);
            if clocked && now > due.saturating_add(period.mul_f64(1.0 / config.rate)) {
                report.skipped += 1;
                continue;
            }
            if let Some(wait) = due.checked_sub(now) {
                std::thread::sleep(wait);
            }
        }
        let pair = dataset.load(k)?;
        let pair = match &rectifier {
            Some(r) => r.rectify(&pair)?,
            None => pair,
        };
        let truth = dataset
            .truth
            .as_ref()
            .map(|t| doorslam_geometry::pose_to_array(&t[k]));
        let header = FrameHeader {
            // The dataset index: strictly increasing, and on a shared clock a restarted
            // replay continues the numbering of the frames it skipped.
            seq: k as u64,
            stamp_ns: f.stamp_ns,
            robot: robot_index,
            camera: 0,
            width: pair.width,
            height: pair.height,
            flags: if truth.is_some() { FRAME_HAS_TRUTH } else { 0 },
            reserved: 0,
            truth_pose: truth.unwrap_or_default(),
        };
        sender.send_with(|slot| StereoFrame::write(slot, header, &pair.left, &pair.right))?;
        report.published += 1;
        if clocked {
            let due = f.stamp_ns.saturating_sub(t0) as f64 * 1e-9 / config.rate;
            let now = Instant::now()
                .saturating_duration_since(start)
                .as_secs_f64();
            late_ms.push(((now - due) * 1e3).max(0.0));
        }
    }
    if let Some(path) = &config.status_file {
        ReplayStatus::new(dataset.len(), &report, &late_ms, true).write(path);
    }
    if report.skipped > 0 {
        tracing::warn!(
            skipped = report.skipped,
            "replay: frames whose time had passed on the shared clock were skipped"
        );
    }
    tracing::info!(
        published = report.published,
        seconds = start.elapsed().as_secs_f64(),
        "replay: finished"
    );
    lifecycle.stopping();
    Ok(report)
}
