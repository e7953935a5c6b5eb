//! Information (inverse covariance) matrices on the tangent space: their layouts outside
//! the process, the rules a matrix must satisfy before it enters an estimator, and
//! covariance conversions.
//!
//! Layout: the row-major upper triangle (21 values) of a 6×6 matrix in rotation-first
//! tangent order (see [`crate::lie`]). A group of dimension `dim` < 6 (SE(2)) uses the
//! top-left `dim × dim` block.

use nalgebra::{DMatrix, Matrix6};

use crate::TangentMatrix;

/// Why an information matrix is refused. The same rules hold for g2o files, messages
/// from the front-end and other robots, and the graph API, so a matrix accepted in one
/// place is accepted in all.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InformationError {
    #[error("information matrix entry ({row}, {col}) is {value}, not finite")]
    NonFinite { row: usize, col: usize, value: f64 },
    #[error("information matrix is not symmetric: ({row}, {col}) differs from its transpose by {diff:e}")]
    NotSymmetric { row: usize, col: usize, diff: f64 },
    #[error(
        "information matrix is not positive definite (smallest eigenvalue {min_eigenvalue:e})"
    )]
    NotPositiveDefinite { min_eigenvalue: f64 },
}

/// Upper triangle (row-major, 21 values) → symmetric 6×6 matrix.
pub fn matrix_from_upper(upper: &[f64; 21]) -> TangentMatrix {
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

/// Symmetric 6×6 matrix → its upper triangle (row-major, 21 values).
pub fn upper_from_matrix(m: &TangentMatrix) -> [f64; 21] {
    let mut upper = [0.0; 21];
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            upper[k] = m[(r, c)];
            k += 1;
        }
    }
    upper
}

/// Diagonal matrix → its upper triangle (row-major, 21 values).
pub fn upper_from_diagonal(diagonal: [f64; 6]) -> [f64; 21] {
    upper_from_matrix(&Matrix6::from_diagonal(&diagonal.into()))
}

/// The top-left `dim × dim` block (the part a group of dimension `dim` uses).
fn block(m: &TangentMatrix, dim: usize) -> DMatrix<f64> {
    m.view((0, 0), (dim, dim)).into_owned()
}

/// Checks the top-left `dim × dim` block: every entry finite, symmetric (to 1e-9 relative
/// to its largest entry), positive definite (Cholesky succeeds).
pub fn check_information(m: &TangentMatrix, dim: usize) -> Result<(), InformationError> {
    check_symmetric(m, dim)?;
    if block(m, dim).cholesky().is_none() {
        return Err(InformationError::NotPositiveDefinite {
            min_eigenvalue: min_eigenvalue(m, dim),
        });
    }
    Ok(())
}

/// The first two rules of [`check_information`] (finite, symmetric), for a caller that
/// deliberately uses indefinite matrices as written (as GTSAM does with such files).
pub fn check_symmetric(m: &TangentMatrix, dim: usize) -> Result<(), InformationError> {
    let scale = 1.0 + m.view((0, 0), (dim, dim)).amax();
    for row in 0..dim {
        for col in 0..dim {
            let value = m[(row, col)];
            if !value.is_finite() {
                return Err(InformationError::NonFinite { row, col, value });
            }
            let diff = (value - m[(col, row)]).abs();
            if diff > 1e-9 * scale {
                return Err(InformationError::NotSymmetric { row, col, diff });
            }
        }
    }
    Ok(())
}

/// The smallest eigenvalue of the top-left `dim × dim` block (symmetric part).
pub fn min_eigenvalue(m: &TangentMatrix, dim: usize) -> f64 {
    let b = block(m, dim);
    let sym = (&b + b.transpose()) * 0.5;
    sym.symmetric_eigenvalues().min()
}

/// The positive-definite matrix nearest to `m` in the Frobenius norm, on the top-left
/// `dim × dim` block: its symmetric part with eigenvalues below `floor = 1e-9 · λmax`
/// raised to the floor (Higham 1988). The rest of the padded matrix stays zero.
pub fn nearest_positive_definite(m: &TangentMatrix, dim: usize) -> TangentMatrix {
    let b = block(m, dim);
    let sym = (&b + b.transpose()) * 0.5;
    let eig = sym.symmetric_eigen();
    let largest = eig.eigenvalues.max().abs().max(f64::MIN_POSITIVE);
    let floor = 1e-9 * largest;
    let clamped = eig.eigenvalues.map(|l| l.max(floor));
    let repaired =
        &eig.eigenvectors * DMatrix::from_diagonal(&clamped) * eig.eigenvectors.transpose();
    let mut out = TangentMatrix::zeros();
    for r in 0..dim {
        for c in 0..dim {
            // Symmetrize again: the product is symmetric only to rounding.
            out[(r, c)] = 0.5 * (repaired[(r, c)] + repaired[(c, r)]);
        }
    }
    out
}

/// `Σ = Ω⁻¹` on the top-left `dim × dim` block, after [`check_information`].
pub fn covariance_from_information(
    information: &TangentMatrix,
    dim: usize,
) -> Result<TangentMatrix, InformationError> {
    invert_spd(information, dim)
}

/// `Ω = Σ⁻¹` on the top-left `dim × dim` block; a covariance obeys the same rules.
pub fn information_from_covariance(
    covariance: &TangentMatrix,
    dim: usize,
) -> Result<TangentMatrix, InformationError> {
    invert_spd(covariance, dim)
}

fn invert_spd(m: &TangentMatrix, dim: usize) -> Result<TangentMatrix, InformationError> {
    check_symmetric(m, dim)?;
    let chol = block(m, dim)
        .cholesky()
        .ok_or_else(|| InformationError::NotPositiveDefinite {
            min_eigenvalue: min_eigenvalue(m, dim),
        })?;
    let inv = chol.inverse();
    let mut out = TangentMatrix::zeros();
    out.view_mut((0, 0), (dim, dim)).copy_from(&inv);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector6;

    #[test]
    fn layouts_round_trip() {
        let m = matrix_from_upper(&upper_from_diagonal([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
        assert_eq!(
            m,
            Matrix6::from_diagonal(&Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0))
        );
        let upper: [f64; 21] = std::array::from_fn(|k| k as f64);
        assert_eq!(upper_from_matrix(&matrix_from_upper(&upper)), upper);
    }

    #[test]
    fn rules() {
        let good = Matrix6::identity() * 4.0;
        assert_eq!(check_information(&good, 6), Ok(()));
        let mut nan = good;
        nan[(2, 3)] = f64::NAN;
        assert!(matches!(
            check_information(&nan, 6),
            Err(InformationError::NonFinite { row: 2, col: 3, .. })
        ));
        let mut asym = good;
        asym[(0, 1)] = 1.0;
        assert!(matches!(
            check_information(&asym, 6),
            Err(InformationError::NotSymmetric { .. })
        ));
        let mut indefinite = good;
        indefinite[(5, 5)] = -1.0;
        assert!(matches!(
            check_information(&indefinite, 6),
            Err(InformationError::NotPositiveDefinite { min_eigenvalue }) if (min_eigenvalue + 1.0).abs() < 1e-12
        ));
        // SE(2) uses the 3×3 block only: the padding may be zero.
        let mut se2 = TangentMatrix::zeros();
        se2.view_mut((0, 0), (3, 3)).fill_with_identity();
        assert_eq!(check_information(&se2, 3), Ok(()));
        assert!(check_information(&se2, 6).is_err());
    }

    #[test]
    fn nearest_pd_repairs_only_what_is_wrong() {
        let good = Matrix6::from_diagonal(&Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0));
        assert!((nearest_positive_definite(&good, 6) - good).amax() < 1e-12);
        let mut bad = good;
        bad[(0, 1)] = 5.0;
        bad[(1, 0)] = 5.0;
        assert!(check_information(&bad, 6).is_err());
        let fixed = nearest_positive_definite(&bad, 6);
        assert_eq!(check_information(&fixed, 6), Ok(()));
        // Untouched directions keep their values.
        assert!((fixed[(5, 5)] - 6.0).abs() < 1e-12);
    }

    #[test]
    fn covariance_inverts_information() {
        let mut info = Matrix6::identity() * 2.0;
        info[(0, 3)] = 0.5;
        info[(3, 0)] = 0.5;
        let cov = covariance_from_information(&info, 6).unwrap();
        assert!((cov * info - Matrix6::identity()).amax() < 1e-12);
        assert!((information_from_covariance(&cov, 6).unwrap() - info).amax() < 1e-12);
    }
}
