//! Conversions between the fixed layouts of the shared-memory types and nalgebra:
//! poses are `[x, y, z, qx, qy, qz, qw]`, information matrices the row-major upper
//! triangle (21 values) of a 6×6 matrix in rotation-first tangent order.

use nalgebra::{Isometry3, Matrix6, Quaternion, Translation3, UnitQuaternion};

/// `[x y z qx qy qz qw]` → pose (the quaternion is normalized).
pub fn pose_from_array(p: &[f64; 7]) -> Isometry3<f64> {
    let q = UnitQuaternion::from_quaternion(Quaternion::new(p[6], p[3], p[4], p[5]));
    Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), q)
}

/// Pose → `[x y z qx qy qz qw]`.
pub fn pose_to_array(p: &Isometry3<f64>) -> [f64; 7] {
    let (t, q) = (p.translation.vector, p.rotation.quaternion());
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// Upper triangle (row-major, 21 values) → symmetric 6×6 matrix.
pub fn matrix_from_upper(upper: &[f64; 21]) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            m[(r, c)] = upper[k];
            m[(c, r)] = upper[k];
            k += 1;
        }
    }
    m
}

/// Diagonal matrix → its upper triangle (row-major, 21 values).
pub fn upper_from_diagonal(diagonal: [f64; 6]) -> [f64; 21] {
    let mut upper = [0.0; 21];
    // Row r of the upper triangle starts at r·6 − r(r−1)/2; its first entry is (r, r).
    for (r, d) in diagonal.iter().enumerate() {
        upper[r * 6 - r * r.saturating_sub(1) / 2] = *d;
    }
    upper
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips() {
        let p = [1.0, -2.0, 3.0, 0.0, 0.0, 0.6, 0.8];
        assert_eq!(pose_to_array(&pose_from_array(&p)), p);
        let m = matrix_from_upper(&upper_from_diagonal([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
        assert_eq!(
            m,
            Matrix6::from_diagonal(&nalgebra::Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0))
        );
    }
}
