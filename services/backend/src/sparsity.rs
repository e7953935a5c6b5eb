//! Block-sparse symmetric matrices with a fixed pattern, assembled in place.
//!
//! The normal equations of a pose graph have one `d × d` block per pose on the diagonal and
//! one per edge off it. The pattern never changes while optimizing, so it is built once in
//! compressed-column form (lower triangle) and every iteration only adds into the values
//! array at precomputed offsets: no triplet sorting, no allocation in the loop.

use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};

use doorslam_geometry::TangentMatrix;

/// Per column c of a diagonal block, the offset of its entry (c, c); entry (r, c), r ≥ c,
/// is at `offset[c] + r - c`. Only [`BlockPattern::diagonal_block`] makes one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DiagonalSlot([usize; 6]);

/// Per column c of an off-diagonal block, the offset of its entry (0, c); entry (r, c) is
/// at `offset[c] + r`. Only [`BlockPattern::off_diagonal_block`] makes one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OffDiagonalSlot([usize; 6]);

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

    /// Where diagonal block (a, a) lives, `None` if `a` is out of range. Diagonal and
    /// off-diagonal blocks are stored differently (lower triangle only, versus full), so
    /// they have distinct slot types: writing one as the other would spill into the
    /// neighbouring columns' entries.
    pub fn diagonal_block(&self, a: usize) -> Option<DiagonalSlot> {
        if a * self.bdim >= self.n {
            return None;
        }
        let mut out = [0usize; 6];
        for (c, o) in out.iter_mut().enumerate().take(self.bdim) {
            *o = self.col_ptr[a * self.bdim + c];
        }
        Some(DiagonalSlot(out))
    }

    /// The slots of all diagonal blocks, in block order.
    pub fn diagonal_blocks(&self) -> Vec<DiagonalSlot> {
        (0..self.n / self.bdim.max(1))
            .filter_map(|a| self.diagonal_block(a))
            .collect()
    }

    /// Where off-diagonal block (max(a, b), min(a, b)) lives; `None` if `a == b` (that is
    /// a diagonal block) or the pair is not in the pattern.
    pub fn off_diagonal_block(&self, a: usize, b: usize) -> Option<OffDiagonalSlot> {
        let (hi, lo) = (a.max(b), a.min(b));
        if hi == lo {
            return None;
        }
        let k = self.below.get(lo)?.binary_search(&hi).ok()?;
        let mut out = [0usize; 6];
        for (c, o) in out.iter_mut().enumerate().take(self.bdim) {
            *o = self.col_ptr[lo * self.bdim + c] + (self.bdim - c) + k * self.bdim;
        }
        Some(OffDiagonalSlot(out))
    }

    /// Adds the lower part of `m` (top-left `bdim × bdim`) into a diagonal block.
    pub fn add_diagonal(&self, values: &mut [f64], slot: &DiagonalSlot, m: &TangentMatrix) {
        for c in 0..self.bdim {
            for r in c..self.bdim {
                values[slot.0[c] + r - c] += m[(r, c)];
            }
        }
    }

    /// Adds `m` into an off-diagonal block: `m` must be the block with rows of the
    /// higher-index pose and columns of the lower one.
    pub fn add_off_diagonal(&self, values: &mut [f64], slot: &OffDiagonalSlot, m: &TangentMatrix) {
        for c in 0..self.bdim {
            for r in 0..self.bdim {
                values[slot.0[c] + r] += m[(r, c)];
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
