//! The fixed layouts poses take outside the process (shared-memory samples, journals,
//! wire messages): `[x, y, z, qx, qy, qz, qw]`, and their validation on the way in.

use nalgebra::{Isometry3, Translation3};

use crate::so3::SO3;
use crate::SE3;

/// Why a pose from outside is refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("a component is not finite")]
    NonFinite,
    #[error("quaternion norm {norm:.6}, expected 1")]
    NotUnitQuaternion { norm: f64 },
}

/// `[x y z qx qy qz qw]` → pose, checked: finite, unit quaternion within
/// [`crate::UNIT_QUATERNION_TOLERANCE`] (then normalized).
pub fn pose_from_array(p: &[f64; 7]) -> Result<SE3, PoseError> {
    if !p[..3].iter().all(|v| v.is_finite()) {
        return Err(PoseError::NonFinite);
    }
    let r = SO3::from_quaternion_checked(p[3], p[4], p[5], p[6])?;
    Ok(Isometry3::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        r.quaternion(),
    ))
}

/// Pose → `[x y z qx qy qz qw]`.
pub fn pose_to_array(p: &SE3) -> [f64; 7] {
    let (t, q) = (p.translation.vector, p.rotation.quaternion());
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_refuses() {
        let p = [1.0, -2.0, 3.0, 0.0, 0.0, 0.6, 0.8];
        assert_eq!(pose_to_array(&pose_from_array(&p).unwrap()), p);
        let zero_q = [0.0; 7];
        assert!(matches!(
            pose_from_array(&zero_q),
            Err(PoseError::NotUnitQuaternion { .. })
        ));
        let nan = [f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        assert_eq!(pose_from_array(&nan), Err(PoseError::NonFinite));
        let nan_q = [0.0, 0.0, 0.0, f64::NAN, 0.0, 0.0, 1.0];
        assert_eq!(pose_from_array(&nan_q), Err(PoseError::NonFinite));
    }
}
