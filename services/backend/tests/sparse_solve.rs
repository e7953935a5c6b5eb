//! faer's sparse Cholesky (with a reused symbolic factorization) agrees with a dense
//! nalgebra Cholesky solve on SPD systems shaped like pose-graph normal equations.

use doorslam_backend::{LinearError, SparseCholesky};
use nalgebra::{DMatrix, DVector};

/// xorshift64*: a deterministic generator so the test needs no RNG crate.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545F4914F6CDD1D) >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

/// A = JᵀJ + I for a chain of `n` 6-dof blocks with odometry and a few loop closures:
/// block-sparse like a pose graph's normal equations.
fn pose_graph_like(n_poses: usize, rng: &mut Rng) -> DMatrix<f64> {
    let n = 6 * n_poses;
    let mut pairs: Vec<(usize, usize)> = (0..n_poses - 1).map(|i| (i, i + 1)).collect();
    pairs.extend([(0, n_poses - 1), (2, n_poses / 2), (1, n_poses - 3)]);
    let mut a = DMatrix::<f64>::identity(n, n);
    for (i, j) in pairs {
        // One 6-row residual block touching poses i and j.
        let mut jac = DMatrix::<f64>::zeros(6, n);
        for r in 0..6 {
            for c in 0..6 {
                jac[(r, 6 * i + c)] = rng.next();
                jac[(r, 6 * j + c)] = rng.next();
            }
        }
        a += jac.transpose() * &jac;
    }
    a
}

fn lower_triplets(a: &DMatrix<f64>) -> Vec<(usize, usize, f64)> {
    let mut t = Vec::new();
    for c in 0..a.ncols() {
        for r in c..a.nrows() {
            if a[(r, c)] != 0.0 {
                t.push((r, c, a[(r, c)]));
            }
        }
    }
    t
}

#[test]
fn sparse_cholesky_matches_dense_and_reuses_symbolic() {
    let mut rng = Rng(0x9E3779B97F4A7C15);
    let mut solver = SparseCholesky::new();
    for round in 0..3 {
        // Same pattern every round, new values: the symbolic analysis must be reused.
        let mut a = pose_graph_like(40, &mut Rng(7));
        a += DMatrix::identity(a.nrows(), a.ncols()) * (round as f64);
        let b = DVector::from_fn(a.nrows(), |_, _| rng.next());
        let dense = a.clone().cholesky().expect("SPD").solve(&b);

        let sparse_a = SparseCholesky::lower_from_triplets(a.nrows(), &lower_triplets(&a)).unwrap();
        let x = solver.solve(&sparse_a, b.as_slice()).unwrap();
        let max_err = x
            .iter()
            .zip(dense.iter())
            .map(|(s, d)| (s - d).abs())
            .fold(0.0, f64::max);
        assert!(
            max_err < 1e-9,
            "round {round}: sparse vs dense max |dx| = {max_err:e}"
        );
        // The residual itself is small too (not just agreement of two wrong answers).
        let r = &a * DVector::from_vec(x) - &b;
        assert!(r.amax() < 1e-9, "round {round}: residual {:e}", r.amax());
    }
    assert_eq!(
        solver.symbolic_builds(),
        1,
        "symbolic factorization recomputed"
    );
}

#[test]
fn indefinite_and_malformed_systems_are_errors() {
    let mut solver = SparseCholesky::new();
    // [[1, 2], [2, 1]] has eigenvalues 3 and -1.
    let a =
        SparseCholesky::lower_from_triplets(2, &[(0, 0, 1.0), (1, 0, 2.0), (1, 1, 1.0)]).unwrap();
    assert!(matches!(
        solver.solve(&a, &[1.0, 1.0]),
        Err(LinearError::NotPositiveDefinite(_))
    ));
    assert!(matches!(
        solver.solve(&a, &[1.0]),
        Err(LinearError::RhsLength { got: 1, want: 2 })
    ));
}
