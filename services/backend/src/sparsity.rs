//! Block-sparse symmetric matrices with a fixed pattern, assembled in place.
//!
//! The normal equations of a pose graph have one `d × d` block per pose on the diagonal and
//! one per edge off it. The pattern never changes while optimizing, so it is built once in
//! compressed-column form (lower triangle) and every iteration only adds into the values
//! array at precomputed offsets: no triplet sorting, no allocation in the loop.

use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};

use doorslam_geometry::TangentMatrix;

/// The lower-triangular CSC pattern of a symmetric block matrix.
pub struct BlockPattern {
    bdim: usize,
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Sorted row blocks (> b) present in block column b.
    below: Vec<Vec<usize>>,
}

impl BlockPattern {
    /// `n_blocks` diagonal blocks of size `bdim` and the off-diagonal blocks of `pairs`
    /// (unordered, duplicates and self-pairs allowed and ignored).
    pub fn new(
        n_blocks: usize,
        bdim: usize,
        pairs: impl IntoIterator<Item = (usize, usize)>,
    ) -> Self {
        let mut below: Vec<Vec<usize>> = vec![Vec::new(); n_blocks];
        for (a, b) in pairs {
            if a != b {
                below[a.min(b)].push(a.max(b));
            }
        }
        for rows in &mut below {
            rows.sort_unstable();
            rows.dedup();
        }
        let n = n_blocks * bdim;
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        for (b, rows) in below.iter().enumerate() {
            for c in 0..bdim {
                row_idx.extend(b * bdim + c..(b + 1) * bdim);
                for &a in rows {
                    row_idx.extend(a * bdim..(a + 1) * bdim);
                }
                col_ptr.push(row_idx.len());
            }
        }
        Self {
            bdim,
            n,
            col_ptr,
            row_idx,
            below,
        }
    }

    pub fn dim(&self) -> usize {
        self.n
    }
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// Offsets of the diagonal entries.
    pub fn diagonal_offsets(&self) -> Vec<usize> {
        (0..self.n).map(|col| self.col_ptr[col]).collect()
    }

    /// For block (a, b), per column c of the block, the offset of entry (row 0 of the
    /// block, column c): entry (r, c) is at `offsets[c] + r` for off-diagonal blocks and
    /// at `offsets[c] + r - c` (r ≥ c) for diagonal blocks. `None` if the block is absent.
    pub fn block_offsets(&self, a: usize, b: usize) -> Option<[usize; 6]> {
        let (hi, lo) = (a.max(b), a.min(b));
        let mut out = [0usize; 6];
        if hi == lo {
            for (c, o) in out.iter_mut().enumerate().take(self.bdim) {
                *o = self.col_ptr[lo * self.bdim + c];
            }
            return Some(out);
        }
        let k = self.below[lo].binary_search(&hi).ok()?;
        for (c, o) in out.iter_mut().enumerate().take(self.bdim) {
            *o = self.col_ptr[lo * self.bdim + c] + (self.bdim - c) + k * self.bdim;
        }
        Some(out)
    }

    /// Adds `m` (top-left `bdim × bdim`) into the diagonal block at `offsets` (lower part).
    pub fn add_diagonal(&self, values: &mut [f64], offsets: &[usize; 6], m: &TangentMatrix) {
        for c in 0..self.bdim {
            for r in c..self.bdim {
                values[offsets[c] + r - c] += m[(r, c)];
            }
        }
    }

    /// Adds `m` into the off-diagonal block (hi, lo) at `offsets`: `m` must be the block
    /// with rows of the higher-index pose and columns of the lower one.
    pub fn add_off_diagonal(&self, values: &mut [f64], offsets: &[usize; 6], m: &TangentMatrix) {
        for c in 0..self.bdim {
            for r in 0..self.bdim {
                values[offsets[c] + r] += m[(r, c)];
            }
        }
    }

    /// A faer view of the matrix with these values.
    pub fn as_matrix<'a>(&'a self, values: &'a [f64]) -> SparseColMatRef<'a, usize, f64> {
        let symbolic = SymbolicSparseColMatRef::new_checked(
            self.n,
            self.n,
            &self.col_ptr,
            None,
            &self.row_idx,
        );
        SparseColMatRef::new(symbolic, values)
    }
}
