//! Descriptor distances and nearest-neighbour search, in float and on the int8 wire form.
//!
//! On the wire a descriptor is `v ≈ s q` (one scale `s`, 128 int8 values `q`, see
//! `doorslam_ipc::wire::Descriptor`). The squared Euclidean distance expands into integer
//! dot products,
//!   ‖v_a − v_b‖² = s_a² (q_a·q_a) + s_b² (q_b·q_b) − 2 s_a s_b (q_a·q_b),
//! so matching never decodes to f32: each term is an exact i32 sum of i8 x i8 products
//! (|sum| ≤ 128 · 127² < 2³¹), and the norms `q·q` are computed once per descriptor.

use doorslam_ipc::wire::{Descriptor, Descriptors, Header, Message, RobotId, DESCRIPTOR_DIM};

/// Bytes on the team link per descriptor when `batch` consecutive keyframes' descriptors
/// travel in one `Descriptors` message, header included (the wire encoder's own count).
pub fn wire_bytes_per_descriptor(batch: usize) -> f64 {
    let batch = batch.max(1);
    let descriptors = (0..batch as u64)
        .map(|i| Descriptor {
            key: (u64::from(b'a') << 56) | i,
            scale: 1.0 / 127.0,
            values: [0; DESCRIPTOR_DIM],
        })
        .collect();
    let message = Message::new(
        Header {
            sender: RobotId::new("a").expect("'a' is a valid robot id"),
            epoch: 0,
            sequence: 0,
        },
        Descriptors {
            robot: 0,
            keyframes: 0..batch as u64,
            descriptors,
        },
    );
    message.encoded_len() as f64 / batch as f64
}

/// Squared Euclidean distance of two float descriptors. Eight partial sums: a single
/// running sum fixes the order of float additions and keeps the compiler from vectorizing.
pub fn distance2(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| (x - y) * (x - y))
        .sum();
    for (xa, xb) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += (xa[k] - xb[k]) * (xa[k] - xb[k]);
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// Integer dot product of two quantized descriptors (16 lanes of i32 partial sums, which
/// the compiler maps onto SIMD multiply-adds).
pub fn dot_i8(a: &[i8; DESCRIPTOR_DIM], b: &[i8; DESCRIPTOR_DIM]) -> i32 {
    let mut acc = [0i32; 16];
    for (xa, xb) in a.chunks_exact(16).zip(b.chunks_exact(16)) {
        for k in 0..16 {
            acc[k] += i32::from(xa[k]) * i32::from(xb[k]);
        }
    }
    acc.iter().sum()
}

/// A quantized descriptor with its integer squared norm, ready for matching.
#[derive(Debug, Clone)]
pub struct Quantized {
    pub descriptor: Descriptor,
    norm2: i32,
}

impl Quantized {
    pub fn new(descriptor: Descriptor) -> Self {
        let norm2 = dot_i8(&descriptor.values, &descriptor.values);
        Self { descriptor, norm2 }
    }

    /// Squared Euclidean distance between the two dequantized vectors, from integer sums.
    pub fn distance2(&self, other: &Quantized) -> f32 {
        let (sa, sb) = (self.descriptor.scale, other.descriptor.scale);
        let cross = dot_i8(&self.descriptor.values, &other.descriptor.values);
        (sa * sa * self.norm2 as f32 + sb * sb * other.norm2 as f32 - 2.0 * sa * sb * cross as f32)
            .max(0.0)
    }
}

/// The nearest neighbour of each query among `database` entries it may match: `(index
/// into database, distance)`, `None` when `allowed` rejects them all. Brute force: 1,000
/// queries x 10,000 keyframes is 10⁷ distances (BENCHMARKS.md has the time).
pub fn nearest<T>(
    queries: &[T],
    database: &[T],
    dist2: impl Fn(&T, &T) -> f32,
    allowed: impl Fn(usize, usize) -> bool,
) -> Vec<Option<(usize, f32)>> {
    queries
        .iter()
        .enumerate()
        .map(|(qi, q)| {
            database
                .iter()
                .enumerate()
                .filter(|(di, _)| allowed(qi, *di))
                .map(|(di, d)| (di, dist2(q, d)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(di, d2)| (di, d2.sqrt()))
        })
        .collect()
}

/// Deterministic pseudo-random unit vectors (xorshift), for timing the matcher.
pub fn random_unit_vectors(n: usize, dim: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut x = seed.max(1);
    (0..n)
        .map(|_| {
            let v: Vec<f32> = (0..dim)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
                })
                .collect();
            let n = v.iter().map(|a| a * a).sum::<f32>().sqrt().max(1e-12);
            v.iter().map(|a| a / n).collect()
        })
        .collect()
}

/// Seconds of a brute-force nearest-neighbour search of `queries` random descriptors
/// against `database` ones, float and int8 (one thread), and how many nearest neighbours
/// the two agree on.
pub fn time_brute_force(queries: usize, database: usize) -> (f64, f64, usize) {
    let q = random_unit_vectors(queries, DESCRIPTOR_DIM, 1);
    let d = random_unit_vectors(database, DESCRIPTOR_DIM, 2);
    let quantize = |v: &Vec<Vec<f32>>| -> Vec<Quantized> {
        v.iter()
            .enumerate()
            .filter_map(|(i, x)| Descriptor::quantize(i as u64, x).ok().map(Quantized::new))
            .collect()
    };
    let (qq, dq) = (quantize(&q), quantize(&d));
    let start = std::time::Instant::now();
    let nf = nearest(&q, &d, |a, b| distance2(a, b), |_, _| true);
    let float_s = start.elapsed().as_secs_f64();
    let start = std::time::Instant::now();
    let ni = nearest(&qq, &dq, |a, b| a.distance2(b), |_, _| true);
    let int8_s = start.elapsed().as_secs_f64();
    let agree = nf
        .iter()
        .zip(&ni)
        .filter(|(a, b)| a.map(|x| x.0) == b.map(|x| x.0))
        .count();
    (float_s, int8_s, agree)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(seed: u32) -> Vec<f32> {
        // A deterministic pseudo-random unit vector.
        let mut x = seed.wrapping_mul(2654435761).max(1);
        let v: Vec<f32> = (0..DESCRIPTOR_DIM)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                (x as f32 / u32::MAX as f32) - 0.5
            })
            .collect();
        let n = v.iter().map(|a| a * a).sum::<f32>().sqrt();
        v.iter().map(|a| a / n).collect()
    }

    #[test]
    fn integer_distance_equals_the_dequantized_one() {
        for seed in 1..20 {
            let (a, b) = (unit(seed), unit(seed + 100));
            let qa = Quantized::new(Descriptor::quantize(0, &a).unwrap());
            let qb = Quantized::new(Descriptor::quantize(1, &b).unwrap());
            let deq = distance2(&qa.descriptor.to_f32(), &qb.descriptor.to_f32());
            assert!((qa.distance2(&qb) - deq).abs() < 1e-4, "{seed}");
            // and close to the float distance: each component is off by <= scale / 2.
            assert!((qa.distance2(&qb).sqrt() - distance2(&a, &b).sqrt()).abs() < 0.02);
        }
    }

    #[test]
    fn nearest_respects_the_filter() {
        let db = vec![unit(1), unit(2), unit(3)];
        let q = vec![unit(2)];
        let nn = nearest(&q, &db, |a, b| distance2(a, b), |_, _| true);
        assert_eq!(nn[0].unwrap().0, 1);
        let nn = nearest(&q, &db, |a, b| distance2(a, b), |_, d| d != 1);
        assert_ne!(nn[0].unwrap().0, 1);
        assert!(nearest(&q, &db, |a, b| distance2(a, b), |_, _| false)[0].is_none());
    }
}
