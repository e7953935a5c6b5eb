//! Trajectory evaluation: read KITTI/TUM/EuRoC trajectories, associate an estimate with a
//! reference (by index or timestamp), align it (Umeyama SE(3)/Sim(3)), and compute the
//! absolute trajectory error (ATE) and relative pose error (RPE).
//!
//! The numbers match evo (github.com/MichaelGrupp/evo), the tool the DOOR-SLAM paper and
//! most SLAM papers report with; `tests/eval_evo.rs` checks them against evo's stored
//! results.
//!
//! ```no_run
//! use doorslam_backend::eval::*;
//! # fn main() -> Result<(), EvalError> {
//! let reference = read_trajectory("KITTI_00_gt.txt", TrajectoryFormat::Kitti)?;
//! let estimate = read_trajectory("KITTI_00_ORB.txt", TrajectoryFormat::Kitti)?;
//! let (reference, estimate) = associate_by_index(&reference, &estimate)?;
//! let ate = absolute_trajectory_error(&reference, &estimate, Alignment::Se3)?;
//! let rpe = relative_pose_error(&reference, &estimate, RpeDelta::Meters(10.0))?;
//! println!("ATE rmse {} m, RPE rmse {} m", ate.stats.rmse, rpe.stats.rmse);
//! # Ok(())
//! # }
//! ```

mod align;
mod error;
mod metrics;
mod sync;
mod trajectory;

pub use align::{align, apply_alignment, umeyama, Alignment};
pub use error::{EvalError, LineProblem};
pub use metrics::{
    absolute_trajectory_error, pairs_by_index, pairs_by_path, relative_pose_error, AteResult,
    ErrorStats, RpeDelta, RpeResult,
};
pub use sync::{associate_by_index, associate_by_timestamp, DEFAULT_MAX_TIME_DIFF};
pub use trajectory::{
    read_euroc, read_kitti, read_kitti_with_times, read_trajectory, read_tum, Trajectory,
    TrajectoryFormat,
};
