//! The bag-of-words baseline (DBoW2-style, as in ORB-SLAM / Kimera-Multi, with a flat
//! vocabulary): ORB descriptors are quantized to the nearest visual word (Hamming
//! distance), and an image becomes the L2-normalized TF-IDF histogram of its words.
//!
//! The vocabulary is trained here with k-majority (k-means for binary descriptors: the
//! centre of a cluster is the bitwise majority of its members) from a fixed seed, so the
//! same training images give the same file.

use std::path::Path;

use doorslam_frontend::opencv::core::Mat;
use doorslam_frontend::opencv::prelude::*;
use rayon::prelude::*;

use crate::image::GrayImage;
use crate::model::PlaceRecognitionError;

/// A 256-bit ORB descriptor.
pub type Orb = [u8; 32];

const MAGIC: &[u8; 8] = b"DSBOWV01";

/// File name of the default vocabulary inside `$DOORSLAM_HOME/models/`.
pub const DEFAULT_VOCABULARY_FILE: &str = "bow-orb-1024.voc";
/// Environment variable naming the vocabulary file (written into the env file by deploy/setup).
pub const VOCABULARY_ENV: &str = "DOORSLAM_BOW_VOCABULARY";

/// `$DOORSLAM_BOW_VOCABULARY`, else the default file next to the default model.
pub fn default_vocabulary_path() -> std::path::PathBuf {
    match std::env::var_os(VOCABULARY_ENV) {
        Some(p) => p.into(),
        None => crate::netvlad::models_dir().join(DEFAULT_VOCABULARY_FILE),
    }
}

fn hamming(a: &Orb, b: &Orb) -> u32 {
    let word = |x: &Orb, i: usize| u64::from_le_bytes(x[i * 8..i * 8 + 8].try_into().unwrap());
    (0..4).map(|i| (word(a, i) ^ word(b, i)).count_ones()).sum()
}

/// Visual words and their inverse document frequencies.
#[derive(Debug, Clone, PartialEq)]
pub struct Vocabulary {
    pub words: Vec<Orb>,
    /// idf_w = ln(N / n_w): N training images, n_w of them contain word w.
    pub idf: Vec<f32>,
}

/// A tiny deterministic generator (xorshift64*) for the vocabulary's seeding.
struct Rng(u64);
impl Rng {
    fn below(&mut self, n: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as usize % n
    }
}

impl Vocabulary {
    /// Trains `k` words on the ORB descriptors of training images (one list per image).
    pub fn train(images: &[Vec<Orb>], k: usize, iterations: usize, seed: u64) -> Option<Self> {
        let all: Vec<Orb> = images.iter().flatten().copied().collect();
        if k == 0 || all.len() < k {
            return None;
        }
        let mut rng = Rng(seed.max(1));
        // Seeds: k distinct descriptors drawn at random.
        let mut words: Vec<Orb> = Vec::with_capacity(k);
        while words.len() < k {
            let d = all[rng.below(all.len())];
            if !words.contains(&d) {
                words.push(d);
            }
        }
        for _ in 0..iterations {
            let labels: Vec<usize> = all.par_iter().map(|d| nearest_word(&words, d)).collect();
            let mut counts = vec![[0u32; 256]; k];
            let mut sizes = vec![0u32; k];
            for (d, &w) in all.iter().zip(&labels) {
                sizes[w] += 1;
                for (bit, c) in counts[w].iter_mut().enumerate() {
                    *c += u32::from(d[bit / 8] >> (bit % 8) & 1);
                }
            }
            for (w, word) in words.iter_mut().enumerate() {
                if sizes[w] == 0 {
                    continue; // an empty cluster keeps its word
                }
                let mut next = [0u8; 32];
                for (bit, &c) in counts[w].iter().enumerate() {
                    if 2 * c > sizes[w] {
                        next[bit / 8] |= 1 << (bit % 8);
                    }
                }
                *word = next;
            }
        }
        let mut vocabulary = Self {
            idf: vec![0.0; k],
            words,
        };
        let mut containing = vec![0u32; k];
        for img in images {
            let mut seen = vec![false; k];
            for d in img {
                seen[vocabulary.word(d)] = true;
            }
            for (c, s) in containing.iter_mut().zip(seen) {
                *c += u32::from(s);
            }
        }
        let n = images.len() as f32;
        vocabulary.idf = containing
            .iter()
            .map(|&c| (n / c.max(1) as f32).ln())
            .collect();
        Some(vocabulary)
    }

    /// The word of one descriptor (nearest in Hamming distance).
    pub fn word(&self, d: &Orb) -> usize {
        nearest_word(&self.words, d)
    }

    /// The L2-normalized TF-IDF vector (dense, one entry per word) of an image's features.
    pub fn describe(&self, descriptors: &[Orb]) -> Vec<f32> {
        let mut v = vec![0f32; self.words.len()];
        for d in descriptors {
            v[self.word(d)] += 1.0;
        }
        let n = descriptors.len().max(1) as f32;
        for (x, idf) in v.iter_mut().zip(&self.idf) {
            *x = *x / n * idf;
        }
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if norm > 0.0 {
            v.iter_mut().for_each(|x| *x /= norm);
        }
        v
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend((self.words.len() as u32).to_le_bytes());
        for (w, idf) in self.words.iter().zip(&self.idf) {
            out.extend(w);
            out.extend(idf.to_le_bytes());
        }
        out
    }

    /// Reads a vocabulary file written by [`Vocabulary::to_bytes`].
    pub fn from_file(path: &Path) -> Result<Self, PlaceRecognitionError> {
        let bad = |reason: String| PlaceRecognitionError::Vocabulary {
            path: path.to_path_buf(),
            reason,
        };
        let bytes = std::fs::read(path).map_err(|e| {
            bad(format!(
                "{e} (build it with `doorslam place vocabulary DIR... --out FILE`)"
            ))
        })?;
        let rest = bytes
            .strip_prefix(MAGIC)
            .ok_or_else(|| bad("not a doorslam BoW vocabulary (bad magic)".into()))?;
        let (k, body) = rest
            .split_first_chunk::<4>()
            .ok_or_else(|| bad("truncated header".into()))?;
        let k = u32::from_le_bytes(*k) as usize;
        if k == 0 || body.len() != k * 36 {
            return Err(bad(format!(
                "{} bytes of words, expected {k} x 36",
                body.len()
            )));
        }
        let mut words = Vec::with_capacity(k);
        let mut idf = Vec::with_capacity(k);
        for chunk in body.chunks_exact(36) {
            words.push(chunk[..32].try_into().unwrap());
            let v = f32::from_le_bytes(chunk[32..].try_into().unwrap());
            if !v.is_finite() || v < 0.0 {
                return Err(bad(format!("idf {v} is not a finite non-negative number")));
            }
            idf.push(v);
        }
        Ok(Self { words, idf })
    }
}

fn nearest_word(words: &[Orb], d: &Orb) -> usize {
    words
        .iter()
        .enumerate()
        .min_by_key(|(i, w)| (hamming(w, d), *i))
        .map_or(0, |(i, _)| i)
}

/// ORB descriptors of a grayscale image (the front-end's detector).
pub fn orb_descriptors(
    img: &GrayImage,
    max_features: i32,
) -> Result<Vec<Orb>, PlaceRecognitionError> {
    let orb = |e: String| PlaceRecognitionError::Orb(e);
    let mat = Mat::new_rows_cols_with_data(img.height as i32, img.width as i32, &img.pixels)
        .map_err(|e| orb(e.to_string()))?;
    // An owned Mat (one 360 kB copy, small next to ORB's 12 ms) for detect_orb's &Mat.
    let mat = mat.try_clone().map_err(|e| orb(e.to_string()))?;
    let features =
        doorslam_frontend::detect_orb(&mat, max_features).map_err(|e| orb(e.to_string()))?;
    Ok(features.descriptors)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random_orb(rng: &mut Rng) -> Orb {
        std::array::from_fn(|_| rng.below(256) as u8)
    }

    #[test]
    fn k_majority_finds_planted_words_and_roundtrips() {
        let mut rng = Rng(7);
        let centres: Vec<Orb> = (0..4).map(|_| random_orb(&mut rng)).collect();
        // Images of noisy copies (2 flipped bits) of the centres; image i lacks centre i.
        let images: Vec<Vec<Orb>> = (0..4)
            .map(|skip| {
                (0..200)
                    .filter(|j| j % 4 != skip)
                    .map(|j| {
                        let mut d = centres[j % 4];
                        for _ in 0..2 {
                            let bit = rng.below(256);
                            d[bit / 8] ^= 1 << (bit % 8);
                        }
                        d
                    })
                    .collect()
            })
            .collect();
        let voc = Vocabulary::train(&images, 4, 10, 1).unwrap();
        for c in &centres {
            assert_eq!(hamming(&voc.words[voc.word(c)], c), 0);
            // Each word is in 3 of 4 images: idf = ln(4/3).
            assert!((voc.idf[voc.word(c)] - (4f32 / 3.0).ln()).abs() < 1e-6);
        }
        let v = voc.describe(&images[0]);
        assert!((v.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-5);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("voc.bin");
        std::fs::write(&path, voc.to_bytes()).unwrap();
        assert_eq!(Vocabulary::from_file(&path).unwrap(), voc);
        std::fs::write(&path, &voc.to_bytes()[..50]).unwrap();
        let err = Vocabulary::from_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("voc.bin") && err.contains("expected 4 x 36"),
            "{err}"
        );
    }
}
