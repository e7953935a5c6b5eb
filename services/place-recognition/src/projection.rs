//! A linear projection of long descriptors to the 128-D wire form: PCA fitted on training
//! descriptors, optionally whitened,
//!   y = Λ^(-p/2) Uᵀ (x − μ),
//! with μ the training mean, U the leading eigenvectors of the training covariance, Λ their
//! eigenvalues and p the whitening power (0: plain PCA, 1: full whitening).
//!
//! The bag-of-words vector (1,024 TF-IDF weights, ~470 of them non-zero: 2.8 kB as a
//! sparse vector) has no wire form of its own; projected, it travels as the same 128 int8
//! values as NetVLAD's (`doorslam_ipc::wire::Descriptor`). BENCHMARKS.md has the recall
//! the projection costs.
//!
//! Why y is not normalized again: with p = 0, ‖y_a − y_b‖ is the distance of the two unit
//! TF-IDF vectors within the kept components, so distances stay comparable across images
//! and one threshold fits all. Normalizing again stretches images whose vector lies
//! partly outside the kept components: on the validation town it cut the area under the
//! precision-recall curve from 0.72 to 0.57 at the same recall@1 (BENCHMARKS.md).

use nalgebra::{DMatrix, DVector};

/// A fitted projection `d_in -> d_out`.
#[derive(Debug, Clone, PartialEq)]
pub struct Projection {
    /// μ, `d_in` values.
    pub mean: Vec<f32>,
    /// Rows of Λ^(-p/2) Uᵀ: `d_out` rows of `d_in` values, row-major.
    pub matrix: Vec<f32>,
    pub d_in: usize,
    pub d_out: usize,
}

/// Why a projection cannot be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    #[error("{got} training vectors, need more than {d_out} to fit {d_out} components")]
    TooFewSamples { got: usize, d_out: usize },
    #[error("training vector {index} has {got} values, expected {want}")]
    Length {
        index: usize,
        got: usize,
        want: usize,
    },
    #[error("{d_out} components requested from {d_in}-D vectors")]
    Dimensions { d_in: usize, d_out: usize },
}

impl Projection {
    /// PCA of `samples` (all the same length) to `d_out` components, each divided by its
    /// standard deviation to the power `whiten` (0 = plain PCA). Deterministic: float64
    /// covariance summed in sample order, each eigenvector's sign fixed so that its largest
    /// component is positive.
    pub fn fit(samples: &[Vec<f32>], d_out: usize, whiten: f64) -> Result<Self, FitError> {
        let d_in = samples.first().map_or(0, Vec::len);
        if d_out == 0 || d_out > d_in {
            return Err(FitError::Dimensions { d_in, d_out });
        }
        if samples.len() <= d_out {
            return Err(FitError::TooFewSamples {
                got: samples.len(),
                d_out,
            });
        }
        if let Some((index, s)) = samples.iter().enumerate().find(|(_, s)| s.len() != d_in) {
            return Err(FitError::Length {
                index,
                got: s.len(),
                want: d_in,
            });
        }
        let n = samples.len() as f64;
        let mut mean = DVector::<f64>::zeros(d_in);
        for s in samples {
            for (m, &x) in mean.iter_mut().zip(s) {
                *m += f64::from(x);
            }
        }
        mean /= n;
        // Centered samples as columns: C = X Xᵀ / n.
        let x = DMatrix::<f64>::from_fn(d_in, samples.len(), |i, j| {
            f64::from(samples[j][i]) - mean[i]
        });
        let covariance = (&x * x.transpose()) / n;
        let eigen = covariance.symmetric_eigen();
        let mut order: Vec<usize> = (0..d_in).collect();
        order.sort_by(|&a, &b| {
            eigen.eigenvalues[b]
                .total_cmp(&eigen.eigenvalues[a])
                .then(a.cmp(&b))
        });
        // The smallest kept eigenvalue may be ~0 for rank-deficient data: floor the
        // whitening scale at 1e-6 of the largest, so no component is blown up by noise.
        let floor = eigen.eigenvalues[order[0]].max(0.0) * 1e-6 + 1e-12;
        let mut matrix = Vec::with_capacity(d_out * d_in);
        for &k in &order[..d_out] {
            let column = eigen.eigenvectors.column(k);
            let largest = column
                .iter()
                .copied()
                .max_by(|a, b| a.abs().total_cmp(&b.abs()))
                .unwrap_or(1.0);
            let sign = if largest < 0.0 { -1.0 } else { 1.0 };
            let scale = sign / eigen.eigenvalues[k].max(floor).powf(whiten / 2.0);
            matrix.extend(column.iter().map(|&u| (u * scale) as f32));
        }
        Ok(Self {
            mean: mean.iter().map(|&m| m as f32).collect(),
            matrix,
            d_in,
            d_out,
        })
    }

    /// The projection of `x` (`d_in` values): `d_out` values, not normalized (see the
    /// module documentation).
    pub fn apply(&self, x: &[f32]) -> Vec<f32> {
        let centered: Vec<f32> = x.iter().zip(&self.mean).map(|(a, m)| a - m).collect();
        self.matrix
            .chunks_exact(self.d_in)
            .map(|row| dot(row, &centered))
            .collect()
    }

    /// Little-endian bytes: `d_in`, `d_out` (u32), mean, matrix (f32).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(8 + 4 * (self.mean.len() + self.matrix.len()));
        out.extend((self.d_in as u32).to_le_bytes());
        out.extend((self.d_out as u32).to_le_bytes());
        for v in self.mean.iter().chain(&self.matrix) {
            out.extend(v.to_le_bytes());
        }
        out
    }

    /// Reads [`Self::to_bytes`]'s layout for `d_in`-D input; the error says what is wrong.
    pub fn from_bytes(bytes: &[u8], d_in: usize) -> Result<Self, String> {
        let u32_at = |i: usize| {
            bytes
                .get(i..i + 4)
                .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
        };
        let (Some(got_in), Some(d_out)) = (u32_at(0), u32_at(4)) else {
            return Err("truncated projection header".into());
        };
        if got_in != d_in || d_out == 0 || d_out > d_in {
            return Err(format!(
                "projection {got_in} -> {d_out}, expected {d_in} -> at most {d_in}"
            ));
        }
        let want = 8 + 4 * d_in * (1 + d_out);
        if bytes.len() != want {
            return Err(format!(
                "projection has {} bytes, expected {want} ({d_in} -> {d_out})",
                bytes.len()
            ));
        }
        let values: Vec<f32> = bytes[8..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
            .collect();
        if let Some(v) = values.iter().find(|v| !v.is_finite()) {
            return Err(format!("projection holds a non-finite value {v}"));
        }
        let (mean, matrix) = values.split_at(d_in);
        Ok(Self {
            mean: mean.to_vec(),
            matrix: matrix.to_vec(),
            d_in,
            d_out,
        })
    }
}

/// Dot product with eight partial sums (vectorizes; see `matching::distance2`).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (xa, xb) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += xa[k] * xb[k];
        }
    }
    acc.iter().sum::<f32>() + tail
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples spread mostly along two known directions of a 6-D space.
    fn samples() -> Vec<Vec<f32>> {
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut r = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        (0..200)
            .map(|_| {
                let (a, b) = (4.0 * r(), 2.0 * r());
                vec![1.0 + a, a, b + 0.01 * r(), -b, 0.01 * r(), 0.5 + 0.01 * r()]
            })
            .collect()
    }

    #[test]
    fn pca_finds_the_main_directions_and_is_deterministic() {
        let s = samples();
        let p = Projection::fit(&s, 2, 0.0).unwrap();
        let row = |k: usize| &p.matrix[k * 6..(k + 1) * 6];
        let h = std::f32::consts::FRAC_1_SQRT_2;
        // First component along (1, 1, 0, ...)/√2, second along (0, 0, 1, -1, ...)/√2
        // (tilted by the sample correlation of a and b, ~1/√200).
        for (got, want) in row(0).iter().zip([h, h, 0.0, 0.0, 0.0, 0.0]) {
            assert!((got - want).abs() < 0.1, "{:?}", row(0));
        }
        for (got, want) in row(1).iter().zip([0.0, 0.0, h, -h, 0.0, 0.0]) {
            assert!((got - want).abs() < 0.1, "{:?}", row(1));
        }
        assert!(row(0)[4].abs() < 0.01 && row(1)[5].abs() < 0.01);
        assert_eq!(Projection::fit(&s, 2, 0.0).unwrap(), p);
        // Distances within the kept components are kept: samples differ by a along
        // (1, 1, 0, ...) and b along (0, 0, 1, -1, ...), so ‖Δy‖² ≈ 2Δa² + 2Δb².
        let (ya, yb) = (p.apply(&s[3]), p.apply(&s[4]));
        let dy2: f32 = ya.iter().zip(&yb).map(|(a, b)| (a - b) * (a - b)).sum();
        let dx2: f32 = s[3].iter().zip(&s[4]).map(|(a, b)| (a - b) * (a - b)).sum();
        assert!((dy2 - dx2).abs() < 1e-3 * dx2.max(1.0), "{dy2} vs {dx2}");
        // Whitening divides each direction by its standard deviation.
        let w = Projection::fit(&s, 2, 1.0).unwrap();
        let spread = |p: &Projection, k: usize| {
            let v: Vec<f32> = s
                .iter()
                .map(|x| {
                    let c: Vec<f32> = x.iter().zip(&p.mean).map(|(a, m)| a - m).collect();
                    dot(&p.matrix[k * 6..(k + 1) * 6], &c)
                })
                .collect();
            (v.iter().map(|a| a * a).sum::<f32>() / v.len() as f32).sqrt()
        };
        assert!((spread(&w, 0) - 1.0).abs() < 1e-3 && (spread(&w, 1) - 1.0).abs() < 1e-3);
    }

    #[test]
    fn bytes_round_trip_and_bad_input_is_named() {
        let p = Projection::fit(&samples(), 3, 0.5).unwrap();
        let bytes = p.to_bytes();
        assert_eq!(Projection::from_bytes(&bytes, 6).unwrap(), p);
        let err = Projection::from_bytes(&bytes[..bytes.len() - 1], 6).unwrap_err();
        assert!(err.contains("expected"), "{err}");
        assert!(Projection::from_bytes(&bytes, 7).is_err());
        assert!(matches!(
            Projection::fit(&samples()[..3], 3, 0.0),
            Err(FitError::TooFewSamples { got: 3, d_out: 3 })
        ));
        assert!(matches!(
            Projection::fit(&[vec![0.0; 2], vec![0.0; 3], vec![0.0; 2]], 1, 0.0),
            Err(FitError::Length { index: 1, .. })
        ));
    }
}
