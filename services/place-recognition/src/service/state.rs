//! The service's decisions as a plain struct fed by values (tested without iceoryx2): the
//! cache of recent left images, which keyframe becomes a job for the inference thread and
//! with what input, and what is skipped (counted, and logged by the loop).
//!
//! Why a cache of frames: a `Keyframe` sample carries features and pose but not its image,
//! and NetVLAD describes images. Frames are lossy and 2 deep, so the loop drains them
//! promptly into this cache, keyed by frame sequence; a keyframe takes its image by
//! `frame_seq`. The cache keeps the left image as sent (one memcpy per frame, no
//! per-frame resampling: only keyframes pay for preprocessing, on the inference thread).

use std::collections::{BTreeSet, VecDeque};
use std::sync::Arc;

use doorslam_ipc::{FrameHeader, Keyframe, MAX_KEYFRAME_FEATURES};

use super::config::BowFeatures;
use crate::bow::Orb;
use crate::describer::Method;
use crate::image::GrayImage;

/// Keyframe ids remembered to recognise repeats (publisher history handed again).
const REMEMBERED_IDS: usize = 4096;

/// Recent left images by frame sequence, oldest evicted first.
#[derive(Debug)]
pub struct FrameCache {
    capacity: usize,
    frames: VecDeque<(u64, Arc<GrayImage>)>,
}

impl FrameCache {
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            frames: VecDeque::with_capacity(capacity.max(1)),
        }
    }

    /// Adds frame `seq`; a sequence that goes back (the camera restarted) empties the
    /// cache first: the old numbers name other images now.
    pub fn insert(&mut self, seq: u64, image: GrayImage) {
        if self.frames.back().is_some_and(|(s, _)| *s >= seq) {
            self.frames.clear();
        }
        if self.frames.len() == self.capacity {
            self.frames.pop_front();
        }
        self.frames.push_back((seq, Arc::new(image)));
    }

    /// The image of frame `seq`, if still cached.
    pub fn get(&self, seq: u64) -> Option<Arc<GrayImage>> {
        let i = self.frames.binary_search_by_key(&seq, |(s, _)| *s).ok()?;
        Some(self.frames[i].1.clone())
    }

    /// Oldest and newest cached sequence.
    pub fn span(&self) -> Option<(u64, u64)> {
        Some((self.frames.front()?.0, self.frames.back()?.0))
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

/// One keyframe for the inference thread.
#[derive(Debug, Clone)]
pub struct Job {
    pub keyframe: u64,
    /// Its left image (NetVLAD; the bag of words when it has no features to use).
    pub image: Option<Arc<GrayImage>>,
    /// Its ORB descriptors (bag of words with `bow_features = "keyframe"`).
    pub features: Vec<Orb>,
}

/// Why a keyframe gets no descriptor.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Skip {
    #[error("keyframe {id}: its frame {frame_seq} is no longer cached (cached: {cached}); frames are lossy: the service fell behind, or frame_cache is too small")]
    FrameNotCached {
        id: u64,
        frame_seq: u64,
        cached: String,
    },
    #[error("keyframe {id} is from robot {got}, this service is robot {want}'s")]
    WrongRobot { id: u64, got: u32, want: u32 },
    #[error("keyframe {id}: n_features {n} exceeds {MAX_KEYFRAME_FEATURES}")]
    TooManyFeatures { id: u64, n: u32 },
    #[error("keyframe {id} was already described (history handed again)")]
    Duplicate { id: u64 },
}

/// Counters, logged at exit and readable by tests.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PlaceReport {
    pub frames: u64,
    /// Frames lost before they reached the cache (gaps in sequence numbers).
    pub dropped_frames: u64,
    pub keyframes: u64,
    /// Keyframes whose frame was no longer cached (no descriptor).
    pub frame_not_cached: u64,
    pub wrong_robot: u64,
    pub invalid: u64,
    pub duplicates: u64,
    /// Descriptors published.
    pub described: u64,
    /// Inference calls, and the largest batch one of them described.
    pub batches: u64,
    pub largest_batch: u64,
}

/// The service's state.
#[derive(Debug)]
pub struct PlaceState {
    robot_index: u32,
    method: Method,
    bow_features: BowFeatures,
    cache: FrameCache,
    last_frame: Option<u64>,
    seen: BTreeSet<u64>,
    report: PlaceReport,
}

impl PlaceState {
    pub fn new(
        robot_index: u32,
        method: Method,
        bow_features: BowFeatures,
        frame_cache: usize,
    ) -> Self {
        Self {
            robot_index,
            method,
            bow_features,
            cache: FrameCache::new(frame_cache),
            last_frame: None,
            seen: BTreeSet::new(),
            report: PlaceReport::default(),
        }
    }

    pub fn report(&self) -> &PlaceReport {
        &self.report
    }

    pub fn cache(&self) -> &FrameCache {
        &self.cache
    }

    /// A keyframe needs its image unless the bag of words can use its features.
    fn needs_image(&self, kf: &Keyframe) -> bool {
        match self.method {
            Method::NetVlad => true,
            Method::BagOfWords => self.bow_features == BowFeatures::Image || kf.n_features == 0,
        }
    }

    /// A frame arrived: its left image into the cache (`left`: `width * height` bytes).
    pub fn on_frame(&mut self, header: &FrameHeader, left: &[u8]) {
        self.report.frames += 1;
        if let Some(prev) = self.last_frame {
            self.report.dropped_frames += header.seq.saturating_sub(prev + 1);
        }
        self.last_frame = Some(header.seq);
        if let Some(image) =
            GrayImage::new(header.width as usize, header.height as usize, left.to_vec())
        {
            self.cache.insert(header.seq, image);
        }
    }

    /// A keyframe arrived: the job for the inference thread, or why there is none.
    pub fn on_keyframe(&mut self, kf: &Keyframe) -> Result<Job, Skip> {
        self.report.keyframes += 1;
        let skip = |report: &mut PlaceReport, s: Skip| {
            match s {
                Skip::FrameNotCached { .. } => report.frame_not_cached += 1,
                Skip::WrongRobot { .. } => report.wrong_robot += 1,
                Skip::TooManyFeatures { .. } => report.invalid += 1,
                Skip::Duplicate { .. } => report.duplicates += 1,
            }
            Err(s)
        };
        if kf.robot != self.robot_index {
            let s = Skip::WrongRobot {
                id: kf.id,
                got: kf.robot,
                want: self.robot_index,
            };
            return skip(&mut self.report, s);
        }
        let n = kf.n_features as usize;
        if n > MAX_KEYFRAME_FEATURES {
            let s = Skip::TooManyFeatures {
                id: kf.id,
                n: kf.n_features,
            };
            return skip(&mut self.report, s);
        }
        if self.seen.contains(&kf.id) {
            return skip(&mut self.report, Skip::Duplicate { id: kf.id });
        }
        let image = if self.needs_image(kf) {
            match self.cache.get(kf.frame_seq) {
                Some(image) => Some(image),
                None => {
                    let cached = match self.cache.span() {
                        Some((a, b)) => format!("{a}..={b}"),
                        None => "none".into(),
                    };
                    let s = Skip::FrameNotCached {
                        id: kf.id,
                        frame_seq: kf.frame_seq,
                        cached,
                    };
                    return skip(&mut self.report, s);
                }
            }
        } else {
            None
        };
        let features = if self.method == Method::BagOfWords && image.is_none() {
            kf.features[..n].iter().map(|f| f.descriptor).collect()
        } else {
            Vec::new()
        };
        self.seen.insert(kf.id);
        if self.seen.len() > REMEMBERED_IDS {
            self.seen.pop_first();
        }
        Ok(Job {
            keyframe: kf.id,
            image,
            features,
        })
    }

    /// The inference thread described a batch of `n` keyframes.
    pub fn on_described(&mut self, n: usize) {
        self.report.batches += 1;
        self.report.described += n as u64;
        self.report.largest_batch = self.report.largest_batch.max(n as u64);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use doorslam_ipc::{Feature, KeyframeSource};

    fn header(seq: u64) -> FrameHeader {
        FrameHeader {
            seq,
            width: 4,
            height: 2,
            ..Default::default()
        }
    }

    fn keyframe(id: u64, frame_seq: u64, n_features: u32) -> Box<Keyframe> {
        let mut features = [Feature::default(); MAX_KEYFRAME_FEATURES];
        for (i, f) in features.iter_mut().enumerate().take(n_features as usize) {
            f.descriptor = [i as u8; 32];
        }
        Box::new(Keyframe {
            robot: 0,
            source: KeyframeSource::VisualOdometry as u32,
            id,
            frame_seq,
            stamp_ns: 0,
            pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            n_features,
            reserved: 0,
            features,
        })
    }

    #[test]
    fn keyframes_take_their_frame_from_the_cache_and_old_frames_are_counted() {
        let mut s = PlaceState::new(0, Method::NetVlad, BowFeatures::Keyframe, 3);
        for seq in [0, 1, 2, 4, 5] {
            s.on_frame(&header(seq), &[seq as u8; 8]);
        }
        assert_eq!(s.report().dropped_frames, 1); // 3 never arrived
        assert_eq!(s.cache().span(), Some((2, 5)));
        let job = s.on_keyframe(&keyframe(0, 4, 0)).unwrap();
        assert_eq!(job.image.unwrap().pixels, vec![4; 8]);
        assert!(job.features.is_empty());
        // Frame 1 was evicted (cache of 3): no descriptor, counted, and the error says why.
        let err = s.on_keyframe(&keyframe(1, 1, 0)).unwrap_err();
        assert!(err.to_string().contains("2..=5"), "{err}");
        assert_eq!(s.report().frame_not_cached, 1);
        // Asked again (history handed to a restarted consumer): a duplicate.
        assert_eq!(
            s.on_keyframe(&keyframe(0, 4, 0)).unwrap_err(),
            Skip::Duplicate { id: 0 }
        );
        // Another robot's keyframe, impossible feature counts.
        let mut other = keyframe(7, 5, 0);
        other.robot = 3;
        assert!(matches!(
            s.on_keyframe(&other),
            Err(Skip::WrongRobot {
                got: 3,
                want: 0,
                ..
            })
        ));
        assert!(matches!(
            s.on_keyframe(&keyframe(8, 5, MAX_KEYFRAME_FEATURES as u32 + 1)),
            Err(Skip::TooManyFeatures { .. })
        ));
        let r = s.report();
        assert_eq!(
            (r.keyframes, r.duplicates, r.wrong_robot, r.invalid),
            (5, 1, 1, 1)
        );
    }

    #[test]
    fn a_camera_restart_empties_the_cache() {
        let mut s = PlaceState::new(0, Method::NetVlad, BowFeatures::Keyframe, 4);
        s.on_frame(&header(10), &[1; 8]);
        s.on_frame(&header(11), &[2; 8]);
        s.on_frame(&header(0), &[3; 8]);
        assert_eq!(s.cache().span(), Some((0, 0)));
        assert_eq!(s.cache().get(0).unwrap().pixels, vec![3; 8]);
    }

    #[test]
    fn the_bag_of_words_uses_keyframe_features_or_the_image() {
        let mut s = PlaceState::new(0, Method::BagOfWords, BowFeatures::Keyframe, 4);
        // Features and no cached frame: described from the features.
        let job = s.on_keyframe(&keyframe(0, 9, 3)).unwrap();
        assert!(job.image.is_none());
        assert_eq!(job.features, vec![[0; 32], [1; 32], [2; 32]]);
        // No features (sim-keyframes): ORB on the cached image.
        s.on_frame(&header(12), &[5; 8]);
        let job = s.on_keyframe(&keyframe(1, 12, 0)).unwrap();
        assert!(job.image.is_some() && job.features.is_empty());
        assert!(s.on_keyframe(&keyframe(2, 13, 0)).is_err());
        // bow_features = "image": always the image.
        let mut s = PlaceState::new(0, Method::BagOfWords, BowFeatures::Image, 4);
        s.on_frame(&header(1), &[5; 8]);
        let job = s.on_keyframe(&keyframe(0, 1, 3)).unwrap();
        assert!(job.image.is_some() && job.features.is_empty());
    }
}
