//! One matching interface over the two global descriptors: the NetVLAD network and the
//! bag-of-words baseline. Both give L2-normalized vectors compared by Euclidean distance,
//! and both have a 128-D wire form ([`Describer::to_wire`]) that robots exchange as int8.

use std::path::Path;

use doorslam_ipc::wire::DESCRIPTOR_DIM;

use crate::bow::{orb_descriptors, Orb, Vocabulary};
use crate::candidates::ChainConfig;
use crate::image::GrayImage;
use crate::model::PlaceRecognitionError;
use crate::netvlad::NetVlad;

/// Which descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
pub enum Method {
    #[serde(rename = "netvlad")]
    NetVlad,
    #[serde(rename = "bow")]
    BagOfWords,
}

impl Method {
    /// The name on the command line, in `robot.toml` and in JSON output.
    pub fn name(self) -> &'static str {
        match self {
            Method::NetVlad => "netvlad",
            Method::BagOfWords => "bow",
        }
    }

    /// The match threshold on the int8 wire form (Euclidean distance of the 128-D wire
    /// descriptors) up to which matches on the validation town (`sim world --seed 201`,
    /// 5 robots x 150 frames) keep precision 0.9: fitted from each descriptor's own
    /// precision-recall curve (`doorslam place eval VAL --int8` prints it; BENCHMARKS.md).
    /// The paper's 0.13-0.15 belongs to its NetVLAD-128, not to these.
    pub fn default_threshold(self) -> f32 {
        match self {
            Method::NetVlad => NETVLAD_THRESHOLD,
            Method::BagOfWords => BOW_THRESHOLD,
        }
    }

    /// The candidate chain for this descriptor: top-k below the match threshold, and the
    /// temporal confirmation (BENCHMARKS.md: fitted on the validation towns).
    pub fn default_chain(self) -> ChainConfig {
        ChainConfig {
            top_k: 3,
            max_distance: self.default_threshold(),
            window: 2,
            min_support: 1,
            max_gap: 3,
        }
    }
}

/// See [`Method::default_threshold`]: 0.7591 on the validation town for the trained head
/// (`netvlad-effnetlite0-triplet-128.onnx`, recall 0.593; rounded down). The untrained
/// head's was 0.6604 (recall 0.055).
pub const NETVLAD_THRESHOLD: f32 = 0.759;
/// See [`Method::default_threshold`]: 0.3676 on the validation town (recall 0.558;
/// rounded down, so precision stays 0.900 there).
pub const BOW_THRESHOLD: f32 = 0.367;

/// ORB features per image for the bag of words (the front-end's keyframe budget).
pub const BOW_FEATURES: i32 = 1000;

/// A global image descriptor.
#[derive(Debug)]
pub enum Describer {
    NetVlad(NetVlad),
    BagOfWords(Vocabulary),
}

/// What one keyframe gives a describer: its left image (NetVLAD needs it), its features
/// (the bag of words uses them when there are any, else ORB on the image).
#[derive(Debug, Clone, Copy)]
pub struct KeyframeInput<'a> {
    pub image: Option<&'a GrayImage>,
    pub features: &'a [Orb],
}

impl Describer {
    /// Loads the descriptor of `method` from its file and checks it has a wire form: a
    /// NetVLAD model with the contract (`model/README.md`), a vocabulary with its
    /// projection. Errors name the file and what was expected.
    pub fn open(
        method: Method,
        model: &Path,
        vocabulary: &Path,
        threads: usize,
    ) -> Result<Self, PlaceRecognitionError> {
        let describer = match method {
            Method::NetVlad => Describer::NetVlad(NetVlad::from_file(model, threads)?),
            Method::BagOfWords => Describer::BagOfWords(Vocabulary::from_file(vocabulary)?),
        };
        if let Describer::BagOfWords(v) = &describer {
            if v.projection.is_none() {
                return Err(PlaceRecognitionError::Vocabulary {
                    path: vocabulary.to_path_buf(),
                    reason: "a first-format file without the 128-D wire projection: rebuild it \
                             (deploy/setup, or `doorslam place vocabulary DIR... --out FILE`)"
                        .into(),
                });
            }
        }
        Ok(describer)
    }

    pub fn method(&self) -> Method {
        match self {
            Describer::NetVlad(_) => Method::NetVlad,
            Describer::BagOfWords(_) => Method::BagOfWords,
        }
    }

    /// Descriptor length.
    pub fn dim(&self) -> usize {
        match self {
            Describer::NetVlad(m) => m.dim(),
            Describer::BagOfWords(v) => v.words.len(),
        }
    }

    /// One L2-normalized descriptor per image (NetVLAD runs the batch at once).
    pub fn describe(
        &mut self,
        images: &[GrayImage],
    ) -> Result<Vec<Vec<f32>>, PlaceRecognitionError> {
        match self {
            Describer::NetVlad(m) => m.describe(images),
            Describer::BagOfWords(v) => images
                .iter()
                .map(|img| Ok(v.describe(&orb_descriptors(img, BOW_FEATURES)?)))
                .collect(),
        }
    }

    /// The 128-D wire form of a descriptor of [`Self::dim`] values.
    ///
    /// - NetVLAD: the first 128 values (the paper's cut of a PCA-ordered descriptor),
    ///   zero-padded when the model gives fewer, L2-normalized again;
    /// - bag of words: the vocabulary's PCA projection of the TF-IDF vector (norm ≤ 1, not
    ///   normalized again: distances stay those of the TF-IDF vectors within the kept
    ///   components, see [`crate::projection`]).
    pub fn to_wire(&self, v: &[f32]) -> Result<Vec<f32>, PlaceRecognitionError> {
        match self {
            Describer::NetVlad(_) => {
                let mut w = vec![0f32; DESCRIPTOR_DIM];
                let n = v.len().min(DESCRIPTOR_DIM);
                w[..n].copy_from_slice(&v[..n]);
                let norm = w.iter().map(|x| x * x).sum::<f32>().sqrt();
                if norm > 0.0 {
                    w.iter_mut().for_each(|x| *x /= norm);
                }
                Ok(w)
            }
            Describer::BagOfWords(voc) => voc.project(v).ok_or_else(|| {
                PlaceRecognitionError::NoWireForm(
                    "the vocabulary has no projection (a first-format file): rebuild it".into(),
                )
            }),
        }
    }

    /// Wire-form descriptors of a batch of keyframes (NetVLAD runs the images of the batch
    /// at once). A keyframe without what its method needs is an error naming its index.
    pub fn describe_wire(
        &mut self,
        inputs: &[KeyframeInput<'_>],
    ) -> Result<Vec<Vec<f32>>, PlaceRecognitionError> {
        let full = match self {
            Describer::NetVlad(m) => {
                let images = inputs
                    .iter()
                    .enumerate()
                    .map(|(i, k)| {
                        k.image.ok_or(PlaceRecognitionError::MissingInput {
                            index: i,
                            what: "image (NetVLAD describes images)",
                        })
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                m.describe_refs(&images)?
            }
            Describer::BagOfWords(v) => inputs
                .iter()
                .enumerate()
                .map(|(i, k)| match (k.features, k.image) {
                    (f, _) if !f.is_empty() => Ok(v.describe(f)),
                    (_, Some(img)) => Ok(v.describe(&orb_descriptors(img, BOW_FEATURES)?)),
                    _ => Err(PlaceRecognitionError::MissingInput {
                        index: i,
                        what: "features and no image (the bag of words needs ORB descriptors)",
                    }),
                })
                .collect::<Result<Vec<_>, _>>()?,
        };
        full.iter().map(|v| self.to_wire(v)).collect()
    }
}
