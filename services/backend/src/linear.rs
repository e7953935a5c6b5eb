//! Sparse symmetric positive-definite solves `A x = b` with faer's supernodal Cholesky.
//!
//! In Gauss-Newton / Levenberg-Marquardt the sparsity pattern of the normal equations
//! `JᵀΩJ` is fixed by the graph's edges, only its values change between iterations. The
//! symbolic analysis (fill-reducing ordering + elimination tree) is the expensive part,
//! so [`SparseCholesky`] computes it once per pattern and reuses it.

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMat, SparseColMatRef, Triplet};
use faer::{Mat, MatMut, Side};

/// Failures of the linear solve.
#[derive(Debug, thiserror::Error)]
pub enum LinearError {
    #[error("matrix is {rows}x{cols}, expected square")]
    NotSquare { rows: usize, cols: usize },
    #[error("right-hand side has {got} rows, matrix has {want}")]
    RhsLength { got: usize, want: usize },
    #[error("invalid sparse matrix: {0}")]
    Build(String),
    #[error("symbolic factorization failed: {0}")]
    Symbolic(String),
    #[error("matrix is not positive definite (Cholesky failed: {0}); is the gauge fixed?")]
    NotPositiveDefinite(String),
}

/// A Cholesky solver that caches the symbolic factorization of the last pattern it saw.
#[derive(Default)]
pub struct SparseCholesky {
    symbolic: Option<(Vec<usize>, Vec<usize>, SymbolicLlt<usize>)>,
    symbolic_builds: usize,
}

impl SparseCholesky {
    pub fn new() -> Self {
        Self::default()
    }

    /// How many symbolic factorizations were computed so far (1 when the pattern never
    /// changed): lets tests and benchmarks check that the analysis is reused.
    pub fn symbolic_builds(&self) -> usize {
        self.symbolic_builds
    }

    /// Builds the lower triangle of a symmetric matrix from triplets (duplicates are summed;
    /// entries above the diagonal are ignored, so callers may pass either triangle's mirror).
    pub fn lower_from_triplets(
        n: usize,
        entries: &[(usize, usize, f64)],
    ) -> Result<SparseColMat<usize, f64>, LinearError> {
        let lower: Vec<Triplet<usize, usize, f64>> = entries
            .iter()
            .filter(|(r, c, _)| r >= c)
            .map(|&(r, c, v)| Triplet::new(r, c, v))
            .collect();
        SparseColMat::try_new_from_triplets(n, n, &lower)
            .map_err(|e| LinearError::Build(format!("{e:?}")))
    }

    /// Solves `A x = b`, where `a` holds (at least) the lower triangle of a symmetric
    /// positive-definite matrix.
    pub fn solve(
        &mut self,
        a: &SparseColMat<usize, f64>,
        b: &[f64],
    ) -> Result<Vec<f64>, LinearError> {
        if b.len() != a.nrows() {
            return Err(LinearError::RhsLength {
                got: b.len(),
                want: a.nrows(),
            });
        }
        let mut rhs = Mat::from_fn(b.len(), 1, |i, _| b[i]);
        self.solve_in_place(a.as_ref(), rhs.as_mut())?;
        Ok((0..b.len()).map(|i| rhs[(i, 0)]).collect())
    }

    /// Solves `A X = B` in place for one or more right-hand-side columns; `a` holds (at
    /// least) the lower triangle of a symmetric positive-definite matrix.
    pub fn solve_in_place(
        &mut self,
        a: SparseColMatRef<'_, usize, f64>,
        mut rhs: MatMut<'_, f64>,
    ) -> Result<(), LinearError> {
        let (rows, cols) = (a.nrows(), a.ncols());
        if rows != cols {
            return Err(LinearError::NotSquare { rows, cols });
        }
        if rhs.nrows() != rows {
            return Err(LinearError::RhsLength {
                got: rhs.nrows(),
                want: rows,
            });
        }
        let pattern = a.symbolic();
        let symbolic = match &self.symbolic {
            // Same pattern: the common case in an optimizer loop; compare cheaply first.
            Some((col_ptr, row_idx, s))
                if col_ptr == pattern.col_ptr() && row_idx == pattern.row_idx() =>
            {
                s.clone()
            }
            _ => {
                let s = SymbolicLlt::try_new(pattern, Side::Lower)
                    .map_err(|e| LinearError::Symbolic(format!("{e:?}")))?;
                self.symbolic = Some((
                    pattern.col_ptr().to_vec(),
                    pattern.row_idx().to_vec(),
                    s.clone(),
                ));
                self.symbolic_builds += 1;
                s
            }
        };
        let llt = Llt::try_new_with_symbolic(symbolic, a, Side::Lower)
            .map_err(|e| LinearError::NotPositiveDefinite(format!("{e:?}")))?;
        llt.solve_in_place(rhs.as_mut());
        Ok(())
    }
}
