//! Failures of trajectory reading, association, alignment and the error metrics.

use std::path::PathBuf;

/// Everything that can go wrong while evaluating a trajectory. Errors about a file name
/// the file and, where one line is to blame, its 1-based line number.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}:{line}: {problem}", path.display())]
    Line {
        path: PathBuf,
        /// 1-based, counting comment and blank lines.
        line: usize,
        problem: LineProblem,
    },
    #[error("{}: no poses (the file is empty or has only comments)", path.display())]
    Empty { path: PathBuf },
    #[error("{}: {times} timestamps for {poses} poses", path.display())]
    TimesCount {
        path: PathBuf,
        times: usize,
        poses: usize,
    },
    #[error("{}: cannot guess the trajectory format (expected 12 numbers per line for KITTI, 8 for TUM, or a .csv EuRoC file)", path.display())]
    UnknownFormat { path: PathBuf },
    #[error("trajectory has {timestamps} timestamps but {poses} poses")]
    Inconsistent { timestamps: usize, poses: usize },
    #[error("cannot associate by index: reference has {reference} poses, estimate has {estimate}")]
    LengthMismatch { reference: usize, estimate: usize },
    #[error("no timestamps of reference ({reference} poses) and estimate ({estimate} poses) match within {max_diff} s")]
    NoMatches {
        reference: usize,
        estimate: usize,
        max_diff: f64,
    },
    #[error("Umeyama alignment is degenerate: {0}")]
    DegenerateAlignment(String),
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    #[error("no pose pairs for RPE with delta {delta} among {poses} poses; try a smaller delta")]
    NoPairs { delta: String, poses: usize },
    #[error("no errors to summarize (empty trajectory)")]
    NoErrors,
}

/// What is wrong with one line of a trajectory file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LineProblem {
    #[error("expected {expected} fields, found {found}")]
    FieldCount { expected: String, found: usize },
    #[error("field {field}: cannot parse {text:?} as a number")]
    Unparsable { field: usize, text: String },
    #[error("field {field}: {text:?} is not finite")]
    NotFinite { field: usize, text: String },
    #[error("quaternion has norm {norm:e}, cannot be normalized")]
    Quaternion { norm: f64 },
    #[error("3x3 block is not a rotation (max |RᵀR - I| = {deviation:e}, det = {det})")]
    NotRotation { deviation: f64, det: f64 },
}
