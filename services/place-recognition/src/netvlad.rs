//! A whole-image descriptor network in onnxruntime (NetVLAD on EfficientNet-Lite0 as built
//! by `model/build_model.py`, or any ONNX with the same contract, see `model/README.md`):
//! input `[batch, 1 or 3, H, W]` float (ImageNet-normalized), output `[batch, D]`.

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::Tensor;

use crate::image::{to_tensor, GrayImage};
use crate::model::{runtime, PlaceRecognitionError};

/// File name of the default model inside `$DOORSLAM_HOME/models/`.
pub const DEFAULT_MODEL_FILE: &str = "netvlad-effnetlite0-triplet-128.onnx";
/// Environment variable naming the model file (written into the env file by deploy/setup).
pub const MODEL_ENV: &str = "DOORSLAM_PLACE_MODEL";
/// Input size used when the model leaves height and width dynamic (the EuRoC aspect).
pub const DYNAMIC_INPUT_SIZE: (usize, usize) = (320, 208);

/// `$DOORSLAM_HOME/models` (deploy/setup's default home: `~/.cache/doorslam`).
pub fn models_dir() -> PathBuf {
    let home = std::env::var_os("DOORSLAM_HOME")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/doorslam")
        });
    home.join("models")
}

/// Where the model is: `$DOORSLAM_PLACE_MODEL`, else `$DOORSLAM_HOME/models/…`.
pub fn default_model_path() -> PathBuf {
    match std::env::var_os(MODEL_ENV) {
        Some(p) => PathBuf::from(p),
        None => models_dir().join(DEFAULT_MODEL_FILE),
    }
}

/// The NetVLAD descriptor network.
pub struct NetVlad {
    session: Session,
    name: String,
    channels: usize,
    width: usize,
    height: usize,
    dim: usize,
    training_towns: Vec<u64>,
}

/// ONNX metadata key naming the `sim world` seeds a model was trained on (comma
/// separated), written by `model/build_model.py`.
pub const TRAINING_TOWNS_KEY: &str = "doorslam.training_towns";

impl std::fmt::Debug for NetVlad {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "NetVlad({}: [batch, {}, {}, {}] -> [batch, {}])",
            self.name, self.channels, self.height, self.width, self.dim
        )
    }
}

/// The contract, as it appears in error messages.
const CONTRACT: &str = "input [batch, 1 or 3, H, W] float, output [batch, D] float";

impl NetVlad {
    /// Loads a model file, checks its signature against the contract, and runs inference
    /// on `threads` intra-op threads (1 = the one-core figure of BENCHMARKS.md).
    pub fn from_file(path: &Path, threads: usize) -> Result<Self, PlaceRecognitionError> {
        let name = path.display().to_string();
        if !path.is_file() {
            return Err(PlaceRecognitionError::ModelMissing {
                path: path.to_path_buf(),
            });
        }
        let load = |reason: String| PlaceRecognitionError::Load {
            model: name.clone(),
            reason,
        };
        let session = Session::builder(runtime()?)
            .map_err(|e| load(e.to_string()))?
            .with_intra_threads(threads.max(1))
            .map_err(|e| load(e.to_string()))?
            .commit_from_file(path)
            .map_err(|e| load(format!("{e} (expected an ONNX model: {CONTRACT})")))?;
        Self::from_session(session, name)
    }

    fn from_session(session: Session, name: String) -> Result<Self, PlaceRecognitionError> {
        let bad = |reason: String| PlaceRecognitionError::Signature {
            model: name.clone(),
            reason: format!("{reason}; expected {CONTRACT}"),
        };
        let (inputs, outputs) = (session.inputs(), session.outputs());
        if inputs.len() != 1 || outputs.len() != 1 {
            return Err(bad(format!(
                "{} inputs and {} outputs",
                inputs.len(),
                outputs.len()
            )));
        }
        let shape = |outlet: &ort::value::Outlet| -> Result<Vec<i64>, PlaceRecognitionError> {
            outlet
                .dtype()
                .tensor_shape()
                .map(|s| s.to_vec())
                .ok_or_else(|| bad(format!("{} is not a tensor", outlet.name())))
        };
        let (input, output) = (shape(&inputs[0])?, shape(&outputs[0])?);
        let (channels, height, width) = match input[..] {
            [_, c @ (1 | 3), h, w] => {
                let (dw, dh) = DYNAMIC_INPUT_SIZE;
                let fixed = |d: i64, default: usize| if d > 0 { d as usize } else { default };
                (c as usize, fixed(h, dh), fixed(w, dw))
            }
            _ => {
                return Err(bad(format!(
                    "input {} has shape {input:?}",
                    inputs[0].name()
                )))
            }
        };
        let dim = match output[..] {
            [_, d] if d > 0 => d as usize,
            _ => {
                return Err(bad(format!(
                    "output {} has shape {output:?}",
                    outputs[0].name()
                )))
            }
        };
        let custom = session
            .metadata()
            .ok()
            .and_then(|m| m.custom(TRAINING_TOWNS_KEY));
        let training_towns = match custom {
            None => Vec::new(),
            Some(v) => v
                .split(',')
                .filter(|s| !s.trim().is_empty())
                .map(|s| s.trim().parse::<u64>())
                .collect::<Result<_, _>>()
                .map_err(|_| {
                    bad(format!(
                        "metadata {TRAINING_TOWNS_KEY} = {v:?} is not a list of seeds"
                    ))
                })?,
        };
        Ok(Self {
            session,
            name,
            channels,
            width,
            height,
            dim,
            training_towns,
        })
    }

    /// The `sim world` seeds of the towns the model was trained on (from its metadata;
    /// empty when it names none).
    pub fn training_towns(&self) -> &[u64] {
        &self.training_towns
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Model input size (width, height).
    pub fn input_size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Descriptors of a batch of images, one vector of `dim()` values each.
    pub fn describe(
        &mut self,
        images: &[GrayImage],
    ) -> Result<Vec<Vec<f32>>, PlaceRecognitionError> {
        self.describe_refs(&images.iter().collect::<Vec<_>>())
    }

    /// [`Self::describe`] of borrowed images (no copy of a batch the caller holds).
    pub fn describe_refs(
        &mut self,
        images: &[&GrayImage],
    ) -> Result<Vec<Vec<f32>>, PlaceRecognitionError> {
        if images.is_empty() {
            return Ok(Vec::new());
        }
        let (c, h, w) = (self.channels, self.height, self.width);
        let input: Vec<f32> = images
            .iter()
            .flat_map(|img| to_tensor(img, c, w, h))
            .collect();
        let model = self.name.clone();
        let run = |e: ort::Error| PlaceRecognitionError::Run {
            model: model.clone(),
            reason: e.to_string(),
        };
        let tensor = Tensor::from_array(([images.len(), c, h, w], input)).map_err(run)?;
        let outputs = self.session.run(ort::inputs![tensor]).map_err(run)?;
        let (shape, values) = outputs[0].try_extract_tensor::<f32>().map_err(run)?;
        let expected = [images.len() as i64, self.dim as i64];
        if shape[..] != expected {
            return Err(PlaceRecognitionError::Run {
                model: self.name.clone(),
                reason: format!("output shape {shape:?}, expected {expected:?}"),
            });
        }
        if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
            return Err(PlaceRecognitionError::Run {
                model: self.name.clone(),
                reason: format!("non-finite descriptor value {bad}"),
            });
        }
        Ok(values.chunks(self.dim).map(<[f32]>::to_vec).collect())
    }
}
