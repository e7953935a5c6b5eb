//! The service's two files under `<run_dir>/<robot>/`:
//! - `frontend.json`: the status (counters, tracking state, timing), rewritten every second
//!   and at exit, for operators and tests;
//! - `frontend.resume`: the last keyframe published (id, stamp, pose, the edge into it), rewritten after
//!   each keyframe, so a restarted front-end continues the keyframe ids (the back-end
//!   skips ids it already has as duplicates; see [`super::FrontendState::new`] for the one
//!   id it skips) and links its first keyframe to that one.
//!
//! Both are written to a temporary file and renamed over the old one: a reader (or a
//! restart after a crash) sees the old or the new content, never half of it.

use std::path::{Path, PathBuf};

use doorslam_geometry::information::{
    check_information, matrix_from_upper, upper_from_matrix, InformationCheck,
};
use doorslam_geometry::{pose_from_array, pose_to_array};
use serde::{Deserialize, Serialize};

use super::state::{Resume, Snapshot};
use super::ServiceError;
use crate::keyframe::OdometryEdge;

/// `frontend.json`: the snapshot plus who and since when.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Status<'a> {
    pub robot: &'a str,
    /// Seconds since the service started.
    pub time_s: f64,
    /// Where the calibration came from.
    pub calibration: String,
    /// Reliable samples (keyframes, edges) that reached fewer consumers than were connected.
    pub undelivered: u64,
    #[serde(flatten)]
    pub snapshot: Snapshot,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ResumeFile {
    keyframe: u64,
    stamp_ns: u64,
    /// x y z qx qy qz qw
    pose: [f64; 7],
    /// The odometry edge into `keyframe` (absent in files of before it was kept, and for a
    /// robot's first keyframe).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    edge: Option<ResumeEdge>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ResumeEdge {
    from: u64,
    /// x y z qx qy qz qw of `keyframe` in the frame of `from`.
    relative: [f64; 7],
    /// Upper triangle of the information, row by row (as on the odometry topic).
    information: Vec<f64>,
}

fn write_atomically(path: &Path, text: &str) -> Result<(), ServiceError> {
    let io = |source| ServiceError::File {
        path: path.to_path_buf(),
        source,
    };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, text).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// The files of one robot's front-end.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Files {
    pub status: PathBuf,
    pub resume: PathBuf,
}

impl Files {
    /// The files in `dir` (`<run_dir>/<robot>`).
    pub fn in_dir(dir: &Path) -> Self {
        Self {
            status: dir.join("frontend.json"),
            resume: dir.join("frontend.resume"),
        }
    }

    pub fn write_status(&self, status: &Status<'_>) -> Result<(), ServiceError> {
        let text = serde_json::to_string_pretty(status).map_err(|e| ServiceError::Resume {
            path: self.status.clone(),
            why: e.to_string(),
        })?;
        write_atomically(&self.status, &(text + "\n"))
    }

    pub fn write_resume(&self, resume: &Resume) -> Result<(), ServiceError> {
        let file = ResumeFile {
            keyframe: resume.keyframe,
            stamp_ns: resume.stamp_ns,
            pose: pose_to_array(&resume.pose),
            edge: resume.edge.map(|e| ResumeEdge {
                from: e.from,
                relative: pose_to_array(&e.relative),
                information: upper_from_matrix(&e.information).to_vec(),
            }),
        };
        let text = serde_json::to_string(&file).map_err(|e| ServiceError::Resume {
            path: self.resume.clone(),
            why: e.to_string(),
        })?;
        write_atomically(&self.resume, &(text + "\n"))
    }

    /// The last keyframe a previous process published; `None` when there was none. A file
    /// that cannot be read or understood is an error naming it: starting over from id 0
    /// would hand the back-end ids it already has.
    pub fn read_resume(&self) -> Result<Option<Resume>, ServiceError> {
        let path = &self.resume;
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => {
                return Err(ServiceError::File {
                    path: path.clone(),
                    source,
                })
            }
        };
        let bad = |why: String| ServiceError::Resume {
            path: path.clone(),
            why,
        };
        let file: ResumeFile = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        if file.keyframe > doorslam_geometry::key::MAX_INDEX {
            return Err(bad(format!(
                "keyframe {} does not fit in a key",
                file.keyframe
            )));
        }
        let pose = pose_from_array(&file.pose).map_err(|e| bad(format!("pose: {e}")))?;
        let edge = match file.edge {
            None => None,
            Some(e) => {
                if e.from >= file.keyframe {
                    return Err(bad(format!(
                        "edge from keyframe {} into keyframe {}: not from an earlier one",
                        e.from, file.keyframe
                    )));
                }
                let relative =
                    pose_from_array(&e.relative).map_err(|x| bad(format!("edge: {x}")))?;
                let upper: [f64; 21] = e.information.as_slice().try_into().map_err(|_| {
                    bad(format!(
                        "edge information: {} values, not the 21 of an upper triangle",
                        e.information.len()
                    ))
                })?;
                let information = matrix_from_upper(&upper);
                check_information(&information, 6, InformationCheck::PositiveDefinite)
                    .map_err(|x| bad(format!("edge information: {x}")))?;
                Some(OdometryEdge {
                    from: e.from,
                    to: file.keyframe,
                    relative,
                    information,
                })
            }
        };
        Ok(Some(Resume {
            keyframe: file.keyframe,
            stamp_ns: file.stamp_ns,
            pose,
            edge,
        }))
    }
}
