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
    let start = Instant::now();
    let t0 = dataset.frames.first().map_or(0, |f| f.stamp_ns);
    let mut report = ReplayReport::default();
    for k in 0..dataset.len() {
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
            if let Some(wait) = due.checked_sub(start.elapsed()) {
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
            seq: report.published,
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
    }
    tracing::info!(
        published = report.published,
        seconds = start.elapsed().as_secs_f64(),
        "replay: finished"
    );
    lifecycle.stopping();
    Ok(report)
}
