//! One matching interface over the two global descriptors: the NetVLAD network and the
//! bag-of-words baseline. Both give L2-normalized vectors compared by Euclidean distance.

use crate::bow::{orb_descriptors, Vocabulary};
use crate::image::GrayImage;
use crate::model::PlaceRecognitionError;
use crate::netvlad::NetVlad;

/// Which descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    NetVlad,
    BagOfWords,
}

impl Method {
    /// The name on the command line and in JSON output.
    pub fn name(self) -> &'static str {
        match self {
            Method::NetVlad => "netvlad",
            Method::BagOfWords => "bow",
        }
    }
}

/// ORB features per image for the bag of words (the front-end's keyframe budget).
pub const BOW_FEATURES: i32 = 1000;

/// A global image descriptor.
#[derive(Debug)]
pub enum Describer {
    NetVlad(NetVlad),
    BagOfWords(Vocabulary),
}

impl Describer {
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
}
