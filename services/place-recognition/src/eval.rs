//! Precision-recall of inter-robot place matches against ground truth.
//!
//! Inputs (`doorslam place eval DIR...`):
//! - a `sim world` output (`closures.csv` + one KITTI folder per robot): positives are its
//!   `overlap` pairs, widened to the keyframes whose ground-truth poses are within
//!   [`SIM_WIDEN_M`] and [`SIM_WIDEN_DEG`] of the pair's own keyframe on each side; the
//!   `aliased` pairs (copies of a building elsewhere in the town) stay negatives;
//! - other folders (KITTI / EuRoC layout with ground truth), one robot each: positives
//!   are keyframes of different robots within [`POSE_MAX_M`] and [`POSE_MAX_DEG`].
//!
//! Every keyframe of every robot queries the keyframes of all other robots; its nearest
//! neighbour at distance `d` is a predicted match when `d` is below the threshold. Sweeping
//! the threshold gives the curve: precision = correct / predicted matches, recall =
//! correct / queries that have a positive. `recall_at_1` is the recall with no threshold.

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};

use doorslam_dataset::Dataset;
use nalgebra::Isometry3;

/// Widening of a simulated overlap pair to the neighbouring keyframes (each side).
pub const SIM_WIDEN_M: f64 = 2.0;
pub const SIM_WIDEN_DEG: f64 = 20.0;
/// Ground truth for real folders: same place when within this distance and angle.
pub const POSE_MAX_M: f64 = 10.0;
pub const POSE_MAX_DEG: f64 = 30.0;

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("{path}: {msg}")]
    Input { path: PathBuf, msg: String },
    #[error(transparent)]
    Dataset(#[from] doorslam_dataset::DatasetError),
}

/// One keyframe to describe: its image files and ground-truth pose.
#[derive(Debug, Clone)]
pub struct Keyframe {
    pub robot: String,
    pub frame: usize,
    /// The left image.
    pub image: PathBuf,
    /// The right image, when the folder is a stereo dataset (the front-end's features
    /// need both).
    pub right: Option<PathBuf>,
    pub pose: Isometry3<f64>,
}

/// Keyframes of all robots and the set of true inter-robot pairs (indices, both orders).
#[derive(Debug, Clone, Default)]
pub struct EvalSet {
    pub keyframes: Vec<Keyframe>,
    pub positives: HashSet<(usize, usize)>,
    /// The `overlap` rows of `sim world` outputs, each widened as the positives are: the
    /// keyframes of robot a near frame a, and of robot b near frame b (a true overlap, for
    /// `place eval --verify`'s recall).
    pub overlaps: Vec<(Vec<usize>, Vec<usize>)>,
    /// The `aliased` pairs widened the same way (both orders): negatives that look alike.
    pub aliased: HashSet<(usize, usize)>,
    /// Each robot's folder (its calibration), by robot name.
    pub robot_dirs: BTreeMap<String, PathBuf>,
    /// The `sim world` outputs read and their seed (`world.txt`), to check that no
    /// evaluation town was a training town of the model.
    pub sim_seeds: Vec<(PathBuf, u64)>,
}

fn near(a: &Isometry3<f64>, b: &Isometry3<f64>, max_m: f64, max_deg: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() <= max_m
        && a.rotation.angle_to(&b.rotation).to_degrees() <= max_deg
}

fn robot_keyframes(dir: &Path, robot: &str, stride: usize) -> Result<Vec<Keyframe>, EvalError> {
    let data = Dataset::open(dir)?;
    let truth = data.truth.as_ref().ok_or_else(|| EvalError::Input {
        path: dir.to_path_buf(),
        msg: "no ground truth (poses.txt) to evaluate against".into(),
    })?;
    Ok(data
        .frames
        .iter()
        .zip(truth)
        .step_by(stride.max(1))
        .map(|(f, pose)| Keyframe {
            robot: robot.to_string(),
            frame: f.index,
            image: f.left.clone(),
            right: Some(f.right.clone()),
            pose: *pose,
        })
        .collect())
}

impl EvalSet {
    /// Reads the folders (see the module documentation); every `stride`-th frame is a
    /// keyframe.
    pub fn load(dirs: &[PathBuf], stride: usize) -> Result<Self, EvalError> {
        let mut set = EvalSet::default();
        for (i, dir) in dirs.iter().enumerate() {
            let first = set.keyframes.len();
            if dir.join("closures.csv").is_file() {
                set.add_sim(dir, i, stride)?;
            } else {
                set.keyframes
                    .extend(robot_keyframes(dir, &format!("{i}"), stride)?);
                set.robot_dirs.insert(format!("{i}"), dir.clone());
            }
            if set.keyframes.len() == first {
                return Err(EvalError::Input {
                    path: dir.clone(),
                    msg: "no frames".into(),
                });
            }
        }
        // Pose ground truth between folders (different sim worlds never share places).
        let n = set.keyframes.len();
        let sim_dir = |k: &Keyframe| k.robot.split_once('/').map(|(d, _)| d.to_string());
        for a in 0..n {
            for b in a + 1..n {
                let (ka, kb) = (&set.keyframes[a], &set.keyframes[b]);
                if ka.robot == kb.robot || sim_dir(ka).is_some() || sim_dir(kb).is_some() {
                    continue;
                }
                if near(&ka.pose, &kb.pose, POSE_MAX_M, POSE_MAX_DEG) {
                    set.positives.extend([(a, b), (b, a)]);
                }
            }
        }
        Ok(set)
    }

    fn add_sim(&mut self, dir: &Path, index: usize, stride: usize) -> Result<(), EvalError> {
        let csv = dir.join("closures.csv");
        let text = std::fs::read_to_string(&csv).map_err(|e| EvalError::Input {
            path: csv.clone(),
            msg: e.to_string(),
        })?;
        let first = self.keyframes.len();
        if let Some(seed) = world_seed(dir)? {
            self.sim_seeds.push((dir.to_path_buf(), seed));
        }
        let mut robots: Vec<String> = std::fs::read_dir(dir)
            .map_err(|e| EvalError::Input {
                path: dir.to_path_buf(),
                msg: e.to_string(),
            })?
            .filter_map(|e| e.ok())
            .filter(|e| e.path().join("image_0").is_dir())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        robots.sort();
        // Full-rate poses per robot (closure frames need not be keyframes).
        let mut all_poses = Vec::new();
        for r in &robots {
            let data = Dataset::open(&dir.join(r))?;
            all_poses.push(data.truth.unwrap_or_default());
            self.robot_dirs.insert(format!("{index}/{r}"), dir.join(r));
            self.keyframes.extend(robot_keyframes(
                &dir.join(r),
                &format!("{index}/{r}"),
                stride,
            )?);
        }
        let robot_of = |name: &str, line: usize| {
            robots
                .iter()
                .position(|r| r == name)
                .ok_or_else(|| EvalError::Input {
                    path: csv.clone(),
                    msg: format!("line {line}: unknown robot {name:?}"),
                })
        };
        for (line, row) in text.lines().enumerate().skip(1) {
            let f: Vec<&str> = row.trim().split(',').collect();
            let [ra, fa, rb, fb, kind] = f[..] else {
                return Err(EvalError::Input {
                    path: csv.clone(),
                    msg: format!(
                        "line {}: expected robot_a,frame_a,robot_b,frame_b,kind",
                        line + 1
                    ),
                });
            };
            let aliased = match kind {
                "overlap" => false,
                "aliased" => true, // negatives, counted apart by --verify
                other => {
                    return Err(EvalError::Input {
                        path: csv.clone(),
                        msg: format!("line {}: unknown kind {other:?}", line + 1),
                    })
                }
            };
            let frame = |s: &str, robot: usize| {
                s.parse::<usize>()
                    .ok()
                    .filter(|&k| k < all_poses[robot].len())
                    .ok_or_else(|| EvalError::Input {
                        path: csv.clone(),
                        msg: format!("line {}: bad frame {s:?}", line + 1),
                    })
            };
            let (ra, rb) = (robot_of(ra, line + 1)?, robot_of(rb, line + 1)?);
            let (pa, pb) = (all_poses[ra][frame(fa, ra)?], all_poses[rb][frame(fb, rb)?]);
            let side = |robot: usize, pose: &Isometry3<f64>| -> Vec<usize> {
                let name = format!("{index}/{}", robots[robot]);
                (first..self.keyframes.len())
                    .filter(|&k| {
                        self.keyframes[k].robot == name
                            && near(&self.keyframes[k].pose, pose, SIM_WIDEN_M, SIM_WIDEN_DEG)
                    })
                    .collect()
            };
            let (xa, xb) = (side(ra, &pa), side(rb, &pb));
            let pairs = if aliased {
                &mut self.aliased
            } else {
                &mut self.positives
            };
            for &a in &xa {
                for &b in &xb {
                    pairs.extend([(a, b), (b, a)]);
                }
            }
            if !aliased {
                self.overlaps.push((xa, xb));
            }
        }
        Ok(())
    }

    /// The training towns of a model among the simulated towns read: an evaluation on a
    /// town the model was trained on measures nothing (`place eval` refuses it).
    pub fn training_towns(&self, trained_on: &[u64]) -> Vec<(PathBuf, u64)> {
        self.sim_seeds
            .iter()
            .filter(|(_, s)| trained_on.contains(s))
            .cloned()
            .collect()
    }

    /// Whether keyframe `b` is another robot's (the only pairs that are queried).
    pub fn inter_robot(&self, a: usize, b: usize) -> bool {
        self.keyframes[a].robot != self.keyframes[b].robot
    }
}

/// The seed of a `sim world` output (`seed = N` in its `world.txt`); `None` without one.
fn world_seed(dir: &Path) -> Result<Option<u64>, EvalError> {
    let path = dir.join("world.txt");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(None);
    };
    for (n, line) in text.lines().enumerate() {
        if let Some(v) = line.strip_prefix("seed = ") {
            return v.trim().parse().map(Some).map_err(|_| EvalError::Input {
                path: path.clone(),
                msg: format!("line {}: seed {v:?} is not a number", n + 1),
            });
        }
    }
    Ok(None)
}

/// Summary of one precision-recall curve.
#[derive(Debug, Clone, PartialEq)]
pub struct PrCurve {
    pub queries: usize,
    /// Queries that have at least one positive (the recall denominator).
    pub queries_with_positive: usize,
    pub recall_at_1: f64,
    pub precision_at_recall_0_5: f64,
    /// Area under the curve (average precision: Σ precision · Δrecall).
    pub auc: f64,
    /// (threshold, recall, precision), thresholds ascending.
    pub points: Vec<(f64, f64, f64)>,
}

/// The curve from each query's nearest neighbour `(index, distance)`.
pub fn pr_curve(set: &EvalSet, nearest: &[Option<(usize, f32)>]) -> PrCurve {
    let has_positive = |q: usize| (0..set.keyframes.len()).any(|k| set.positives.contains(&(q, k)));
    let positives = (0..nearest.len()).filter(|&q| has_positive(q)).count();
    let mut matches: Vec<(f64, bool)> = nearest
        .iter()
        .enumerate()
        .filter_map(|(q, nn)| nn.map(|(k, d)| (f64::from(d), set.positives.contains(&(q, k)))))
        .collect();
    matches.sort_by(|a, b| a.0.total_cmp(&b.0));
    let denom = positives.max(1) as f64;
    let (mut tp, mut auc, mut last_recall) = (0usize, 0.0, 0.0);
    let mut points = Vec::with_capacity(matches.len());
    for (i, &(d, correct)) in matches.iter().enumerate() {
        tp += usize::from(correct);
        let (recall, precision) = (tp as f64 / denom, tp as f64 / (i + 1) as f64);
        auc += precision * (recall - last_recall);
        last_recall = recall;
        points.push((d, recall, precision));
    }
    let precision_at_recall_0_5 = points
        .iter()
        .filter(|p| p.1 >= 0.5)
        .map(|p| p.2)
        .fold(0.0, f64::max);
    PrCurve {
        queries: nearest.len(),
        queries_with_positive: positives,
        recall_at_1: tp as f64 / denom,
        precision_at_recall_0_5,
        auc,
        points,
    }
}

/// The match threshold of a curve at precision `precision`: the distance between the last
/// match at which precision is still at least `precision` and the next one (so every match
/// up to it, and none after, is accepted by `distance < threshold`), with the recall there.
/// `None` when no match reaches that precision.
pub fn threshold_at_precision(curve: &PrCurve, precision: f64) -> Option<(f64, f64)> {
    let last = curve.points.iter().rposition(|p| p.2 >= precision)?;
    let (d, recall, _) = curve.points[last];
    let threshold = match curve.points.get(last + 1) {
        Some(next) => 0.5 * (d + next.0),
        None => d + 1e-3,
    };
    Some((threshold, recall))
}

/// Recall and precision of the matches a threshold accepts (`distance < threshold`);
/// `None` when it accepts none.
pub fn at_threshold(curve: &PrCurve, threshold: f64) -> Option<(f64, f64)> {
    let accepted = curve.points.partition_point(|p| p.0 < threshold);
    let (_, recall, precision) = *curve.points.get(accepted.checked_sub(1)?)?;
    Some((recall, precision))
}

/// The curves as one SVG plot (recall on x, precision on y).
pub fn svg(curves: &[(&str, &PrCurve)]) -> String {
    let (w, h, m) = (480.0, 360.0, 50.0);
    let x = |r: f64| m + r * (w - 2.0 * m);
    let y = |p: f64| h - m - p * (h - 2.0 * m);
    let colours = [
        "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b",
    ];
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"11\">\n\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n\
         <rect x=\"{m}\" y=\"{m}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"black\"/>\n\
         <text x=\"{}\" y=\"{}\" text-anchor=\"middle\">recall</text>\n\
         <text x=\"12\" y=\"{}\" transform=\"rotate(-90 12 {})\" text-anchor=\"middle\">precision</text>\n",
        w - 2.0 * m,
        h - 2.0 * m,
        w / 2.0,
        h - 12.0,
        h / 2.0,
        h / 2.0
    );
    for t in 0..=5 {
        let v = t as f64 / 5.0;
        s += &format!(
            "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{v:.1}</text><text x=\"{}\" y=\"{}\" text-anchor=\"end\">{v:.1}</text>\n",
            x(v),
            h - m + 14.0,
            m - 4.0,
            y(v) + 4.0
        );
    }
    for (i, (label, curve)) in curves.iter().enumerate() {
        let c = colours[i % colours.len()];
        let pts: Vec<String> = curve
            .points
            .iter()
            .map(|&(_, r, p)| format!("{:.1},{:.1}", x(r), y(p)))
            .collect();
        s += &format!(
            "<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"1.5\" points=\"{}\"/>\n\
             <text x=\"{}\" y=\"{}\" fill=\"{c}\">{label} (AUC {:.3})</text>\n",
            pts.join(" "),
            m + 8.0,
            m + 16.0 + 14.0 * i as f64,
            curve.auc
        );
    }
    s + "</svg>\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(n: usize, positives: &[(usize, usize)]) -> EvalSet {
        EvalSet {
            keyframes: (0..n)
                .map(|i| Keyframe {
                    robot: format!("{}", i % 2),
                    frame: i,
                    image: PathBuf::new(),
                    right: None,
                    pose: Isometry3::identity(),
                })
                .collect(),
            positives: positives.iter().copied().collect(),
            ..Default::default()
        }
    }

    #[test]
    fn curve_of_a_known_ranking() {
        // Queries 0..4; 0, 1, 2 have positives. Ranked by distance: q0 correct (0.1),
        // q3 wrong (0.2, no positive), q1 correct (0.3), q2 wrong (0.4).
        let s = set(4, &[(0, 1), (1, 0), (2, 1)]);
        let nn = vec![
            Some((1, 0.1)),
            Some((0, 0.3)),
            Some((3, 0.4)),
            Some((0, 0.2)),
        ];
        let c = pr_curve(&s, &nn);
        assert_eq!((c.queries, c.queries_with_positive), (4, 3));
        assert!((c.recall_at_1 - 2.0 / 3.0).abs() < 1e-12);
        // Points: (1/3, 1), (1/3, 1/2), (2/3, 2/3), (2/3, 1/2).
        assert!((c.auc - (1.0 / 3.0 + 2.0 / 9.0)).abs() < 1e-12, "{}", c.auc);
        assert!((c.precision_at_recall_0_5 - 2.0 / 3.0).abs() < 1e-12);
        // Precision >= 0.9 holds up to the first match only (0.1; the next is at 0.2).
        let (t, r) = threshold_at_precision(&c, 0.9).unwrap();
        assert!(
            (t - 0.15).abs() < 1e-6 && (r - 1.0 / 3.0).abs() < 1e-12,
            "{t} {r}"
        );
        // Precision >= 0.6 last holds at the third match (2/3 at 0.3).
        let (t, r) = threshold_at_precision(&c, 0.6).unwrap();
        assert!(
            (t - 0.35).abs() < 1e-6 && (r - 2.0 / 3.0).abs() < 1e-12,
            "{t} {r}"
        );
        assert!(svg(&[("test", &c)]).contains("<polyline"));
    }
}
