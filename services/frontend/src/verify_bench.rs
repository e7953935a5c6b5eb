//! The verification benchmark (`doorslam verify --bench DIR`): geometric verification of
//! pairs whose true relative pose is known, on the full-precision features and on the wire
//! packet the remote robot would send, side by side.
//!
//! Two kinds of folder:
//! - a `doorslam sim world` output: every row of `closures.csv` (`overlap`: two drones saw
//!   the same place, a true closure; `aliased`: two copies of one building design seen from
//!   the same relative viewpoint, a false closure that verification may well accept, which
//!   is PCM's job), ground truth from each robot's `poses.txt`;
//! - EuRoC's loop-closure pairs (`left_img_N.png`, `right_img_N.png`, `sensorLeft.yaml`,
//!   `sensorRight.yaml`, `ground_truth_poses.txt` of the body): pairs (0, 1) and (2, 3),
//!   rectified, ground truth moved from the body to the rectified left camera.
//!
//! In a pair `(a, b)`, `a` is the remote keyframe (its features come as a packet) and `b`
//! the local one; the estimate is `X_a⁻¹ X_b`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use doorslam_dataset::StereoCalibration;
use doorslam_dataset::{read_gray_png, Dataset, DatasetError, EurocCamera, Pair, Rectifier};
use doorslam_geometry::{LieGroup, SE3};
use doorslam_ipc::wire::RobotId;
use nalgebra::{Quaternion, Translation3, UnitQuaternion};

use crate::config::VoConfig;
use crate::error::FrontendError;
use crate::keyframe::Feature;
use crate::packet::{from_packet, packet_file_bytes, to_packet, PacketError, MAX_PACKET_FEATURES};
use crate::verify::{verify, Rejection, Verified, VerifyConfig};
use crate::vo::StereoVo;
use doorslam_vision::Gray;

/// Failures of reading a benchmark folder.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Frontend(#[from] FrontendError),
    #[error(transparent)]
    Packet(#[from] PacketError),
    #[error("{path}:{line}: {msg}")]
    Line {
        path: PathBuf,
        line: usize,
        msg: String,
    },
    #[error("{path}: neither a `doorslam sim world` output (closures.csv) nor EuRoC loop-closure pairs (ground_truth_poses.txt)")]
    UnknownFolder { path: PathBuf },
}

/// What a pair is, by ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum PairKind {
    /// Two views of the same place (simulated overlap, or a real loop closure).
    Overlap,
    /// Two copies of one design: looks like a closure, is not one.
    Aliased,
}

impl PairKind {
    pub fn as_str(self) -> &'static str {
        match self {
            PairKind::Overlap => "overlap",
            PairKind::Aliased => "aliased",
        }
    }
}

/// One verified pair.
#[derive(Debug, Clone)]
pub struct PairOutcome {
    pub label: String,
    pub kind: PairKind,
    /// True `X_a⁻¹ X_b` (for aliased pairs: of the two cameras in the world, which the
    /// estimate cannot match).
    pub truth: SE3,
    pub full: Result<Verified, Rejection>,
    pub packet: Result<Verified, Rejection>,
    pub full_ms: f64,
    pub packet_ms: f64,
    /// Features of the remote keyframe, and in its packet.
    pub features: usize,
    pub packet_features: usize,
    pub packet_bytes: usize,
}

/// Rotation (degrees) and translation (m) error of an estimate against the truth.
pub fn pose_error(truth: &SE3, estimate: &SE3) -> (f64, f64) {
    let e = (truth.inverse() * estimate).log();
    (
        e.fixed_rows::<3>(0).norm().to_degrees(),
        e.fixed_rows::<3>(3).norm(),
    )
}

/// Keyframe features of stereo pairs, computed once per frame.
struct Features {
    vo: StereoVo,
    cache: BTreeMap<(String, usize), Vec<Feature>>,
}

impl Features {
    fn of(
        &mut self,
        key: (String, usize),
        pair: impl FnOnce() -> Result<Pair, BenchError>,
    ) -> Result<&[Feature], BenchError> {
        if !self.cache.contains_key(&key) {
            let pair = pair()?;
            let (w, h) = (pair.width as usize, pair.height as usize);
            let left = Gray::new(w, h, &pair.left).map_err(FrontendError::from)?;
            let right = Gray::new(w, h, &pair.right).map_err(FrontendError::from)?;
            let features = self.vo.keyframe_features(&left, &right)?;
            self.cache.insert(key.clone(), features);
        }
        Ok(self.cache[&key].as_slice())
    }
}

fn verify_pair(
    label: String,
    kind: PairKind,
    truth: SE3,
    calib: &StereoCalibration,
    remote: &[Feature],
    local: &[Feature],
    config: &VerifyConfig,
) -> Result<PairOutcome, BenchError> {
    let t0 = Instant::now();
    let full = verify(calib, local, calib, remote, config);
    let full_ms = t0.elapsed().as_secs_f64() * 1e3;
    // Robot 'a', keyframe 0: a valid key; the size does not depend on which.
    let key = (b'a' as u64) << 56;
    let packet = to_packet(key, calib, remote, MAX_PACKET_FEATURES)?;
    let sender = RobotId::new("bench").map_err(PacketError::Sender)?;
    let packet_bytes = packet_file_bytes(&sender, 0, packet.clone())?.len();
    let t1 = Instant::now();
    let (remote_calib, received) = from_packet(&packet, config.disparity_sigma_px);
    let quantized = verify(calib, local, &remote_calib, &received, config);
    let packet_ms = t1.elapsed().as_secs_f64() * 1e3;
    Ok(PairOutcome {
        label,
        kind,
        truth,
        full,
        packet: quantized,
        full_ms,
        packet_ms,
        features: remote.len(),
        packet_features: packet.features.len(),
        packet_bytes,
    })
}

/// Verifies every pair of a benchmark folder (at most `limit` of each kind, in file
/// order); `progress(done, total)` hears about each.
pub fn bench_folder(
    dir: &Path,
    vo_config: &VoConfig,
    config: &VerifyConfig,
    limit: Option<usize>,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<PairOutcome>, BenchError> {
    if dir.join("closures.csv").is_file() {
        bench_sim(dir, vo_config, config, limit, progress)
    } else if dir.join("ground_truth_poses.txt").is_file() {
        bench_euroc_pairs(dir, vo_config, config, progress)
    } else {
        Err(BenchError::UnknownFolder {
            path: dir.to_path_buf(),
        })
    }
}

fn bench_sim(
    dir: &Path,
    vo_config: &VoConfig,
    config: &VerifyConfig,
    limit: Option<usize>,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<PairOutcome>, BenchError> {
    let csv = dir.join("closures.csv");
    let text = std::fs::read_to_string(&csv).map_err(|source| DatasetError::Io {
        path: csv.clone(),
        source,
    })?;
    let line_err = |line: usize, msg: String| BenchError::Line {
        path: csv.clone(),
        line,
        msg,
    };
    let mut rows = Vec::new();
    let mut per_kind: BTreeMap<PairKind, usize> = BTreeMap::new();
    for (n, row) in text.lines().enumerate().skip(1) {
        if row.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = row.trim().split(',').collect();
        let [ra, fa, rb, fb, kind] = f[..] else {
            return Err(line_err(
                n + 1,
                "expected robot_a,frame_a,robot_b,frame_b,kind".into(),
            ));
        };
        let kind = match kind {
            "overlap" => PairKind::Overlap,
            "aliased" => PairKind::Aliased,
            other => return Err(line_err(n + 1, format!("unknown kind {other:?}"))),
        };
        let frame = |s: &str| {
            s.parse::<usize>()
                .map_err(|_| line_err(n + 1, format!("{s:?} is not a frame number")))
        };
        let count = per_kind.entry(kind).or_default();
        if limit.is_some_and(|l| *count >= l) {
            continue;
        }
        *count += 1;
        rows.push((ra.to_string(), frame(fa)?, rb.to_string(), frame(fb)?, kind));
    }
    let mut datasets: BTreeMap<String, Dataset> = BTreeMap::new();
    let mut calib = None;
    for (ra, _, rb, _, _) in &rows {
        for r in [ra, rb] {
            if !datasets.contains_key(r) {
                let d = Dataset::open(&dir.join(r))?;
                if d.truth.is_none() {
                    return Err(BenchError::Dataset(DatasetError::Layout {
                        path: dir.join(r),
                        msg: "no poses.txt: the benchmark needs ground truth".into(),
                    }));
                }
                calib.get_or_insert(d.calibration()?);
                datasets.insert(r.clone(), d);
            }
        }
    }
    let Some(calib) = calib else {
        return Ok(Vec::new());
    };
    let mut features = Features {
        vo: StereoVo::new(calib, vo_config.clone())?,
        cache: BTreeMap::new(),
    };
    let mut out = Vec::with_capacity(rows.len());
    for (i, (ra, fa, rb, fb, kind)) in rows.iter().enumerate() {
        let (da, db) = (&datasets[ra], &datasets[rb]);
        let pose = |d: &Dataset, f: usize, r: &str| {
            d.frames
                .iter()
                .position(|x| x.index == f)
                .and_then(|k| d.truth.as_ref().map(|t| (k, t[k])))
                .ok_or_else(|| line_err(i + 2, format!("robot {r} has no frame {f}")))
        };
        let (ka, xa) = pose(da, *fa, ra)?;
        let (kb, xb) = pose(db, *fb, rb)?;
        let remote = features
            .of((ra.clone(), *fa), || Ok(da.load(ka)?))?
            .to_vec();
        let local = features
            .of((rb.clone(), *fb), || Ok(db.load(kb)?))?
            .to_vec();
        out.push(verify_pair(
            format!("{ra}{fa}-{rb}{fb}"),
            *kind,
            xa.inverse() * xb,
            &calib,
            &remote,
            &local,
            config,
        )?);
        progress(i + 1, rows.len());
    }
    Ok(out)
}

fn bench_euroc_pairs(
    dir: &Path,
    vo_config: &VoConfig,
    config: &VerifyConfig,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<PairOutcome>, BenchError> {
    let left = EurocCamera::from_yaml(&dir.join("sensorLeft.yaml"))?;
    let right = EurocCamera::from_yaml(&dir.join("sensorRight.yaml"))?;
    let rectifier = Rectifier::new(&left, &right, &dir.join("sensorRight.yaml"))?;
    let gt_path = dir.join("ground_truth_poses.txt");
    let text = std::fs::read_to_string(&gt_path).map_err(|source| DatasetError::Io {
        path: gt_path.clone(),
        source,
    })?;
    // image_index role timestamp tx ty tz qx qy qz qw: the body's pose in the world.
    let mut body: BTreeMap<usize, SE3> = BTreeMap::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        let v: Option<Vec<f64>> = f
            .get(3..10)
            .map(|s| s.iter().filter_map(|x| x.parse().ok()).collect());
        let (Some(index), Some(v)) = (f.first().and_then(|s| s.parse::<usize>().ok()), v) else {
            return Err(BenchError::Line {
                path: gt_path.clone(),
                line: n + 1,
                msg: "expected: index role timestamp tx ty tz qx qy qz qw".into(),
            });
        };
        if v.len() != 7 || v.iter().any(|x| !x.is_finite()) {
            return Err(BenchError::Line {
                path: gt_path.clone(),
                line: n + 1,
                msg: "expected 7 finite numbers after index, role and timestamp".into(),
            });
        }
        let q = UnitQuaternion::from_quaternion(Quaternion::new(v[6], v[3], v[4], v[5]));
        body.insert(
            index,
            SE3::from_parts(Translation3::new(v[0], v[1], v[2]), q),
        );
    }
    let camera = rectifier.body_from_rectified();
    let calib = rectifier.calibration();
    let mut features = Features {
        vo: StereoVo::new(calib, vo_config.clone())?,
        cache: BTreeMap::new(),
    };
    let load = |i: usize| -> Result<Pair, BenchError> {
        let (w, h, l) = read_gray_png(&dir.join(format!("left_img_{i}.png")))?;
        let (_, _, r) = read_gray_png(&dir.join(format!("right_img_{i}.png")))?;
        Ok(rectifier.rectify(&Pair {
            width: w,
            height: h,
            left: l,
            right: r,
        })?)
    };
    let pairs = [(0usize, 1usize), (2, 3)];
    let mut out = Vec::new();
    for (i, &(a, b)) in pairs.iter().enumerate() {
        let truth_of = |k: usize| {
            body.get(&k)
                .map(|x| x * camera)
                .ok_or_else(|| BenchError::Line {
                    path: gt_path.clone(),
                    line: 0,
                    msg: format!("no pose of image {k}"),
                })
        };
        let (xa, xb) = (truth_of(a)?, truth_of(b)?);
        let remote = features.of(("euroc".into(), a), || load(a))?.to_vec();
        let local = features.of(("euroc".into(), b), || load(b))?.to_vec();
        out.push(verify_pair(
            format!("euroc {a}-{b}"),
            PairKind::Overlap,
            xa.inverse() * xb,
            &calib,
            &remote,
            &local,
            config,
        )?);
        progress(i + 1, pairs.len());
    }
    Ok(out)
}

/// Statistics of one kind of pair, for one form of the remote features.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FormSummary {
    pub accepted: usize,
    /// Of accepted pairs: inliers (median), rotation (degrees) and translation (m) error
    /// against the truth (median, 90th percentile, maximum).
    pub inliers_median: f64,
    pub rotation_error_deg_median: f64,
    pub rotation_error_deg_p90: f64,
    pub rotation_error_deg_max: f64,
    pub translation_error_m_median: f64,
    pub translation_error_m_p90: f64,
    pub translation_error_m_max: f64,
    /// Time per verification (ms), accepted or not.
    pub ms_median: f64,
    pub ms_p90: f64,
    /// Rejections by reason.
    pub rejected: BTreeMap<String, usize>,
}

/// One kind of pair, full features and packet side by side.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct KindSummary {
    pub pairs: usize,
    pub full: FormSummary,
    pub packet: FormSummary,
    /// Pairs accepted in both forms: how far the packet's estimate is from the full
    /// features' (degrees, m; median and maximum).
    pub packet_vs_full_rotation_deg_median: f64,
    pub packet_vs_full_rotation_deg_max: f64,
    pub packet_vs_full_translation_m_median: f64,
    pub packet_vs_full_translation_m_max: f64,
}

/// The benchmark's figures.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct BenchSummary {
    pub overlap: KindSummary,
    pub aliased: KindSummary,
    pub features_mean: f64,
    pub packet_features_mean: f64,
    pub packet_bytes_mean: f64,
    pub packet_bytes_max: usize,
}

fn quantile(values: &[f64], q: f64) -> f64 {
    crate::run::quantile(values, q).unwrap_or(0.0)
}

fn form_summary<'a>(
    outcomes: impl Iterator<Item = (&'a PairOutcome, &'a Result<Verified, Rejection>, f64)>,
) -> FormSummary {
    let mut s = FormSummary::default();
    let (mut inliers, mut rot, mut trans, mut ms) = (vec![], vec![], vec![], vec![]);
    for (o, result, time) in outcomes {
        ms.push(time);
        match result {
            Ok(v) => {
                s.accepted += 1;
                inliers.push(v.inliers as f64);
                let (r, t) = pose_error(&o.truth, &v.relative);
                rot.push(r);
                trans.push(t);
            }
            Err(e) => *s.rejected.entry(e.name().to_string()).or_default() += 1,
        }
    }
    s.inliers_median = quantile(&inliers, 0.5);
    s.rotation_error_deg_median = quantile(&rot, 0.5);
    s.rotation_error_deg_p90 = quantile(&rot, 0.9);
    s.rotation_error_deg_max = quantile(&rot, 1.0);
    s.translation_error_m_median = quantile(&trans, 0.5);
    s.translation_error_m_p90 = quantile(&trans, 0.9);
    s.translation_error_m_max = quantile(&trans, 1.0);
    s.ms_median = quantile(&ms, 0.5);
    s.ms_p90 = quantile(&ms, 0.9);
    s
}

fn kind_summary(outcomes: &[&PairOutcome]) -> KindSummary {
    let (mut dr, mut dt) = (vec![], vec![]);
    for o in outcomes {
        if let (Ok(f), Ok(p)) = (&o.full, &o.packet) {
            let (r, t) = pose_error(&f.relative, &p.relative);
            dr.push(r);
            dt.push(t);
        }
    }
    KindSummary {
        pairs: outcomes.len(),
        full: form_summary(outcomes.iter().map(|o| (*o, &o.full, o.full_ms))),
        packet: form_summary(outcomes.iter().map(|o| (*o, &o.packet, o.packet_ms))),
        packet_vs_full_rotation_deg_median: quantile(&dr, 0.5),
        packet_vs_full_rotation_deg_max: quantile(&dr, 1.0),
        packet_vs_full_translation_m_median: quantile(&dt, 0.5),
        packet_vs_full_translation_m_max: quantile(&dt, 1.0),
    }
}

/// The figures of a benchmark run.
pub fn summarize(outcomes: &[PairOutcome]) -> BenchSummary {
    let of = |k: PairKind| outcomes.iter().filter(|o| o.kind == k).collect::<Vec<_>>();
    let n = outcomes.len().max(1) as f64;
    BenchSummary {
        overlap: kind_summary(&of(PairKind::Overlap)),
        aliased: kind_summary(&of(PairKind::Aliased)),
        features_mean: outcomes.iter().map(|o| o.features as f64).sum::<f64>() / n,
        packet_features_mean: outcomes
            .iter()
            .map(|o| o.packet_features as f64)
            .sum::<f64>()
            / n,
        packet_bytes_mean: outcomes.iter().map(|o| o.packet_bytes as f64).sum::<f64>() / n,
        packet_bytes_max: outcomes.iter().map(|o| o.packet_bytes).max().unwrap_or(0),
    }
}
