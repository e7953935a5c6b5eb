//! `<state_dir>/<robot>/trajectory.tum`: the back-end's current estimate of every keyframe,
//! rewritten after each optimization, in TUM format (`stamp_s x y z qx qy qz qw`, one
//! keyframe per line, in the order they arrived), so `doorslam eval ate|rpe --format tum`
//! compares it with ground truth. Written to a temporary file and renamed: a reader sees
//! the previous estimate or the new one, never half of it.

use std::fmt::Write as _;
use std::path::Path;

use doorslam_geometry::{pose_to_array, SE3};

/// The trajectory as TUM text: `(id, stamp_ns, pose)` per keyframe.
pub fn tum_text<'a>(poses: impl Iterator<Item = (u64, u64, &'a SE3)>) -> String {
    let mut out = String::new();
    for (_, stamp_ns, pose) in poses {
        let [x, y, z, qx, qy, qz, qw] = pose_to_array(pose);
        let _ = writeln!(
            out,
            "{}.{:09} {x:.9} {y:.9} {z:.9} {qx:.9} {qy:.9} {qz:.9} {qw:.9}",
            stamp_ns / 1_000_000_000,
            stamp_ns % 1_000_000_000
        );
    }
    out
}

/// Writes the trajectory to `path` atomically (temporary file, then rename).
pub fn write_tum<'a>(
    path: &Path,
    poses: impl Iterator<Item = (u64, u64, &'a SE3)>,
) -> std::io::Result<()> {
    let tmp = path.with_extension("tum.tmp");
    std::fs::write(&tmp, tum_text(poses))?;
    std::fs::rename(&tmp, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_tum_line_per_keyframe() {
        let a = SE3::translation(1.0, 2.0, 3.0);
        let b = SE3::identity();
        let text = tum_text([(0, 1_500_000_000, &a), (1, 7, &b)].into_iter());
        assert_eq!(
            text,
            "1.500000000 1.000000000 2.000000000 3.000000000 0.000000000 0.000000000 0.000000000 1.000000000\n\
             0.000000007 0.000000000 0.000000000 0.000000000 0.000000000 0.000000000 0.000000000 1.000000000\n"
        );
    }
}
