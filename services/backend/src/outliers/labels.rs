//! Ground truth of inter-robot loop closures (inlier or outlier), to measure what outlier
//! rejection keeps. Two file formats, told apart line by line:
//!
//! - `doorslam sim graph`'s `labels.txt`: `key_a key_b robot_a index_a robot_b index_b
//!   label [group]` (keys as GTSAM symbols, robots as numbers);
//! - the outlier benchmarks' `inter_robot_labels.txt`: `file line robot_i index_i robot_j
//!   index_j label` (robots as key characters).
//!
//! Label 1 is an inlier, 0 an outlier; `#` starts a comment. A key pair may be labelled
//! twice (two measurements between the same poses); each labelled edge counts once.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use doorslam_geometry::key;

/// A labels file that cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum LabelsError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}:{line}: {reason}")]
    Line {
        path: PathBuf,
        line: usize,
        reason: String,
    },
}

/// Labelled closures by unordered key pair (lower key first): one flag per labelled edge.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Labels {
    pairs: BTreeMap<(u64, u64), Vec<bool>>,
}

/// What a set of kept closures is worth against the labels.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Quality {
    pub precision: f64,
    pub recall: f64,
    pub true_positives: usize,
    pub false_positives: usize,
    pub false_negatives: usize,
}

/// The unordered pair of two keys.
pub fn unordered(a: u64, b: u64) -> (u64, u64) {
    (a.min(b), a.max(b))
}

impl Labels {
    /// Adds one labelled closure.
    pub fn insert(&mut self, a: u64, b: u64, inlier: bool) {
        self.pairs.entry(unordered(a, b)).or_default().push(inlier);
    }

    /// Labelled edges.
    pub fn len(&self) -> usize {
        self.pairs.values().map(Vec::len).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    pub fn inliers(&self) -> usize {
        self.pairs.values().flatten().filter(|l| **l).count()
    }

    /// Precision and recall of keeping the closures whose key pairs are in `kept`
    /// (unordered pairs, see [`unordered`]).
    pub fn quality(&self, kept: &BTreeSet<(u64, u64)>) -> Quality {
        let (mut tp, mut fp, mut fne) = (0, 0, 0);
        for (pair, labels) in &self.pairs {
            let k = kept.contains(pair);
            for &inlier in labels {
                match (inlier, k) {
                    (true, true) => tp += 1,
                    (false, true) => fp += 1,
                    (true, false) => fne += 1,
                    (false, false) => {}
                }
            }
        }
        Quality {
            precision: tp as f64 / (tp + fp).max(1) as f64,
            recall: tp as f64 / (tp + fne).max(1) as f64,
            true_positives: tp,
            false_positives: fp,
            false_negatives: fne,
        }
    }

    /// Writes the labels in `doorslam sim graph`'s format.
    pub fn write(&self, path: &Path) -> Result<(), LabelsError> {
        let mut text = String::from("# key_a key_b robot_a index_a robot_b index_b label group\n");
        for ((a, b), labels) in &self.pairs {
            for &l in labels {
                let r = |k: u64| key::robot(k).map_or(-1, i64::from);
                text.push_str(&format!(
                    "{a} {b} {} {} {} {} {} -1\n",
                    r(*a),
                    key::index(*a),
                    r(*b),
                    key::index(*b),
                    u8::from(l)
                ));
            }
        }
        std::fs::write(path, text).map_err(|source| LabelsError::Io {
            path: path.to_owned(),
            source,
        })
    }
}

/// Reads a labels file of either format.
pub fn read_labels(path: &Path) -> Result<Labels, LabelsError> {
    let text = std::fs::read_to_string(path).map_err(|source| LabelsError::Io {
        path: path.to_owned(),
        source,
    })?;
    let mut labels = Labels::default();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |reason: String| LabelsError::Line {
            path: path.to_owned(),
            line: n + 1,
            reason,
        };
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 7 {
            return Err(bad(format!("{} fields, expected at least 7", f.len())));
        }
        let number = |i: usize| -> Result<u64, LabelsError> {
            f[i].parse()
                .map_err(|_| bad(format!("field {} ({:?}) is not a number", i + 1, f[i])))
        };
        let (a, b) = if f[0].parse::<u64>().is_ok() {
            // Simulator: the keys themselves.
            let (a, b) = (number(0)?, number(1)?);
            for k in [a, b] {
                if key::robot(k).is_none() {
                    return Err(bad(format!("{k} is not a multi-robot key")));
                }
            }
            (a, b)
        } else {
            // Benchmarks: robot characters and indices.
            let symbol = |r: usize, i: usize| -> Result<u64, LabelsError> {
                let robot = match f[r].as_bytes() {
                    [c] => key::robot_of_char(*c),
                    _ => None,
                }
                .ok_or_else(|| {
                    bad(format!(
                        "field {} ({:?}) is not a robot letter",
                        r + 1,
                        f[r]
                    ))
                })?;
                key::symbol(robot, number(i)?).map_err(|e| bad(e.to_string()))
            };
            (symbol(2, 3)?, symbol(4, 5)?)
        };
        let inlier = match f[6] {
            "1" => true,
            "0" => false,
            other => {
                return Err(bad(format!(
                    "label {other:?} is not 1 (inlier) or 0 (outlier)"
                )))
            }
        };
        labels.insert(a, b, inlier);
    }
    Ok(labels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_formats_read_and_quality_counts_each_edge() {
        let dir = std::env::temp_dir().join(format!("doorslam-labels-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let k = |r, i| key::symbol(r, i).unwrap();
        let sim = dir.join("labels.txt");
        std::fs::write(
            &sim,
            format!(
                "# header\n{} {} 0 8 2 10 1 -1\n{} {} 0 3 1 4 0 -1\n",
                k(0, 8),
                k(2, 10),
                k(0, 3),
                k(1, 4)
            ),
        )
        .unwrap();
        let bench = dir.join("inter_robot_labels.txt");
        std::fs::write(&bench, "# c\n0.g2o 42 a 8 c 10 1\n0.g2o 43 B 3 a 4 0\n").unwrap();
        let s = read_labels(&sim).unwrap();
        let b = read_labels(&bench).unwrap();
        assert_eq!((s.len(), s.inliers(), b.len(), b.inliers()), (2, 1, 2, 1));
        assert!(b.pairs.contains_key(&unordered(k(27, 3), k(0, 4))));
        let q = s.quality(&BTreeSet::from([unordered(k(2, 10), k(0, 8))]));
        assert_eq!((q.precision, q.recall, q.false_positives), (1.0, 1.0, 0));
        let q = s.quality(&BTreeSet::from([unordered(k(0, 3), k(1, 4))]));
        assert_eq!((q.precision, q.recall), (0.0, 0.0));
        std::fs::write(&bench, "0.g2o 42 a 8 c 10 7\n").unwrap();
        let e = read_labels(&bench).unwrap_err().to_string();
        assert!(e.contains(":1:") && e.contains("label"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
