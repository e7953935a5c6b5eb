//! `doorslam vo DIR`: stereo visual odometry over a KITTI-layout folder (KITTI odometry or
//! `doorslam sim world` output) or an EuRoC folder (rectified on the fly); writes every
//! frame's pose in KITTI format, and with `--keyframes` each keyframe's verification packet.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use doorslam_frontend::run::{
    edge_nees, endpoint_drift, kitti_text, quantile, run_dataset, EdgeNees,
};
use doorslam_frontend::{Detector, VoConfig};

#[derive(Debug, Args)]
pub struct VoArgs {
    /// Dataset folder: KITTI layout (image_0/, image_1/, calib.txt, optional times.txt and
    /// poses.txt) or EuRoC ([mav0/]cam0/data, cam1/data, cam0/sensor.yaml, cam1/sensor.yaml:
    /// rectified with maps computed once).
    pub dir: PathBuf,
    /// Write each keyframe's verification packet (the wire message another robot would
    /// receive) into this folder as kf_NNNNNN.bin, plus keyframes.txt (id frame segment
    /// pose); `doorslam verify` reads them.
    #[arg(long, value_name = "OUTDIR")]
    pub keyframes: Option<PathBuf>,
    /// Write the estimated pose of every frame here (KITTI format: 12 numbers per line, one
    /// line per frame; a lost frame repeats the last estimated pose).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also write the pairs as the odometry sees them (rectified for EuRoC) into this
    /// folder in KITTI layout (image_0/, image_1/, calib.txt, times.txt, poses.txt), so
    /// another odometry can run on exactly the same frames.
    #[arg(long, value_name = "OUTDIR")]
    pub export_rectified: Option<PathBuf>,
    /// Print one JSON object on stdout instead of a summary line.
    #[arg(long)]
    pub json: bool,
    /// OpenCV worker threads (the robot's budget is one core).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Odometry settings (TOML with any fields of the front-end's VoConfig).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Keypoint detector: gftt (default), fast or orb.
    #[arg(long)]
    pub detector: Option<String>,
}

pub fn run(a: VoArgs) -> Result<()> {
    let mut config: VoConfig = match &a.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
        }
        None => VoConfig::default(),
    };
    if let Some(t) = a.threads {
        config.threads = t;
    }
    if let Some(d) = &a.detector {
        config.detector = match d.as_str() {
            "gftt" => Detector::Gftt,
            "fast" => Detector::Fast,
            "orb" => Detector::Orb,
            other => anyhow::bail!("--detector {other}: expected gftt, fast or orb"),
        };
    }
    config.validate().context("odometry settings")?;
    let dataset = doorslam_dataset::Dataset::open(&a.dir)
        .with_context(|| format!("opening {}", a.dir.display()))?;
    if let Some(out) = &a.export_rectified {
        let n = dataset
            .write_kitti_layout(out)
            .with_context(|| format!("writing the rectified pairs to {}", out.display()))?;
        eprintln!("vo: {n} rectified pairs written to {}", out.display());
    }
    let step = dataset.len().div_ceil(10).max(1);
    let progress = |done: usize, total: usize| {
        if done.is_multiple_of(step) || done == total {
            eprintln!("vo: {done}/{total} frames");
        }
    };
    let detector = config.detector;
    let threads = config.threads;
    let report = run_dataset(&dataset, config, &progress)
        .with_context(|| format!("visual odometry on {}", a.dir.display()))?;
    if let Some(out) = &a.out {
        std::fs::write(out, kitti_text(&report.poses))
            .with_context(|| format!("writing {}", out.display()))?;
    }
    let packet_bytes = match &a.keyframes {
        Some(dir) => Some(
            doorslam_frontend::packet::write_keyframe_packets(
                dir,
                &report.calibration,
                &report.keyframes,
            )
            .with_context(|| format!("writing keyframe packets to {}", dir.display()))?,
        ),
        None => None,
    };
    let drift = dataset
        .truth
        .as_ref()
        .and_then(|t| endpoint_drift(&report.poses, t));
    let median = quantile(&report.ms_per_frame, 0.5).unwrap_or(0.0);
    let p90 = quantile(&report.ms_per_frame, 0.9).unwrap_or(0.0);
    let cpu_median = quantile(&report.cpu_ms_per_frame, 0.5).unwrap_or(0.0);
    let s = report.stats;
    if a.json {
        let mut v = serde_json::json!({
            "frames": s.frames,
            "keyframes": s.keyframes,
            "lost": s.lost,
            "segments": s.segments,
            "time_s": report.time_s,
            "ms_per_frame_median": median,
            "ms_per_frame_p90": p90,
            "lost_frames": s.lost_frames,
            "cpu_ms_per_frame_median": quantile(&report.cpu_ms_per_frame, 0.5).unwrap_or(0.0),
            "cpu_ms_per_frame_p90": quantile(&report.cpu_ms_per_frame, 0.9).unwrap_or(0.0),
            "cpu_ms_per_frame_mean": report.cpu_ms_per_frame.iter().sum::<f64>() / report.cpu_ms_per_frame.len().max(1) as f64,
            "cpu_ms_per_frame_by_stage": report
                .stages
                .entries()
                .iter()
                .map(|&(name, ms)| (name.to_string(), serde_json::Value::from(ms / s.frames.max(1) as f64)))
                .collect::<serde_json::Map<_, _>>(),
            "edges": report.edges.len(),
            "ms_per_frame_mean": report.ms_per_frame.iter().sum::<f64>() / report.ms_per_frame.len().max(1) as f64,
            "load_ms_per_frame_median": quantile(&report.load_ms_per_frame, 0.5).unwrap_or(0.0),
            "lost_by_reason": s
                .lost_by_reason
                .entries()
                .iter()
                .map(|&(name, n)| (name.to_string(), serde_json::Value::from(n)))
                .collect::<serde_json::Map<_, _>>(),
            "detector": format!("{detector:?}").to_lowercase(),
            "threads": threads,
        });
        if let Some(truth) = &dataset.truth {
            let index: Vec<usize> = dataset.frames.iter().map(|f| f.index).collect();
            let nees = edge_nees(&report.keyframes, &report.edges, &index, truth);
            if !nees.is_empty() {
                let mean =
                    |f: fn(&EdgeNees) -> f64| nees.iter().map(f).sum::<f64>() / nees.len() as f64;
                let total: Vec<f64> = nees.iter().map(|n| n.total).collect();
                v["edge_nees_mean"] = mean(|n| n.total).into();
                v["edge_nees_median"] = quantile(&total, 0.5).unwrap_or(0.0).into();
                // 3 dof each: expected 3 when consistent.
                v["edge_nees_rotation_mean"] = mean(|n| n.rotation).into();
                v["edge_nees_translation_mean"] = mean(|n| n.translation).into();
            }
        }
        if let Some(d) = drift {
            v["distance_m"] = d.distance_m.into();
            v["endpoint_error_m"] = d.endpoint_error_m.into();
            v["drift_percent"] = d.percent.into();
        }
        if let Some(out) = &a.out {
            v["out"] = out.display().to_string().into();
        }
        if let Some(bytes) = packet_bytes {
            v["keyframe_packet_bytes_mean"] =
                (bytes as f64 / report.keyframes.len().max(1) as f64).into();
        }
        println!("{v}");
    } else {
        let drift = drift
            .map(|d| {
                format!(
                    ", end-point drift {:.2} m over {:.1} m ({:.2} %)",
                    d.endpoint_error_m, d.distance_m, d.percent
                )
            })
            .unwrap_or_default();
        println!(
            "{}: {} frames, {} keyframes, {} segment(s), lost {} time(s) ({} frames); {median:.1} ms/frame median ({cpu_median:.1} ms CPU), {p90:.1} p90{drift}",
            a.dir.display(),
            s.frames,
            s.keyframes,
            s.segments,
            s.lost,
            s.lost_frames
        );
    }
    Ok(())
}
