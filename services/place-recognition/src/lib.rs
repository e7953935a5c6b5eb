//! # doorslam-place-recognition
//!
//! Global place descriptors: an image (or its pooled features) goes through an ONNX model
//! run by onnxruntime (`ort`), and the output is an L2-normalized vector that robots
//! exchange at rendezvous and compare by Euclidean distance (paper §III-B).
//!
//! Landed so far:
//! - [`onnx`]: a small writer of ONNX model files, used to generate the projection head of
//!   the descriptor (`y = normalize(x·W + b)`, NetVLAD's PCA-whitening + L2 step) so tests
//!   need no downloaded weights;
//! - [`model`]: loading an ONNX model with onnxruntime and running it on a batch.

pub mod model;
pub mod onnx;

pub use model::{DescriptorModel, PlaceRecognitionError};
