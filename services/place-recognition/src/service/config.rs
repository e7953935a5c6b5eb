//! `[place]` of `robot.toml`: which descriptor, its files, matching and batching.

use std::path::PathBuf;

use serde::Deserialize;

use crate::bow::default_vocabulary_path;
use crate::candidates::ChainConfig;
use crate::describer::Method;
use crate::netvlad::default_model_path;

/// Where the bag of words takes a keyframe's ORB descriptors from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BowFeatures {
    /// ORB's own detector (oriented, 8 levels) on the keyframe's image: what the
    /// vocabulary trains on, and the default: with the front-end's features recall@1 on
    /// the held-out towns falls from 0.712 to 0.490 (BENCHMARKS.md).
    #[default]
    Image,
    /// The keyframe's own features (the front-end's GFTT + upright ORB with a stereo
    /// match: no ORB run, no image needed); ORB on the image for a keyframe without any.
    Keyframe,
}

/// `[place]`. Unknown keys are errors: a typo must not be ignored.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaceSection {
    /// `bow` (the default: it wins on the held-out towns, BENCHMARKS.md) or `netvlad`.
    #[serde(default = "default_method")]
    pub method: Method,
    /// NetVLAD ONNX model (contract: `services/place-recognition/model/README.md`; any
    /// model with it drops in). Default `$DOORSLAM_PLACE_MODEL`, else
    /// `$DOORSLAM_HOME/models/netvlad-effnetlite0-triplet-128.onnx`.
    #[serde(default)]
    pub model: Option<PathBuf>,
    /// Bag-of-words vocabulary with its wire projection. Default
    /// `$DOORSLAM_BOW_VOCABULARY`, else `$DOORSLAM_HOME/models/bow-orb-1024-w128.voc`.
    #[serde(default)]
    pub vocabulary: Option<PathBuf>,
    /// Largest Euclidean distance of a match on the int8 wire form; default: the method's
    /// fitted value ([`Method::default_threshold`]).
    #[serde(default)]
    pub match_threshold: Option<f32>,
    /// onnxruntime intra-op threads of the inference thread.
    #[serde(default = "default_threads")]
    pub threads: usize,
    /// Most keyframes described in one inference call when they queue up.
    #[serde(default = "default_batch_size")]
    pub batch_size: usize,
    /// Left images of recent frames kept for the keyframes that refer to them.
    #[serde(default = "default_frame_cache")]
    pub frame_cache: usize,
    /// Intra-robot matching: own keyframes within this many ids are not candidates.
    #[serde(default = "default_temporal_exclusion")]
    pub temporal_exclusion: u64,
    /// Bag of words only: `image` (ORB on the keyframe's image) or `keyframe` (its
    /// features).
    #[serde(default)]
    pub bow_features: BowFeatures,
    /// The candidate chain the team link runs on received descriptors (and on the robot's
    /// own, for its own loops): candidates per query, and the temporal confirmation
    /// (`temporal_window` keyframes on each side, `min_support` of them agreeing within
    /// `max_gap` keyframes; 0: no check). Defaults: the method's, [`Method::default_chain`].
    #[serde(default)]
    pub top_k: Option<usize>,
    #[serde(default)]
    pub temporal_window: Option<u64>,
    #[serde(default)]
    pub min_support: Option<usize>,
    #[serde(default)]
    pub max_gap: Option<u64>,
    /// Close the robot's own loops: its new keyframes against its older ones (beyond
    /// `temporal_exclusion`), through the same chain and PnP, PCM in the back-end.
    #[serde(default = "default_true")]
    pub own_loops: bool,
}

fn default_true() -> bool {
    true
}

fn default_method() -> Method {
    Method::BagOfWords
}
fn default_threads() -> usize {
    1
}
fn default_batch_size() -> usize {
    8
}
fn default_frame_cache() -> usize {
    16
}
fn default_temporal_exclusion() -> u64 {
    10
}

impl Default for PlaceSection {
    fn default() -> Self {
        Self {
            method: default_method(),
            model: None,
            vocabulary: None,
            match_threshold: None,
            threads: default_threads(),
            batch_size: default_batch_size(),
            frame_cache: default_frame_cache(),
            temporal_exclusion: default_temporal_exclusion(),
            bow_features: BowFeatures::default(),
            top_k: None,
            temporal_window: None,
            min_support: None,
            max_gap: None,
            own_loops: true,
        }
    }
}

/// A `[place]` value out of range, named by its key.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("place.{key} = {value}: {expected}")]
pub struct PlaceConfigError {
    pub key: &'static str,
    pub value: String,
    pub expected: &'static str,
}

impl PlaceSection {
    pub fn validate(&self) -> Result<(), PlaceConfigError> {
        let bad = |key, value: String, expected| {
            Err(PlaceConfigError {
                key,
                value,
                expected,
            })
        };
        if let Some(t) = self.match_threshold {
            if !(t.is_finite() && t > 0.0 && t <= 2.0) {
                return bad(
                    "match_threshold",
                    t.to_string(),
                    "a distance of unit vectors, in (0, 2]",
                );
            }
        }
        if !(1..=64).contains(&self.threads) {
            return bad("threads", self.threads.to_string(), "1 to 64");
        }
        if !(1..=64).contains(&self.batch_size) {
            return bad("batch_size", self.batch_size.to_string(), "1 to 64");
        }
        if !(1..=256).contains(&self.frame_cache) {
            return bad(
                "frame_cache",
                self.frame_cache.to_string(),
                "1 to 256 frames",
            );
        }
        let chain = self.chain();
        if !(1..=64).contains(&chain.top_k) {
            return bad("top_k", chain.top_k.to_string(), "1 to 64 candidates");
        }
        if chain.min_support as u64 > 2 * chain.window {
            return bad(
                "min_support",
                chain.min_support.to_string(),
                "at most the 2 x temporal_window neighbours a query has",
            );
        }
        Ok(())
    }

    /// The candidate chain: the method's defaults with this section's values.
    pub fn chain(&self) -> ChainConfig {
        let mut c = self.method.default_chain();
        if let Some(t) = self.match_threshold {
            c.max_distance = t;
        }
        c.top_k = self.top_k.unwrap_or(c.top_k);
        c.window = self.temporal_window.unwrap_or(c.window);
        c.min_support = self.min_support.unwrap_or(c.min_support);
        c.max_gap = self.max_gap.unwrap_or(c.max_gap);
        c
    }

    /// The settings of the place-recognition service of robot `robot` (index
    /// `robot_index`), default paths resolved from the environment now.
    pub fn for_robot(&self, robot: &str, robot_index: u32) -> PlaceConfig {
        PlaceConfig {
            robot: robot.to_string(),
            robot_index,
            method: self.method,
            model: self.model.clone().unwrap_or_else(default_model_path),
            vocabulary: self
                .vocabulary
                .clone()
                .unwrap_or_else(default_vocabulary_path),
            match_threshold: self
                .match_threshold
                .unwrap_or(self.method.default_threshold()),
            threads: self.threads,
            batch_size: self.batch_size,
            frame_cache: self.frame_cache,
            temporal_exclusion: self.temporal_exclusion,
            bow_features: self.bow_features,
        }
    }
}

/// Settings of one place-recognition process.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaceConfig {
    /// Robot id (service names) and index (keyframe samples carry it).
    pub robot: String,
    pub robot_index: u32,
    pub method: Method,
    pub model: PathBuf,
    pub vocabulary: PathBuf,
    pub match_threshold: f32,
    pub threads: usize,
    pub batch_size: usize,
    pub frame_cache: usize,
    pub temporal_exclusion: u64,
    pub bow_features: BowFeatures,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_out_of_range_values_named_by_key() {
        let s = PlaceSection::default();
        s.validate().unwrap();
        let c = s.for_robot("a", 0);
        assert_eq!(c.method, Method::BagOfWords);
        assert_eq!(c.match_threshold, Method::BagOfWords.default_threshold());
        for (section, key) in [
            (
                PlaceSection {
                    match_threshold: Some(f32::NAN),
                    ..Default::default()
                },
                "place.match_threshold",
            ),
            (
                PlaceSection {
                    batch_size: 0,
                    ..Default::default()
                },
                "place.batch_size",
            ),
            (
                PlaceSection {
                    threads: 0,
                    ..Default::default()
                },
                "place.threads",
            ),
            (
                PlaceSection {
                    frame_cache: 0,
                    ..Default::default()
                },
                "place.frame_cache",
            ),
            (
                PlaceSection {
                    top_k: Some(0),
                    ..Default::default()
                },
                "place.top_k",
            ),
            (
                PlaceSection {
                    temporal_window: Some(1),
                    min_support: Some(3),
                    ..Default::default()
                },
                "place.min_support",
            ),
        ] {
            let err = section.validate().unwrap_err().to_string();
            assert!(err.starts_with(key), "{err}");
        }
    }
}
