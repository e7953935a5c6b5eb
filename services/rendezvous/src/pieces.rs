//! The three pieces the team link's protocol calls into, for real: this robot's place
//! descriptors and their matching ([`Places`]), PnP-RANSAC verification of putative pairs
//! ([`PnpVerifier`]), and the relay to the back-end ([`BackendRelay`]). They share one
//! [`Shared`] state, fed by the robot's iceoryx2 topics (keyframes from the front-end,
//! descriptors from place recognition, the back-end's messages) in
//! [`crate::run::IpcSide`] and read here; nothing in this file touches shared memory, so
//! the pieces are tested with values.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};

use doorslam_dataset::StereoCalibration;
use doorslam_frontend::{verify, Rejection, VerifyConfig};
use doorslam_geometry::information::upper_from_matrix;
use doorslam_geometry::{key, pose_to_array, reverse_measurement};
use doorslam_ipc::wire::{
    Body, Descriptor, Header, Information, LoopClosure, Match, Message, Pose, RobotId,
    VerificationFeature, VerificationFeatures, DESCRIPTOR_DIM,
};
use doorslam_ipc::{EnvelopeEvent, Feature, Keyframe, PlaceDescriptor};
use doorslam_place_recognition::matching::Quantized;
use doorslam_team::protocol::{BackendExchange, BackendRefusal, DescriptorBatch, DescriptorSource};
use doorslam_team::{Pieces, Verifier};
use serde::Serialize;

/// How putative pairs are chosen and verified.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchSettings {
    /// A received descriptor matches an own keyframe whose descriptor is nearer than this
    /// (Euclidean distance of the L2-normalized descriptors, on the int8 wire form).
    pub threshold: f32,
    /// At most this many own keyframes per received descriptor (the nearest).
    pub max_candidates: usize,
    /// Features in a verification packet (the strongest first, as the front-end orders
    /// them); bounds the packet's size.
    pub max_packet_features: usize,
    pub verify: VerifyConfig,
}

impl Default for MatchSettings {
    fn default() -> Self {
        Self {
            threshold: 0.8,
            max_candidates: 1,
            max_packet_features: 475,
            verify: VerifyConfig::default(),
        }
    }
}

/// An envelope for the back-end (iceoryx2 topic `team-in`).
#[derive(Debug, Clone, PartialEq)]
pub struct ToBackend {
    pub event: EnvelopeEvent,
    pub peer_robot: u32,
    pub epoch: u64,
    pub bytes: Vec<u8>,
}

/// Counters of the pieces (in `status.json`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct PiecesStats {
    pub keyframes: u64,
    pub descriptors: u64,
    /// Own samples refused (wrong robot, wrong dimension, ...).
    pub refused_inputs: u64,
    pub putative_pairs: u64,
    pub verified: u64,
    /// Verification failures by reason.
    pub rejected: BTreeMap<String, u64>,
    pub closures_to_backend: u64,
    pub messages_to_backend: u64,
    pub messages_from_backend: u64,
    /// Closures handed to the back-end, per peer.
    pub closures_by_peer: BTreeMap<String, u64>,
    /// Back-end messages received from each peer (relayed to the back-end).
    pub backend_messages_by_peer: BTreeMap<String, u64>,
    /// Back-end messages sent to each peer (taken by the protocol).
    pub peer_messages_by_peer: BTreeMap<String, u64>,
}

/// What the pieces share.
#[derive(Debug)]
pub struct State {
    robot: u8,
    calib: StereoCalibration,
    settings: MatchSettings,
    /// Own keyframes' features, by keyframe index.
    features: BTreeMap<u64, Vec<Feature>>,
    /// Own descriptors, by keyframe index, in the wire's int8 form.
    descriptors: BTreeMap<u64, Quantized>,
    /// Team-in envelopes and closures waiting to be published to the back-end.
    to_backend: VecDeque<ToBackend>,
    closures: VecDeque<doorslam_ipc::LoopClosure>,
    /// The back-end's messages for each peer robot, waiting for the protocol.
    for_peers: BTreeMap<u8, VecDeque<Body>>,
    /// Peers by id: robot number and team-link epoch, from their Hello.
    peers: BTreeMap<RobotId, (u8, u64, bool)>,
    stats: PiecesStats,
}

/// The state behind the three pieces.
#[derive(Debug, Clone)]
pub struct Shared(Arc<Mutex<State>>);

impl Shared {
    pub fn new(robot: u8, calib: StereoCalibration, settings: MatchSettings) -> Self {
        Self(Arc::new(Mutex::new(State {
            robot,
            calib,
            settings,
            features: BTreeMap::new(),
            descriptors: BTreeMap::new(),
            to_backend: VecDeque::new(),
            closures: VecDeque::new(),
            for_peers: BTreeMap::new(),
            peers: BTreeMap::new(),
            stats: PiecesStats::default(),
        })))
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock cannot leave the maps half-updated in a way that
        // matters more than stopping the robot's team link would.
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The protocol's pieces over this state.
    pub fn pieces(&self) -> Pieces {
        Pieces {
            place: Box::new(Places(self.clone())),
            verifier: Box::new(PnpVerifier(self.clone())),
            backend: Box::new(BackendRelay(self.clone())),
        }
    }

    pub fn stats(&self) -> PiecesStats {
        self.lock().stats.clone()
    }

    /// Keyframes known (the highest index + 1).
    pub fn keyframes(&self) -> u64 {
        self.lock()
            .features
            .keys()
            .next_back()
            .map_or(0, |k| k + 1)
    }

    /// An own keyframe from the front-end: its features, for verification packets and
    /// for verifying the peers' packets against it.
    pub fn add_keyframe(&self, kf: &Keyframe) -> Result<(), String> {
        let mut s = self.lock();
        if kf.robot != u32::from(s.robot) {
            s.stats.refused_inputs += 1;
            return Err(format!(
                "keyframe {} of robot {}, this is robot {}",
                kf.id, kf.robot, s.robot
            ));
        }
        let n = (kf.n_features as usize).min(kf.features.len());
        s.features.insert(kf.id, kf.features[..n].to_vec());
        s.stats.keyframes += 1;
        Ok(())
    }

    /// An own place descriptor from place recognition.
    pub fn add_descriptor(&self, d: &PlaceDescriptor) -> Result<(), String> {
        let mut s = self.lock();
        let refuse = |s: &mut State, why: String| {
            s.stats.refused_inputs += 1;
            Err(why)
        };
        if d.robot != u32::from(s.robot) {
            let why = format!("descriptor of robot {}, this is robot {}", d.robot, s.robot);
            return refuse(&mut s, why);
        }
        if d.dim as usize != DESCRIPTOR_DIM {
            let why = format!(
                "descriptor of keyframe {} has {} values; the wire form has {DESCRIPTOR_DIM} \
                 (configure place recognition for {DESCRIPTOR_DIM}-D descriptors)",
                d.keyframe, d.dim
            );
            return refuse(&mut s, why);
        }
        let k = match key::symbol(s.robot, d.keyframe) {
            Ok(k) => k,
            Err(e) => return refuse(&mut s, e.to_string()),
        };
        match Descriptor::quantize(k, &d.values[..DESCRIPTOR_DIM]) {
            Ok(q) => {
                s.descriptors.insert(d.keyframe, Quantized::new(q));
                s.stats.descriptors += 1;
                Ok(())
            }
            Err(e) => refuse(&mut s, format!("descriptor of keyframe {}: {e}", d.keyframe)),
        }
    }

    /// A message the back-end wants sent to robot `peer_robot` (its body goes out through
    /// the protocol, under the protocol's own header).
    pub fn queue_for_peer(&self, peer_robot: u8, message: Message) {
        let mut s = self.lock();
        s.stats.messages_from_backend += 1;
        s.for_peers
            .entry(peer_robot)
            .or_default()
            .push_back(message.body);
    }

    /// Envelopes and closures for the back-end, oldest first.
    pub fn take_for_backend(&self) -> (Vec<ToBackend>, Vec<doorslam_ipc::LoopClosure>) {
        let mut s = self.lock();
        (s.to_backend.drain(..).collect(), s.closures.drain(..).collect())
    }

    /// Presence envelopes of every peer present now (after the back-end restarted, it
    /// must learn who is in range).
    pub fn announce_presence(&self) {
        let mut s = self.lock();
        let present: Vec<(u8, u64)> = s
            .peers
            .values()
            .filter(|p| p.2)
            .map(|p| (p.0, p.1))
            .collect();
        for (robot, epoch) in present {
            s.to_backend.push_back(ToBackend {
                event: EnvelopeEvent::PeerPresent,
                peer_robot: u32::from(robot),
                epoch,
                bytes: Vec::new(),
            });
        }
    }

    /// The link started a new epoch: messages the back-end had queued for peers were
    /// written for the old one and are dropped (the back-end sends again after
    /// [`EnvelopeEvent::TeamStarted`]).
    pub fn new_epoch(&self, epoch: u64) {
        let mut s = self.lock();
        s.for_peers.clear();
        for p in s.peers.values_mut() {
            p.2 = false;
        }
        let robot = u32::from(s.robot);
        s.to_backend.push_back(ToBackend {
            event: EnvelopeEvent::TeamStarted,
            peer_robot: robot,
            epoch,
            bytes: Vec::new(),
        });
    }
}

/// Own descriptors and their matching: [`DescriptorSource`].
pub struct Places(Shared);

impl DescriptorSource for Places {
    fn descriptors_since(&mut self, from: u64, limit: usize) -> DescriptorBatch {
        let s = self.0.lock();
        // Descriptors come in keyframe order; a keyframe place recognition skipped (its
        // image was gone) is covered by the next descriptor's range and never sent.
        let end = s
            .descriptors
            .keys()
            .next_back()
            .map_or(from, |last| (last + 1).max(from));
        let mut descriptors = Vec::new();
        let mut covered = from;
        for (&i, q) in s.descriptors.range(from..end) {
            if descriptors.len() == limit {
                break;
            }
            descriptors.push(q.descriptor.clone());
            covered = i + 1;
        }
        if descriptors.len() < limit {
            covered = end;
        }
        DescriptorBatch {
            keyframes: from..covered,
            descriptors,
        }
    }

    fn match_descriptors(&mut self, _peer: &RobotId, received: &[Descriptor]) -> Vec<Match> {
        let mut s = self.0.lock();
        let (threshold, k) = (s.settings.threshold, s.settings.max_candidates.max(1));
        let robot = s.robot;
        let mut out = Vec::new();
        for d in received {
            let q = Quantized::new(d.clone());
            let mut near: Vec<(u64, f32)> = s
                .descriptors
                .iter()
                .map(|(&i, own)| (i, own.distance2(&q).sqrt()))
                .filter(|(_, dist)| *dist < threshold)
                .collect();
            near.sort_by(|a, b| a.1.total_cmp(&b.1));
            for (i, distance) in near.into_iter().take(k) {
                if let Ok(candidate) = key::symbol(robot, i) {
                    out.push(Match {
                        query: d.key,
                        candidate,
                        distance,
                    });
                }
            }
        }
        s.stats.putative_pairs += out.len() as u64;
        out
    }

    fn verification_features(&mut self, k: u64) -> Option<VerificationFeatures> {
        let s = self.0.lock();
        if key::robot(k) != Some(s.robot) {
            return None;
        }
        let features = s.features.get(&key::index(k))?;
        let packet: Vec<VerificationFeature> = features
            .iter()
            .filter_map(|f| VerificationFeature::quantize(f).ok())
            .take(s.settings.max_packet_features)
            .collect();
        Some(VerificationFeatures {
            key: k,
            features: packet,
        })
    }
}

/// A keyframe feature as verification uses it.
fn frontend_feature(f: &Feature, calib: &StereoCalibration) -> doorslam_frontend::Feature {
    // The stereo depth uncertainty for a 0.5 px disparity error (as the odometry's).
    let z = f64::from(f.point[2]);
    let depth_sigma = z * z * 0.5 / (calib.fx * calib.baseline_m);
    doorslam_frontend::Feature {
        pixel: f.uv,
        descriptor: f.descriptor,
        point: f.point,
        depth_sigma_m: depth_sigma as f32,
    }
}

fn rejection_name(r: &Rejection) -> &'static str {
    match r {
        Rejection::TooFewFeatures { .. } => "too_few_features",
        Rejection::BadFeature { .. } => "bad_feature",
        Rejection::TooFewMatches { .. } => "too_few_matches",
        Rejection::NoPose => "no_pose",
        Rejection::TooFewInliers { .. } => "too_few_inliers",
    }
}

/// PnP-RANSAC verification of a putative pair: [`Verifier`].
pub struct PnpVerifier(Shared);

impl Verifier for PnpVerifier {
    fn verify(
        &mut self,
        peer: &RobotId,
        m: &Match,
        packet: &VerificationFeatures,
    ) -> Option<LoopClosure> {
        let mut s = self.0.lock();
        let calib = s.calib;
        let Some(own) = s.features.get(&key::index(m.query)) else {
            *s.stats.rejected.entry("unknown_keyframe".into()).or_default() += 1;
            return None;
        };
        let local: Vec<_> = own.iter().map(|f| frontend_feature(f, &calib)).collect();
        let remote: Vec<_> = packet
            .features
            .iter()
            .map(|f| frontend_feature(&f.to_feature(), &calib))
            .collect();
        let verified = match verify(&calib, &local, &remote, &s.settings.verify) {
            Ok(v) => v,
            Err(r) => {
                tracing::debug!(peer = %peer, pair = %format!("{} - {}", key::label(m.query), key::label(m.candidate)), "verification: {r}");
                *s.stats.rejected.entry(rejection_name(&r).into()).or_default() += 1;
                return None;
            }
        };
        // Verification gives the local (own) camera in the remote (peer's) keyframe's
        // frame; the closure goes from the own keyframe to the peer's.
        let (z, information) = reverse_measurement(&verified.relative, &verified.information);
        let closure = LoopClosure {
            key_a: m.query,
            key_b: m.candidate,
            relative: Pose::from_se3(&z).ok()?,
            information: Information::from_matrix(&information).ok()?,
            inliers: verified.inliers as u32,
        };
        s.stats.verified += 1;
        tracing::info!(
            peer = %peer,
            pair = %format!("{} - {}", key::label(m.query), key::label(m.candidate)),
            inliers = verified.inliers,
            "verification: accepted"
        );
        Some(closure)
    }
}

/// The relay to the back-end: [`BackendExchange`].
pub struct BackendRelay(Shared);

impl BackendExchange for BackendRelay {
    fn loop_closures(&mut self, peer: &RobotId, closures: &[LoopClosure]) {
        let mut s = self.0.lock();
        *s.stats
            .closures_by_peer
            .entry(peer.to_string())
            .or_default() += closures.len() as u64;
        for c in closures {
            let (Some(ra), Some(rb)) = (key::robot(c.key_a), key::robot(c.key_b)) else {
                continue;
            };
            s.closures.push_back(doorslam_ipc::LoopClosure {
                robot_a: u32::from(ra),
                robot_b: u32::from(rb),
                keyframe_a: key::index(c.key_a),
                keyframe_b: key::index(c.key_b),
                relative: pose_to_array(c.relative.se3()),
                information: upper_from_matrix(c.information.matrix()),
                inliers: c.inliers,
                reserved: 0,
            });
            s.stats.closures_to_backend += 1;
        }
    }

    fn messages_for(&mut self, peer: &RobotId) -> Vec<Body> {
        let mut s = self.0.lock();
        let Some(&(robot, _, _)) = s.peers.get(peer) else {
            return Vec::new();
        };
        let bodies: Vec<Body> = s
            .for_peers
            .get_mut(&robot)
            .map(|q| q.drain(..).collect())
            .unwrap_or_default();
        *s.stats
            .peer_messages_by_peer
            .entry(peer.to_string())
            .or_default() += bodies.len() as u64;
        bodies
    }

    fn receive(
        &mut self,
        peer: &RobotId,
        header: &Header,
        body: Body,
    ) -> Result<(), BackendRefusal> {
        let mut s = self.0.lock();
        let Some(&(robot, _, _)) = s.peers.get(peer) else {
            return Err(BackendRefusal(format!("{peer} said no Hello yet")));
        };
        let bytes = Message::new(header.clone(), body)
            .encode()
            .map_err(|e| BackendRefusal(format!("does not re-encode: {e}")))?;
        s.stats.messages_to_backend += 1;
        *s.stats
            .backend_messages_by_peer
            .entry(peer.to_string())
            .or_default() += 1;
        s.to_backend.push_back(ToBackend {
            event: EnvelopeEvent::Message,
            peer_robot: u32::from(robot),
            epoch: header.epoch,
            bytes,
        });
        Ok(())
    }

    fn presence(&mut self, peer: &RobotId, robot: u8, epoch: u64, present: bool) {
        let mut s = self.0.lock();
        s.peers.insert(peer.clone(), (robot, epoch, present));
        s.to_backend.push_back(ToBackend {
            event: if present {
                EnvelopeEvent::PeerPresent
            } else {
                EnvelopeEvent::PeerAbsent
            },
            peer_robot: u32::from(robot),
            epoch,
            bytes: Vec::new(),
        });
    }
}
