//! The odometry over a dataset folder (what `doorslam vo` runs): every frame's pose, the
//! keyframes and edges, per-frame timing, and the end-point drift against ground truth.

use std::fmt::Write as _;
use std::time::Instant;

use doorslam_dataset::{Dataset, DatasetError};
use doorslam_geometry::SE3;

use crate::config::VoConfig;
use crate::error::FrontendError;
use crate::keyframe::{Keyframe, OdometryEdge, SegmentLink};
use crate::vo::{StageCpu, StereoVo, TrackState, VoStats};
use doorslam_vision::Gray;

/// Failures of a dataset run.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Frontend(#[from] FrontendError),
    #[error("{path}: no frames")]
    Empty { path: String },
}

/// Everything a run produced.
#[derive(Debug, Clone)]
pub struct RunReport {
    /// The rectified calibration the odometry ran with.
    pub calibration: doorslam_dataset::StereoCalibration,
    /// One pose per frame. A lost frame repeats the last estimated pose (the identity
    /// before the first one); `tracked[k]` tells which frames have an estimate of their own.
    pub poses: Vec<SE3>,
    pub tracked: Vec<bool>,
    pub segments_of_frames: Vec<u32>,
    pub keyframes: Vec<Keyframe>,
    pub edges: Vec<OdometryEdge>,
    pub links: Vec<SegmentLink>,
    pub stats: VoStats,
    /// CPU time of the odometry's stages over the run.
    pub stages: StageCpu,
    /// Time of `StereoVo::process` per frame (ms), without decoding the images.
    pub ms_per_frame: Vec<f64>,
    /// CPU time of this thread in `StereoVo::process` per frame (ms): the cost on one core,
    /// unlike the wall time not inflated by other processes sharing the machine.
    pub cpu_ms_per_frame: Vec<f64>,
    /// Time of decoding the PNG pairs, and rectifying them when the dataset is not
    /// rectified (ms per frame).
    pub load_ms_per_frame: Vec<f64>,
    pub time_s: f64,
}

/// Runs the odometry on every frame of a dataset folder: KITTI layout (KITTI, `doorslam sim
/// world`: rectified on disk) or EuRoC (each pair rectified first, maps computed once;
/// the rectification is counted in the load time, not in the VO's); `progress(done,
/// total)` hears about every frame.
pub fn run_dataset(
    dataset: &Dataset,
    config: VoConfig,
    progress: &dyn Fn(usize, usize),
) -> Result<RunReport, RunError> {
    if dataset.is_empty() {
        return Err(RunError::Empty {
            path: dataset.root.display().to_string(),
        });
    }
    let stereo = dataset.stereo()?;
    let mut vo = StereoVo::new(stereo.calibration, config)?;
    let start = Instant::now();
    let n = dataset.len();
    let mut report = RunReport {
        calibration: stereo.calibration,
        poses: Vec::with_capacity(n),
        tracked: Vec::with_capacity(n),
        segments_of_frames: Vec::with_capacity(n),
        keyframes: Vec::new(),
        edges: Vec::new(),
        links: Vec::new(),
        stats: VoStats::default(),
        stages: StageCpu::default(),
        ms_per_frame: Vec::with_capacity(n),
        cpu_ms_per_frame: Vec::with_capacity(n),
        load_ms_per_frame: Vec::with_capacity(n),
        time_s: 0.0,
    };
    let mut last = SE3::identity();
    for k in 0..n {
        let t0 = Instant::now();
        let pair = stereo.prepare(dataset.load(k)?)?;
        let (w, h) = (pair.width as usize, pair.height as usize);
        let left = Gray::new(w, h, &pair.left).map_err(FrontendError::from)?;
        let right = Gray::new(w, h, &pair.right).map_err(FrontendError::from)?;
        let t1 = Instant::now();
        let c1 = thread_cpu_s();
        let files = &dataset.frames[k];
        let result = vo.process(files.index as u64, files.stamp_ns, &left, &right)?;
        let t2 = Instant::now();
        report.cpu_ms_per_frame.push((thread_cpu_s() - c1) * 1e3);
        report.load_ms_per_frame.push((t1 - t0).as_secs_f64() * 1e3);
        report.ms_per_frame.push((t2 - t1).as_secs_f64() * 1e3);
        if let Some(p) = result.pose {
            last = p;
        }
        report.poses.push(last);
        report.tracked.push(result.state != TrackState::Lost);
        report.segments_of_frames.push(result.segment);
        report.keyframes.extend(result.keyframe);
        report.edges.extend(result.edge);
        report.links.extend(result.link);
        progress(k + 1, n);
    }
    report.stats = vo.stats();
    report.stages = vo.stage_cpu();
    report.time_s = start.elapsed().as_secs_f64();
    Ok(report)
}

/// CPU time consumed by the calling thread (s), 0 if the clock is unavailable.
pub(crate) fn thread_cpu_s() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into the valid, exclusively borrowed `ts`.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc == 0 {
        ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
    } else {
        0.0
    }
}

/// Poses in KITTI's format: the top 3×4 of each camera-to-world matrix, row-major, one
/// line per pose.
pub fn kitti_text(poses: &[SE3]) -> String {
    let mut out = String::with_capacity(poses.len() * 160);
    for p in poses {
        let m = p.to_homogeneous();
        let mut first = true;
        for r in 0..3 {
            for c in 0..4 {
                if !first {
                    out.push(' ');
                }
                first = false;
                let _ = write!(out, "{:.9e}", m[(r, c)]);
            }
        }
        out.push('\n');
    }
    out
}

/// The `q`-quantile (0..=1) of `values` by nearest rank; `None` when empty.
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
    Some(v[rank - 1])
}

/// End-point drift of an estimated trajectory against ground truth, both expressed
/// relative to their first pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Drift {
    /// Length of the true path (m).
    pub distance_m: f64,
    /// Distance between the estimated and true end positions (m).
    pub endpoint_error_m: f64,
    /// `endpoint_error / distance`, in percent.
    pub percent: f64,
}

/// End-point drift (`None` for fewer than two poses or a path shorter than 1 cm).
pub fn endpoint_drift(estimate: &[SE3], truth: &[SE3]) -> Option<Drift> {
    let n = estimate.len().min(truth.len());
    if n < 2 {
        return None;
    }
    let distance_m: f64 = truth[..n]
        .windows(2)
        .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
        .sum();
    if distance_m < 0.01 {
        return None;
    }
    let est = estimate[0].inverse() * estimate[n - 1];
    let gt = truth[0].inverse() * truth[n - 1];
    let endpoint_error_m = (est.translation.vector - gt.translation.vector).norm();
    Some(Drift {
        distance_m,
        endpoint_error_m,
        percent: 100.0 * endpoint_error_m / distance_m,
    })
}

/// Normalized estimation error squared of one odometry edge against ground truth, in
/// total (6 dof) and split into its rotation and translation parts (3 dof each, against
/// the marginal covariances): which part is overconfident.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EdgeNees {
    pub total: f64,
    pub rotation: f64,
    pub translation: f64,
}

/// Normalized estimation error squared of every odometry edge against ground truth:
/// `rᵀ Ω r` with `r = Log(Z_true⁻¹ · Z)`. Its mean is 6 when the information matrices are
/// the inverse covariances of the actual errors; above 6 they are overconfident.
/// `truth[k]` is the true pose of the frame with index `frame_index[k]`.
pub fn edge_nees(
    keyframes: &[Keyframe],
    edges: &[OdometryEdge],
    frame_index: &[usize],
    truth: &[SE3],
) -> Vec<EdgeNees> {
    use doorslam_geometry::LieGroup;
    let position: std::collections::HashMap<u64, usize> = frame_index
        .iter()
        .enumerate()
        .map(|(pos, &index)| (index as u64, pos))
        .collect();
    let truth_of = |id: u64| {
        let kf = keyframes.iter().find(|k| k.id == id)?;
        truth.get(*position.get(&kf.frame)?)
    };
    edges
        .iter()
        .filter_map(|e| {
            let (a, b) = (truth_of(e.from)?, truth_of(e.to)?);
            let r = ((a.inverse() * b).inverse() * e.relative).log();
            let covariance = e.information.try_inverse()?;
            let part = |k: usize| {
                let c = covariance.fixed_view::<3, 3>(k, k).into_owned();
                let x = r.fixed_rows::<3>(k).into_owned();
                c.try_inverse().map(|w| (x.transpose() * w * x)[0])
            };
            Some(EdgeNees {
                total: (r.transpose() * e.information * r)[0],
                rotation: part(0)?,
                translation: part(3)?,
            })
        })
        .collect()
}
