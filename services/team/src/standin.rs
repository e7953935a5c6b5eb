//! Stand-ins for the pieces the protocol calls into, so the team link runs (and is tested)
//! before place recognition, the front-end's verification and the distributed back-end
//! are plugged in. Simulation only: never on a flying robot.
//!
//! [`SimWorld`] gives every keyframe of every robot a place, deterministically from a seed;
//! a keyframe's descriptor is its place's appearance plus a little noise, and every
//! `alias_every`-th place looks like its neighbour (perceptual aliasing), so matching finds
//! true pairs and aliased ones, and [`TruthVerifier`] accepts exactly the true ones.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use doorslam_geometry::{key, SE3};
use doorslam_ipc::wire::{
    Body, CompactPose, Descriptor, Estimate, Header, Information, LoopClosure, Match, Pose,
    PoseEstimate, PoseEstimates, RobotId, Stage, VerificationCamera, VerificationFeature,
    VerificationFeatures, DESCRIPTOR_DIM,
};

use crate::protocol::{
    BackendExchange, BackendRefusal, DescriptorBatch, DescriptorSource, Verifier,
};

/// SplitMix64: a deterministic hash of the seed and indices (no RNG state to share).
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

fn unit(h: u64) -> f32 {
    // [-1, 1)
    (h >> 40) as f32 / (1u64 << 23) as f32 - 1.0
}

/// The simulated world every robot of a test agrees on (same seed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimWorld {
    pub seed: u64,
    /// Number of distinct places keyframes fall in.
    pub places: u64,
    /// Every `alias_every`-th place looks like the previous one (0: no aliasing).
    pub alias_every: u64,
    /// Per-component noise amplitude of a keyframe's descriptor around its place's.
    pub noise: f32,
}

impl Default for SimWorld {
    fn default() -> Self {
        Self {
            seed: 1,
            places: 100,
            alias_every: 5,
            noise: 0.004,
        }
    }
}

impl SimWorld {
    /// The place keyframe `index` of robot `robot` sees.
    pub fn place_of(&self, robot: u8, index: u64) -> u64 {
        mix(self.seed ^ (u64::from(robot) << 48) ^ index.wrapping_mul(0x1000_0001))
            % self.places.max(1)
    }

    /// The place it looks like (itself, or its neighbour for an aliased place).
    fn appearance(&self, place: u64) -> u64 {
        if self.alias_every > 1 && place % self.alias_every == self.alias_every - 1 {
            place - 1
        } else {
            place
        }
    }

    /// Whether two keys saw the same place (the truth a verifier stand-in accepts by).
    pub fn same_place(&self, a: u64, b: u64) -> bool {
        match (key::robot(a), key::robot(b)) {
            (Some(ra), Some(rb)) => {
                self.place_of(ra, key::index(a)) == self.place_of(rb, key::index(b))
            }
            _ => false,
        }
    }

    /// The L2-normalized float descriptor of a keyframe.
    pub fn descriptor(&self, robot: u8, index: u64) -> [f32; DESCRIPTOR_DIM] {
        let look = self.appearance(self.place_of(robot, index));
        let noise_seed = mix(self.seed ^ 0x5555 ^ (u64::from(robot) << 48) ^ index);
        let mut v: [f32; DESCRIPTOR_DIM] = std::array::from_fn(|i| {
            unit(mix(self.seed ^ (look << 8) ^ i as u64))
                + self.noise * unit(mix(noise_seed ^ (i as u64) << 32))
        });
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        for x in &mut v {
            *x /= norm;
        }
        v
    }
}

/// Simulated keyframes and place recognition of one robot: keyframe `i` exists once
/// `created() > i` (advanced by the caller, e.g. one per interval of a run).
#[derive(Debug)]
pub struct SimPlaces {
    world: SimWorld,
    robot: u8,
    created: Arc<AtomicU64>,
    features_per_keyframe: usize,
    /// Match threshold on the Euclidean distance of L2-normalized descriptors.
    threshold: f32,
    own: Vec<[f32; DESCRIPTOR_DIM]>,
}

impl SimPlaces {
    pub fn new(world: SimWorld, robot: u8, features_per_keyframe: usize) -> Self {
        Self {
            world,
            robot,
            created: Arc::new(AtomicU64::new(0)),
            features_per_keyframe,
            threshold: 0.15,
            own: Vec::new(),
        }
    }

    /// The shared counter of keyframes created so far.
    pub fn created(&self) -> Arc<AtomicU64> {
        self.created.clone()
    }

    fn own_until(&mut self, end: u64) {
        while (self.own.len() as u64) < end {
            let i = self.own.len() as u64;
            // What a peer sees is the quantized descriptor: compare like with like.
            let d = self.world.descriptor(self.robot, i);
            let q = Descriptor::quantize(0, &d).map(|q| q.to_f32()).unwrap_or(d);
            self.own.push(q);
        }
    }
}

impl DescriptorSource for SimPlaces {
    fn descriptors_since(&mut self, from: u64, limit: usize) -> DescriptorBatch {
        let end = self
            .created
            .load(Ordering::Acquire)
            .min(from + limit as u64);
        let descriptors = (from..end.max(from))
            .filter_map(|i| {
                let k = key::symbol(self.robot, i).ok()?;
                Descriptor::quantize(k, &self.world.descriptor(self.robot, i)).ok()
            })
            .collect();
        DescriptorBatch {
            keyframes: from..end.max(from),
            descriptors,
        }
    }

    fn match_descriptors(&mut self, _peer: &RobotId, received: &[Descriptor]) -> Vec<Match> {
        let end = self.created.load(Ordering::Acquire);
        self.own_until(end);
        let mut out = Vec::new();
        for d in received {
            let q = d.to_f32();
            let best = self
                .own
                .iter()
                .enumerate()
                .map(|(i, o)| {
                    let dist = o
                        .iter()
                        .zip(&q)
                        .map(|(a, b)| (a - b) * (a - b))
                        .sum::<f32>();
                    (i, dist.sqrt())
                })
                .min_by(|a, b| a.1.total_cmp(&b.1));
            if let Some((i, distance)) = best {
                if distance < self.threshold {
                    if let Ok(candidate) = key::symbol(self.robot, i as u64) {
                        out.push(Match {
                            query: d.key,
                            candidate,
                            distance,
                        });
                    }
                }
            }
        }
        out
    }

    fn verification_features(&mut self, k: u64) -> Option<VerificationFeatures> {
        if key::robot(k) != Some(self.robot)
            || key::index(k) >= self.created.load(Ordering::Acquire)
        {
            return None;
        }
        let features = (0..self.features_per_keyframe as u64)
            .map(|j| {
                let h = mix(self.world.seed ^ k ^ (j << 20));
                VerificationFeature {
                    pixel: [(h % 12_000) as u16, ((h >> 16) % 7_600) as u16],
                    disparity: 64 + ((h >> 32) % 4_000) as u16,
                    descriptor: std::array::from_fn(|b| (mix(h ^ b as u64) & 0xff) as u8),
                }
            })
            .collect();
        Some(VerificationFeatures {
            key: k,
            camera: VerificationCamera {
                fx: 458.0,
                fy: 458.0,
                cx: 376.0,
                cy: 240.0,
                baseline_m: 0.11,
            },
            features,
        })
    }
}

/// Verification stand-in: accepts a putative pair exactly when a truth table says the two
/// keyframes saw the same place (and the packet is the candidate's and not empty). The
/// closure it makes has an identity relative pose and a fixed information.
pub struct TruthVerifier {
    truth: Box<dyn FnMut(u64, u64) -> bool + Send>,
}

impl TruthVerifier {
    pub fn new(truth: impl FnMut(u64, u64) -> bool + Send + 'static) -> Self {
        Self {
            truth: Box::new(truth),
        }
    }

    /// The truth of a [`SimWorld`].
    pub fn from_world(world: SimWorld) -> Self {
        Self::new(move |a, b| world.same_place(a, b))
    }
}

impl Verifier for TruthVerifier {
    fn verify(
        &mut self,
        _peer: &RobotId,
        m: &Match,
        features: &VerificationFeatures,
    ) -> Option<LoopClosure> {
        if features.key != m.candidate || features.features.is_empty() {
            return None;
        }
        if !(self.truth)(m.query, m.candidate) {
            return None;
        }
        let relative = Pose::from_array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).ok()?;
        let information =
            Information::from_matrix(&(doorslam_geometry::TangentMatrix::identity() * 100.0))
                .ok()?;
        Some(LoopClosure {
            key_a: m.query,
            key_b: m.candidate,
            relative,
            information,
            inliers: features.features.len() as u32,
        })
    }
}

/// What a back-end stand-in saw, readable at run time.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct BackendLog {
    /// Loop closures handed over, per peer.
    pub closures: BTreeMap<String, u64>,
    /// Pose estimates received, per peer.
    pub estimates_received: BTreeMap<String, u64>,
    /// Rounds sent, per peer.
    pub rounds_sent: BTreeMap<String, u64>,
}

/// Back-end stand-in that only records the closures and sends nothing.
#[derive(Debug, Default)]
pub struct NoBackend {
    pub log: Arc<Mutex<BackendLog>>,
}

impl BackendExchange for NoBackend {
    fn loop_closures(&mut self, peer: &RobotId, closures: &[LoopClosure]) {
        let mut log = self.log.lock().unwrap_or_else(|p| p.into_inner());
        *log.closures.entry(peer.to_string()).or_default() += closures.len() as u64;
    }

    fn messages_for(&mut self, _peer: &RobotId) -> Vec<Body> {
        Vec::new()
    }

    fn receive(
        &mut self,
        _peer: &RobotId,
        _header: &Header,
        body: Body,
    ) -> Result<(), BackendRefusal> {
        Err(BackendRefusal(format!(
            "no back-end runs here ({} dropped)",
            body.kind().name()
        )))
    }
}

/// Back-end stand-in that exercises the back-end's path through the link: after new
/// closures with a peer it sends one round of pose estimates of its own closure keyframes
/// (identity poses), and accepts pose estimates.
#[derive(Debug)]
pub struct EchoBackend {
    robot: u8,
    optimization: u64,
    due: BTreeMap<RobotId, Vec<u64>>,
    pub log: Arc<Mutex<BackendLog>>,
}

impl EchoBackend {
    pub fn new(robot: u8) -> Self {
        Self {
            robot,
            optimization: 0,
            due: BTreeMap::new(),
            log: Arc::default(),
        }
    }
}

impl BackendExchange for EchoBackend {
    fn loop_closures(&mut self, peer: &RobotId, closures: &[LoopClosure]) {
        let mut log = self.log.lock().unwrap_or_else(|p| p.into_inner());
        *log.closures.entry(peer.to_string()).or_default() += closures.len() as u64;
        let own = closures.iter().flat_map(|c| [c.key_a, c.key_b]);
        let own = own.filter(|&k| key::robot(k) == Some(self.robot));
        self.due.entry(peer.clone()).or_default().extend(own);
    }

    fn messages_for(&mut self, peer: &RobotId) -> Vec<Body> {
        let Some(keys) = self.due.remove(peer) else {
            return Vec::new();
        };
        let Ok(pose) = CompactPose::quantize(&SE3::identity()) else {
            return Vec::new();
        };
        let mut keys = keys;
        keys.sort_unstable();
        keys.dedup();
        let rounds: Vec<Body> = keys
            .chunks(doorslam_ipc::wire::MAX_POSE_ESTIMATES)
            .map(|chunk| {
                self.optimization += 1;
                Body::PoseEstimates(PoseEstimates {
                    optimization: self.optimization,
                    round: 0,
                    stage: Stage::Refine,
                    flags: 0,
                    anchor: self.robot,
                    estimates: chunk
                        .iter()
                        .map(|&key| PoseEstimate {
                            key,
                            value: Estimate::Pose(pose.clone()),
                        })
                        .collect(),
                })
            })
            .collect();
        let mut log = self.log.lock().unwrap_or_else(|p| p.into_inner());
        *log.rounds_sent.entry(peer.to_string()).or_default() += rounds.len() as u64;
        rounds
    }

    fn receive(
        &mut self,
        peer: &RobotId,
        _header: &Header,
        body: Body,
    ) -> Result<(), BackendRefusal> {
        let Body::PoseEstimates(p) = body else {
            return Err(BackendRefusal(format!(
                "echo back-end takes pose estimates, not {}",
                body.kind().name()
            )));
        };
        let mut log = self.log.lock().unwrap_or_else(|p| p.into_inner());
        *log.estimates_received.entry(peer.to_string()).or_default() += p.estimates.len() as u64;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_place_matches_and_aliases_are_rejected_by_the_truth() {
        let world = SimWorld::default();
        let mut a = SimPlaces::new(world, 0, 10);
        let mut b = SimPlaces::new(world, 1, 10);
        a.created().store(200, Ordering::Release);
        b.created().store(200, Ordering::Release);
        let batch = a.descriptors_since(0, 200);
        assert_eq!(batch.keyframes, 0..200);
        let peer = RobotId::new("a").unwrap();
        let matches = b.match_descriptors(&peer, &batch.descriptors);
        let mut verifier = TruthVerifier::from_world(world);
        let (mut yes, mut no) = (0, 0);
        for m in &matches {
            let f = b.verification_features(m.candidate).unwrap();
            match verifier.verify(&peer, m, &f) {
                Some(_) => yes += 1,
                None => no += 1,
            }
        }
        // 200 keyframes over 100 places: most find a true pair, and the aliased places
        // (1 in 5) give putative pairs the truth rejects.
        assert!(yes > 100, "{yes} true pairs");
        assert!(no > 5, "{no} aliased pairs");
        // A match is never proposed between different-looking places.
        for m in &matches {
            assert!(m.distance < 0.15);
        }
    }
}
