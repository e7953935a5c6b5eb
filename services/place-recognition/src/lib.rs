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
//! - [`eval`]: precision-recall of inter-robot matches against ground truth;
//! - [`onnx`]: a small writer of ONNX files (tests build models without downloads);
//!   [`model`]: a `[batch, d] -> [batch, d']` model and the onnxruntime environment.

pub mod bow;
pub mod describer;
pub mod eval;
pub mod image;
pub mod matching;
pub mod model;
pub mod netvlad;
pub mod onnx;

pub use describer::{Describer, Method};
pub use image::GrayImage;
pub use model::{DescriptorModel, PlaceRecognitionError};
pub use netvlad::NetVlad;
