//! Information (inverse covariance) matrices on the tangent space: their layouts outside
//! the process, the rules a matrix must satisfy before it enters an estimator, and
//! covariance conversions.
//!
//! Layout: the row-major upper triangle (21 values) of a 6×6 matrix in rotation-first
//! tangent order (see [`crate::lie`]). A group of dimension `dim` < 6 (SE(2)) uses the
//! top-left `dim × dim` block.

use nalgebra::{DMatrix, Matrix6};

use crate::TangentMatrix;

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

/// How strictly an information matrix is checked (the graph API's `add_edge_with`, the g2o
/// reader). Finiteness and symmetry are always required: a NaN poisons the cost, and the
/// solver reads only the lower triangle, so an asymmetric matrix would silently become a
/// different one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InformationCheck {
    /// Also positive definite (the default): an indefinite Ω makes rᵀΩr negative in some
    /// directions, so the cost is not a sum of squares and Gauss-Newton's normal equations
    /// may be singular or indefinite.
    #[default]
    PositiveDefinite,
    /// Use the matrix as written even if it is indefinite or singular: published benchmark
    /// files (SE-Sync's cubicle) contain such matrices and other solvers accept them.
    /// Levenberg-Marquardt's damping keeps its steps defined; Gauss-Newton may fail.
    AsIs,
}

/// Why an information matrix was refused by [`check_information`]. The same rules hold for g2o
/// files, messages from the front-end and other robots, and the graph API, so a matrix
/// accepted in one place is accepted in all.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InformationError {
    #[error("information matrix entry ({row}, {col}) is {value}, not finite")]
    NonFinite { row: usize, col: usize, value: f64 },
    #[error(
        "information matrix is not symmetric: entries ({row}, {col}) and ({col}, {row}) are {a} and {b}"
    )]
    NotSymmetric {
        row: usize,
        col: usize,
        a: f64,
        b: f64,
    },
    #[error("information matrix is not positive definite")]
    NotPositiveDefinite,
}

/// Relative tolerance of the symmetry check, against the largest entry: a matrix computed
/// as `AᵀA` or as an inverse is symmetric only to rounding.
pub const SYMMETRY_TOLERANCE: f64 = 1e-9;

/// The one definition of an acceptable information matrix, for the graph API and the g2o
/// reader alike: the leading `dim × dim` block (the rest is padding, see [`crate::lie`])
/// must be finite, symmetric to [`SYMMETRY_TOLERANCE`] and, with
/// [`InformationCheck::PositiveDefinite`], have a Cholesky factorization.
pub fn check_information(
    information: &TangentMatrix,
    dim: usize,
    check: InformationCheck,
) -> Result<(), InformationError> {
    let dim = dim.min(6);
    let mut scale = 0.0f64;
    for col in 0..dim {
        for row in 0..dim {
            let value = information[(row, col)];
            if !value.is_finite() {
                return Err(InformationError::NonFinite { row, col, value });
            }
            scale = scale.max(value.abs());
        }
    }
    for col in 0..dim {
        for row in col + 1..dim {
            let (a, b) = (information[(row, col)], information[(col, row)]);
            if (a - b).abs() > SYMMETRY_TOLERANCE * scale {
                return Err(InformationError::NotSymmetric { row, col, a, b });
            }
        }
    }
    if check == InformationCheck::PositiveDefinite
        && information
            .view((0, 0), (dim, dim))
            .into_owned()
            .cholesky()
            .is_none()
    {
        return Err(InformationError::NotPositiveDefinite);
    }
    Ok(())
}

/// Eigenvalues of a repaired matrix are at least this fraction of its largest one: small
/// enough to stay close to the original, large enough for the condition number (1e8) to
/// leave the Cholesky factorization well defined.
pub const NEAREST_PD_FLOOR: f64 = 1e-8;

/// The nearest positive-definite matrix to the (symmetrized) leading `dim × dim` block:
/// symmetric eigen-decomposition with the eigenvalues clamped to [`NEAREST_PD_FLOOR`]
/// times the largest magnitude (the Frobenius-nearest PSD matrix clamps to 0, which is not
/// definite). The padding is zeroed. `None` if an entry is not finite or all are zero: then
/// there is no scale to repair towards.
pub fn nearest_positive_definite(information: &TangentMatrix, dim: usize) -> Option<TangentMatrix> {
    let dim = dim.min(6);
    let block = information.view((0, 0), (dim, dim)).into_owned();
    if block.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let sym = (&block + block.transpose()) * 0.5;
    let eig = sym.symmetric_eigen();
    let largest = eig.eigenvalues.amax();
    if largest <= 0.0 {
        return None;
    }
    let floor = NEAREST_PD_FLOOR * largest;
    let clamped = eig.eigenvalues.map(|l| l.max(floor));
    let v = &eig.eigenvectors;
    let repaired = v * nalgebra::DMatrix::from_diagonal(&clamped) * v.transpose();
    let mut out = TangentMatrix::zeros();
    for c in 0..dim {
        for r in 0..dim {
            // Average the mirror entries: the product is symmetric only to rounding.
            out[(r, c)] = 0.5 * (repaired[(r, c)] + repaired[(c, r)]);
        }
    }
    Some(out)
}

/// `Σ = Ω⁻¹` on the top-left `dim × dim` block (which must pass [`check_information`]).
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
    check_information(m, dim, InformationCheck::AsIs)?;
    let chol = block(m, dim)
        .cholesky()
        .ok_or(InformationError::NotPositiveDefinite)?;
    let inv = chol.inverse();
    let mut out = TangentMatrix::zeros();
    out.view_mut((0, 0), (dim, dim)).copy_from(&inv);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector6;

    const PD: InformationCheck = InformationCheck::PositiveDefinite;

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
        assert_eq!(check_information(&good, 6, PD), Ok(()));
        let mut nan = good;
        nan[(2, 3)] = f64::NAN;
        assert!(matches!(
            check_information(&nan, 6, PD),
            Err(InformationError::NonFinite { row: 2, col: 3, .. })
        ));
        let mut asym = good;
        asym[(0, 1)] = 1.0;
        assert!(matches!(
            check_information(&asym, 6, PD),
            Err(InformationError::NotSymmetric { .. })
        ));
        let mut indefinite = good;
        indefinite[(5, 5)] = -1.0;
        assert!(matches!(
            check_information(&indefinite, 6, PD),
            Err(InformationError::NotPositiveDefinite)
        ));
        // SE(2) uses the 3×3 block only: the padding may be zero.
        let mut se2 = TangentMatrix::zeros();
        se2.view_mut((0, 0), (3, 3)).fill_with_identity();
        assert_eq!(check_information(&se2, 3, PD), Ok(()));
        assert!(check_information(&se2, 6, PD).is_err());
        // As-is admits the indefinite matrix, never a NaN.
        assert_eq!(
            check_information(&indefinite, 6, InformationCheck::AsIs),
            Ok(())
        );
        assert!(check_information(&nan, 6, InformationCheck::AsIs).is_err());
    }

    #[test]
    fn nearest_pd_repairs_only_what_is_wrong() {
        let good = Matrix6::from_diagonal(&Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0));
        assert!((nearest_positive_definite(&good, 6).unwrap() - good).amax() < 1e-12);
        let mut bad = good;
        bad[(0, 1)] = 5.0;
        bad[(1, 0)] = 5.0;
        assert!(check_information(&bad, 6, PD).is_err());
        let fixed = nearest_positive_definite(&bad, 6).unwrap();
        assert_eq!(check_information(&fixed, 6, PD), Ok(()));
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
