//! # doorslam-place-recognition
//!
//! Global place descriptors (paper §III-B): a keyframe's image becomes one L2-normalized
//! vector that robots exchange at rendezvous and compare by Euclidean distance.
//!
//! - [`netvlad`]: the NetVLAD network (EfficientNet-Lite0 backbone cut mid-way, NetVLAD
//!   head, PCA-whitening to 128-D) in onnxruntime, built by `model/build_model.py`;
//! - [`bow`]: the bag-of-words baseline over the front-end's ORB features (vocabulary by
//!   k-majority, TF-IDF);
//! - [`describer`]: both behind one interface; [`image`]: preprocessing;
//! - [`matching`]: distances, also on the int8 wire form with integer dot products;
//! - [`index`]: one robot's keyframes on the int8 form, matched against received ones;
//! - [`candidates`]: the candidate chain (top-k, distance bound, temporal confirmation);
//! - [`projection`]: PCA to the 128-D wire form (the bag of words' wire form);
//! - [`service`]: the `place-recognition` service (keyframes in, descriptors out);
//! - [`eval`]: precision-recall of inter-robot matches against ground truth (the whole
//!   chain with PnP verification, `place eval --verify`, is `doorslam-rendezvous`'s
//!   `chain_eval`: it needs the front-end's verifier);
//! - [`onnx`]: a small writer of ONNX files (tests build models without downloads);
//!   [`model`]: a `[batch, d] -> [batch, d']` model and the onnxruntime environment.

pub mod bow;
pub mod candidates;
pub mod describer;
pub mod eval;
pub mod image;
pub mod index;
pub mod matching;
pub mod model;
pub mod netvlad;
pub mod onnx;
pub mod projection;
pub mod service;

pub use candidates::{CandidateChain, ChainConfig, ChainStats};
pub use describer::{Describer, KeyframeInput, Method};
pub use image::GrayImage;
pub use index::{IndexError, MatchIndex};
pub use model::{DescriptorModel, PlaceRecognitionError};
pub use netvlad::NetVlad;
