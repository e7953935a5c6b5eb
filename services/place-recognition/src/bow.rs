//! The bag-of-words baseline (DBoW2-style, as in ORB-SLAM / Kimera-Multi, with a flat
//! vocabulary): ORB descriptors are quantized to the nearest visual word (Hamming
//! distance), and an image becomes the L2-normalized TF-IDF histogram of its words.
//!
//! The vocabulary is trained here with k-majority (k-means for binary descriptors: the
//! centre of a cluster is the bitwise majority of its members) from a fixed seed, so the
//! same training images give the same file.

use std::path::Path;

use rayon::prelude::*;

use crate::image::GrayImage;
use crate::model::PlaceRecognitionError;
use crate::projection::Projection;

/// A 256-bit ORB descriptor.
pub type Orb = [u8; 32];

/// Words and idf only (the first format: no wire form).
const MAGIC_V1: &[u8; 8] = b"DSBOWV01";
/// Words, idf, then the projection to the 128-D wire form ([`Projection::to_bytes`]).
const MAGIC_V2: &[u8; 8] = b"DSBOWV02";

/// File name of the default vocabulary inside `$DOORSLAM_HOME/models/` (with its 128-D
/// wire projection; the name changed with the format so `deploy/setup` builds it anew).
pub const DEFAULT_VOCABULARY_FILE: &str = "bow-orb-1024-w128.voc";
/// Components of the wire projection (the int8 wire descriptor's length).
pub const WIRE_DIM: usize = doorslam_ipc::wire::DESCRIPTOR_DIM;
/// Whitening power of the wire projection (chosen on the validation town, BENCHMARKS.md).
pub const WIRE_WHITENING: f64 = 0.0;
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
    /// TF-IDF vector -> 128-D wire form, fitted on the training images
    /// ([`Vocabulary::fit_projection`]); `None` in a first-format file.
    pub projection: Option<Projection>,
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
            projection: None,
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

    /// Fits the wire projection (PCA of the TF-IDF vectors of the training images, to
    /// `d_out` components, whitening power `whiten`).
    pub fn fit_projection(
        &mut self,
        images: &[Vec<Orb>],
        d_out: usize,
        whiten: f64,
    ) -> Result<(), crate::projection::FitError> {
        let vectors: Vec<Vec<f32>> = images.par_iter().map(|d| self.describe(d)).collect();
        self.projection = Some(Projection::fit(&vectors, d_out, whiten)?);
        Ok(())
    }

    /// The wire form of a TF-IDF vector ([`Self::describe`]'s output): its 128 principal
    /// components (not normalized again: see [`crate::projection`]); `None` without a
    /// projection.
    pub fn project(&self, tf_idf: &[f32]) -> Option<Vec<f32>> {
        self.projection.as_ref().map(|p| p.apply(tf_idf))
    }

    /// The file's bytes: the second format when there is a projection, else the first.
    pub fn to_bytes(&self) -> Vec<u8> {
        let magic = if self.projection.is_some() {
            MAGIC_V2
        } else {
            MAGIC_V1
        };
        let mut out = magic.to_vec();
        out.extend((self.words.len() as u32).to_le_bytes());
        for (w, idf) in self.words.iter().zip(&self.idf) {
            out.extend(w);
            out.extend(idf.to_le_bytes());
        }
        if let Some(p) = &self.projection {
            out.extend(p.to_bytes());
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
        let (rest, projected) = if let Some(rest) = bytes.strip_prefix(MAGIC_V2) {
            (rest, true)
        } else if let Some(rest) = bytes.strip_prefix(MAGIC_V1) {
            (rest, false)
        } else {
            return Err(bad("not a doorslam BoW vocabulary (bad magic)".into()));
        };
        let (k, body) = rest
            .split_first_chunk::<4>()
            .ok_or_else(|| bad("truncated header".into()))?;
        let k = u32::from_le_bytes(*k) as usize;
        let words_len = k.saturating_mul(36);
        let short = if projected {
            body.len() < words_len
        } else {
            body.len() != words_len
        };
        if k == 0 || short {
            return Err(bad(format!(
                "{} bytes of words, expected {k} x 36",
                body.len()
            )));
        }
        let (body, projection) = body.split_at(words_len);
        let projection = if projected {
            Some(Projection::from_bytes(projection, k).map_err(bad)?)
        } else {
            None
        };
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
        Ok(Self {
            words,
            idf,
            projection,
        })
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
    let orb = |e: doorslam_vision::VisionError| PlaceRecognitionError::Orb(e.to_string());
    let gray = doorslam_vision::Gray::new(img.width, img.height, &img.pixels).map_err(orb)?;
    let features = doorslam_vision::detect_orb_gray(&gray, max_features).map_err(orb)?;
    Ok(features.descriptors)
}

/// The ORB descriptors a front-end keyframe carries for this stereo pair: its detector's
/// features (GFTT + upright ORB by default) that found a stereo match, as in
/// `doorslam_frontend::StereoVo`'s keyframes (the extractor of `doorslam_vision`).
pub fn keyframe_descriptors(
    extractor: &mut doorslam_vision::Extractor,
    left: &GrayImage,
    right: &GrayImage,
) -> Result<Vec<Orb>, PlaceRecognitionError> {
    fn orb(e: doorslam_vision::VisionError) -> PlaceRecognitionError {
        PlaceRecognitionError::Orb(e.to_string())
    }
    fn gray(img: &GrayImage) -> Result<doorslam_vision::Gray<'_>, PlaceRecognitionError> {
        doorslam_vision::Gray::new(img.width, img.height, &img.pixels).map_err(orb)
    }
    let (l, r) = (gray(left)?, gray(right)?);
    let features = extractor.extract(&l, &r).map_err(orb)?;
    Ok(features
        .features
        .iter()
        .take(doorslam_ipc::MAX_KEYFRAME_FEATURES)
        .map(|f| f.descriptor)
        .collect())
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
        let mut voc = Vocabulary::train(&images, 4, 10, 1).unwrap();
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
        // With the wire projection (second format): 4 words -> 2 components.
        let first_format = voc.clone();
        voc.fit_projection(&images, 2, 0.0).unwrap();
        let w = voc.project(&voc.describe(&images[1])).unwrap();
        assert_eq!(w.len(), 2);
        assert!(
            w.iter().all(|x| x.is_finite()) && w.iter().any(|x| *x != 0.0),
            "{w:?}"
        );
        std::fs::write(&path, voc.to_bytes()).unwrap();
        assert_eq!(Vocabulary::from_file(&path).unwrap(), voc);
        assert_eq!(first_format.project(&w), None);
        std::fs::write(&path, &voc.to_bytes()[..voc.to_bytes().len() - 4]).unwrap();
        let err = Vocabulary::from_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("voc.bin") && err.contains("projection"),
            "{err}"
        );
        let voc = first_format;
        std::fs::write(&path, &voc.to_bytes()[..50]).unwrap();
        let err = Vocabulary::from_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("voc.bin") && err.contains("expected 4 x 36"),
            "{err}"
        );
    }
}
