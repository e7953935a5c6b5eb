//! A robot's own loops (DOOR-SLAM's front-end closes them too): each new own descriptor
//! runs through the same candidate chain as a peer's, against the robot's older keyframes
//! (the index skips the `temporal_exclusion` most recent ones), and each confirmed pair is
//! verified with the same PnP on the two keyframes' full features. What passes goes to
//! the back-end as a loop closure of one robot (PCM among them there); counted apart from
//! the inter-robot ones ([`OwnLoopStats`] in `status.json`).

use std::collections::{BTreeMap, VecDeque};

use doorslam_dataset::StereoCalibration;
use doorslam_frontend::{verify, Rejection, VerifyConfig};
use doorslam_geometry::information::upper_from_matrix;
use doorslam_geometry::{key, pose_to_array, reverse_measurement};
use doorslam_ipc::wire::{Descriptor, Match};
use doorslam_place_recognition::{CandidateChain, ChainConfig, ChainStats, MatchIndex};
use serde::Serialize;

use crate::features::OwnFeatures;
use crate::store::OwnStore;

/// Pairs waiting for a keyframe's features (the descriptor came first), at most.
const MAX_WAITING: usize = 1024;

/// Counters of the robot's own loops.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct OwnLoopStats {
    pub chain: ChainStats,
    pub verified: u64,
    pub rejected: BTreeMap<String, u64>,
    /// Closures handed to the back-end.
    pub closures: u64,
    /// Pairs whose keyframe features had not arrived yet.
    pub waiting: u64,
}

/// The chain over own descriptors and the pairs waiting for features.
#[derive(Debug, Clone)]
pub struct OwnLoops {
    chain: CandidateChain,
    waiting: VecDeque<Match>,
    stats: OwnLoopStats,
}

/// What a pair's verification needs: both keyframes' features (in memory or read back
/// from the store), the camera, the settings.
pub struct VerifyInputs<'a> {
    pub robot: u8,
    pub calib: &'a StereoCalibration,
    pub features: &'a mut OwnFeatures,
    pub store: Option<&'a OwnStore>,
    pub config: &'a VerifyConfig,
}

impl OwnLoops {
    pub fn new(config: ChainConfig) -> Self {
        Self {
            chain: CandidateChain::new(config),
            waiting: VecDeque::new(),
            stats: OwnLoopStats::default(),
        }
    }

    pub fn stats(&self) -> OwnLoopStats {
        let mut s = self.stats.clone();
        s.chain = self.chain.stats().clone();
        s.waiting = self.waiting.len() as u64;
        s
    }

    /// A new own descriptor, ranked against the older keyframes of `index` (call before
    /// inserting it); returns the closures verified now (this descriptor's pairs and
    /// earlier ones it confirmed, or whose features arrived since).
    pub fn on_descriptor(
        &mut self,
        index: &MatchIndex,
        d: &Descriptor,
        inputs: &mut VerifyInputs<'_>,
    ) -> Vec<doorslam_ipc::LoopClosure> {
        let confirmed = self.chain.push(index, std::slice::from_ref(d));
        self.waiting.extend(confirmed);
        while self.waiting.len() > MAX_WAITING {
            self.waiting.pop_front();
        }
        self.retry(inputs)
    }

    /// Verifies every waiting pair whose two keyframes have features now.
    pub fn retry(&mut self, inputs: &mut VerifyInputs<'_>) -> Vec<doorslam_ipc::LoopClosure> {
        let mut out = Vec::new();
        let mut still = VecDeque::new();
        let sigma = inputs.config.disparity_sigma_px;
        for m in std::mem::take(&mut self.waiting) {
            let (q, c) = (key::index(m.query), key::index(m.candidate));
            // Both there before either is read back from the store: a pair still waiting
            // for one keyframe costs no read per retry.
            if !(inputs.features.contains(q) && inputs.features.contains(c)) {
                still.push_back(m);
                continue;
            }
            let local = inputs.features.get(q, inputs.store, sigma);
            let remote = inputs.features.get(c, inputs.store, sigma);
            let (Some(local), Some(remote)) = (local, remote) else {
                // Known but unreadable (a failed read, counted): the pair is dropped.
                self.stats
                    .rejected
                    .entry("features_unreadable".into())
                    .and_modify(|n| *n += 1)
                    .or_insert(1);
                continue;
            };
            match verify(inputs.calib, &local, inputs.calib, &remote, inputs.config) {
                Ok(v) => {
                    self.stats.verified += 1;
                    // Verification gives the query's camera in the candidate's frame; the
                    // closure goes from the query keyframe to the candidate.
                    let (z, information) = reverse_measurement(&v.relative, &v.information);
                    tracing::info!(
                        pair = %format!("{} - {}", key::label(m.query), key::label(m.candidate)),
                        inliers = v.inliers,
                        "own loop: verified"
                    );
                    out.push(doorslam_ipc::LoopClosure {
                        robot_a: u32::from(inputs.robot),
                        robot_b: u32::from(inputs.robot),
                        keyframe_a: q,
                        keyframe_b: c,
                        relative: pose_to_array(&z),
                        information: upper_from_matrix(&information),
                        inliers: v.inliers as u32,
                        reserved: 0,
                    });
                }
                Err(r) => self.reject(&r),
            }
        }
        self.waiting = still;
        self.stats.closures += out.len() as u64;
        out
    }

    fn reject(&mut self, r: &Rejection) {
        *self.stats.rejected.entry(r.name().into()).or_default() += 1;
    }
}
