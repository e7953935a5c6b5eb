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
use doorslam_frontend::packet::{from_packet, to_packet, MAX_PACKET_FEATURES};
use doorslam_frontend::{verify, VerifyConfig};
use doorslam_geometry::information::upper_from_matrix;
use doorslam_geometry::{key, pose_to_array, reverse_measurement};
use doorslam_ipc::wire::{
    Body, Descriptor, Descriptors, Header, Information, LoopClosure, Match, Message, Pose, RobotId,
    VerificationFeatures, DESCRIPTOR_DIM,
};
use doorslam_ipc::{EnvelopeEvent, Feature, Keyframe, PlaceDescriptor};
use doorslam_place_recognition::{CandidateChain, ChainConfig, ChainStats, MatchIndex};
use doorslam_team::protocol::{BackendExchange, BackendRefusal, DescriptorBatch, DescriptorSource};
use doorslam_team::{Pieces, Verifier};
use serde::Serialize;

use crate::features::{OwnFeatureStats, OwnFeatures, DEFAULT_FEATURES_IN_MEMORY};
use crate::own_loops::{OwnLoopStats, OwnLoops, VerifyInputs};
use crate::store::{OwnStore, StoreError};

/// How putative pairs are chosen and verified.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchSettings {
    /// The candidate chain of received descriptors against own keyframes: top-k below the
    /// match threshold (Euclidean distance on the int8 wire form; place recognition's
    /// fitted threshold of the descriptor in use, `[place] match_threshold`), temporal
    /// confirmation (`[place]`, [`doorslam_place_recognition::CandidateChain`]).
    pub chain: ChainConfig,
    /// The robot's own loops: the chain over its own descriptors against its keyframes
    /// older than `temporal_exclusion` ids (`None`: off; `[place] own_loops`).
    pub own_loops: Option<ChainConfig>,
    pub temporal_exclusion: u64,
    /// Features in a verification packet (the strongest first, as the front-end orders
    /// them); bounds the packet's size (the front-end's packet holds at most
    /// [`MAX_PACKET_FEATURES`]: ≤ 20 kB).
    pub max_packet_features: usize,
    pub verify: VerifyConfig,
    /// The back-end's messages waiting for one peer robot (while it is away) at most: a
    /// state message merges into the newest waiting one of its slot first; beyond, the
    /// new one is refused (`for_peer_refused`).
    pub for_peer_limit: usize,
    /// Own keyframes' features held in memory at most; the least recently used leaves
    /// for the keyframe store and is read back when needed ([`crate::features`]).
    pub features_in_memory: usize,
}

impl Default for MatchSettings {
    fn default() -> Self {
        let chain = doorslam_place_recognition::Method::BagOfWords.default_chain();
        Self {
            own_loops: Some(chain.clone()),
            chain,
            temporal_exclusion: 10,
            max_packet_features: MAX_PACKET_FEATURES,
            verify: VerifyConfig::default(),
            // Every back-end kind is a state kind, merged per slot: what waits for a peer
            // is a few messages per robot of the team; this is far above that.
            for_peer_limit: 1024,
            features_in_memory: DEFAULT_FEATURES_IN_MEMORY,
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
    /// The candidate chain's stages over all peers (`putative_pairs` = its confirmed).
    pub chain: ChainStats,
    pub verified: u64,
    /// Verification failures by reason.
    pub rejected: BTreeMap<String, u64>,
    pub closures_to_backend: u64,
    pub messages_to_backend: u64,
    pub messages_from_backend: u64,
    /// The back-end's messages for a peer merged into a waiting one of their slot, and
    /// refused because `for_peer_limit` were waiting.
    pub for_peer_superseded: u64,
    pub for_peer_refused: u64,
    /// Closures handed to the back-end, per peer.
    pub closures_by_peer: BTreeMap<String, u64>,
    /// Back-end messages received from each peer (relayed to the back-end).
    pub backend_messages_by_peer: BTreeMap<String, u64>,
    /// Back-end messages sent to each peer (taken by the protocol).
    pub peer_messages_by_peer: BTreeMap<String, u64>,
    /// Own keyframes and descriptors read back from the store at start (a restart).
    pub restored_keyframes: u64,
    pub restored_descriptors: u64,
    /// Appends to the store that failed (logged; the keyframe is still offered until the
    /// next restart).
    pub store_errors: u64,
    /// The robot's own loops (counted apart from the inter-robot closures above).
    pub own_loops: OwnLoopStats,
    /// Own keyframes' features in memory, on disk, moved between them.
    pub own_features: OwnFeatureStats,
}

/// What the pieces share.
#[derive(Debug)]
pub struct State {
    robot: u8,
    calib: StereoCalibration,
    settings: MatchSettings,
    /// Own keyframes' features (strongest first, as the front-end sends them), by index:
    /// `features_in_memory` in memory, the rest in the store.
    features: OwnFeatures,
    /// Own descriptors, by keyframe index, in the wire's int8 form (sent as they are), and
    /// the index matching received ones against them.
    descriptors: BTreeMap<u64, Descriptor>,
    index: MatchIndex,
    /// The candidate chain of each peer robot's descriptors.
    chains: BTreeMap<u8, CandidateChain>,
    own_loops: Option<OwnLoops>,
    /// Team-in envelopes and closures waiting to be published to the back-end.
    to_backend: VecDeque<ToBackend>,
    closures: VecDeque<doorslam_ipc::LoopClosure>,
    /// The back-end's messages for each peer robot, waiting for the protocol.
    for_peers: BTreeMap<u8, VecDeque<Body>>,
    /// Peers by id: robot number and team-link epoch, from their Hello.
    peers: BTreeMap<RobotId, (u8, u64, bool)>,
    /// Where own keyframes are kept across restarts (none in tests of the protocol).
    store: Option<OwnStore>,
    stats: PiecesStats,
}

/// The state behind the three pieces.
#[derive(Debug, Clone)]
pub struct Shared(Arc<Mutex<State>>);

impl Shared {
    pub fn new(robot: u8, calib: StereoCalibration, settings: MatchSettings) -> Self {
        let index = MatchIndex::new(
            robot,
            settings.chain.max_distance,
            settings.temporal_exclusion,
        );
        let own_loops = settings.own_loops.clone().map(OwnLoops::new);
        let features = OwnFeatures::new(settings.features_in_memory);
        Self(Arc::new(Mutex::new(State {
            robot,
            calib,
            settings,
            features,
            descriptors: BTreeMap::new(),
            index,
            chains: BTreeMap::new(),
            own_loops,
            to_backend: VecDeque::new(),
            closures: VecDeque::new(),
            for_peers: BTreeMap::new(),
            peers: BTreeMap::new(),
            store: None,
            stats: PiecesStats::default(),
        })))
    }

    /// Keeps own keyframes in the store at `path` from now on, after taking back what it
    /// holds (the keyframes of this robot's earlier runs, see [`crate::store`]).
    pub fn open_store(&self, path: &std::path::Path) -> Result<(), StoreError> {
        let mut guard = self.lock();
        let s = &mut *guard;
        let store = OwnStore::open(path, |body, offset| match body {
            // Only where it is: read back when a keyframe is needed.
            Body::VerificationFeatures(v) if key::robot(v.key) == Some(s.robot) => {
                s.features.spilled(key::index(v.key), offset);
                s.stats.restored_keyframes += 1;
            }
            Body::Descriptors(d) => {
                for q in d.descriptors {
                    if key::robot(q.key) != Some(s.robot) || s.index.insert(q.clone()).is_err() {
                        continue;
                    }
                    s.descriptors.insert(key::index(q.key), q);
                    s.stats.restored_descriptors += 1;
                }
            }
            _ => {}
        })?;
        if s.stats.restored_keyframes > 0 || s.stats.restored_descriptors > 0 {
            tracing::info!(
                path = %path.display(),
                keyframes = s.stats.restored_keyframes,
                descriptors = s.stats.restored_descriptors,
                "team: own keyframes of earlier runs restored"
            );
        }
        s.store = Some(store);
        Ok(())
    }

    /// Appends to the store, if any, and returns the record's offset; a failure is logged
    /// and counted, never fatal.
    fn keep(s: &mut State, body: impl FnOnce(&State) -> Option<Body>) -> Option<u64> {
        s.store.as_ref()?;
        let body = body(s)?;
        let store = s.store.as_mut()?;
        match store.append(body) {
            Ok(offset) => Some(offset),
            Err(e) => {
                tracing::error!("team: {e}");
                s.stats.store_errors += 1;
                None
            }
        }
    }

    /// Own keyframe `index`'s features, from memory or read back from the store.
    fn features_of(s: &mut State, index: u64) -> Option<Arc<[doorslam_frontend::Feature]>> {
        let sigma = s.settings.verify.disparity_sigma_px;
        s.features.get(index, s.store.as_ref(), sigma)
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
        let s = self.lock();
        let mut stats = s.stats.clone();
        for c in s.chains.values() {
            let c = c.stats();
            stats.chain.queries += c.queries;
            stats.chain.ranked += c.ranked;
            stats.chain.confirmed += c.confirmed;
            stats.chain.unconfirmed += c.unconfirmed;
        }
        if let Some(own) = &s.own_loops {
            stats.own_loops = own.stats();
        }
        stats.own_features = s.features.stats();
        stats
    }

    /// Keyframes known (the highest index + 1).
    pub fn keyframes(&self) -> u64 {
        self.lock().features.last().map_or(0, |k| k + 1)
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
        let sigma = s.settings.verify.disparity_sigma_px;
        let features: Vec<_> = kf.features[..n]
            .iter()
            .map(|f| frontend_feature(f, &s.calib, sigma))
            .collect();
        let id = kf.id;
        // Into the store first, so that the keyframe can leave memory from now on.
        let spilled = Self::keep(&mut s, |s| {
            let k = key::symbol(s.robot, id).ok()?;
            to_packet(k, &s.calib, &features, s.settings.max_packet_features)
                .ok()
                .map(Body::VerificationFeatures)
        });
        if let Some(offset) = spilled {
            s.features.spilled(id, offset);
        }
        s.features.insert(id, features);
        s.stats.keyframes += 1;
        Self::own_loops(&mut s, None);
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
        let q = match Descriptor::quantize(k, &d.values[..DESCRIPTOR_DIM]) {
            Ok(q) => q,
            Err(e) => {
                return refuse(
                    &mut s,
                    format!("descriptor of keyframe {}: {e}", d.keyframe),
                )
            }
        };
        // Own loops first: the new keyframe against the older ones, before it joins them.
        Self::own_loops(&mut s, Some(&q));
        if let Err(e) = s.index.insert(q.clone()) {
            return refuse(&mut s, e.to_string());
        }
        s.descriptors.insert(d.keyframe, q.clone());
        s.stats.descriptors += 1;
        let (robot, keyframe) = (s.robot, d.keyframe);
        Self::keep(&mut s, |_| {
            Some(Body::Descriptors(Descriptors {
                robot,
                keyframes: keyframe..keyframe + 1,
                descriptors: vec![q],
            }))
        });
        Ok(())
    }

    /// Runs the own-loop chain on a new own descriptor (or, without one, retries the pairs
    /// waiting for keyframe features); closures go to the back-end's queue.
    fn own_loops(s: &mut State, descriptor: Option<&Descriptor>) {
        let State {
            robot,
            calib,
            settings,
            features,
            index,
            own_loops,
            closures,
            store,
            ..
        } = s;
        let Some(own) = own_loops.as_mut() else {
            return;
        };
        let mut inputs = VerifyInputs {
            robot: *robot,
            calib,
            features,
            store: store.as_ref(),
            config: &settings.verify,
        };
        let found = match descriptor {
            Some(d) => own.on_descriptor(index, d, &mut inputs),
            None => own.retry(&mut inputs),
        };
        closures.extend(found);
    }

    /// A message the back-end wants sent to robot `peer_robot` (its body goes out through
    /// the protocol, under the protocol's own header).
    pub fn queue_for_peer(&self, peer_robot: u8, message: Message) {
        let mut s = self.lock();
        s.stats.messages_from_backend += 1;
        let limit = s.settings.for_peer_limit;
        let body = message.body;
        let queue = s.for_peers.entry(peer_robot).or_default();
        // The newest of its slot: an update composes with the version just before it.
        if let Some(slot) = body.slot() {
            if let Some(at) = queue.iter().rposition(|b| b.slot() == Some(slot)) {
                if queue[at].supersede(body.clone()).is_ok() {
                    s.stats.for_peer_superseded += 1;
                    return;
                }
            }
        }
        if queue.len() >= limit {
            // Refused, not an older one dropped: the peer must get what it gets in order
            // (a graph update names the version before it).
            tracing::warn!(
                peer_robot,
                kind = body.kind().name(),
                limit,
                "back-end message for an absent peer refused: for_peer_limit waiting"
            );
            s.stats.for_peer_refused += 1;
            return;
        }
        queue.push_back(body);
    }

    /// Envelopes and closures for the back-end, oldest first.
    pub fn take_for_backend(&self) -> (Vec<ToBackend>, Vec<doorslam_ipc::LoopClosure>) {
        let mut s = self.lock();
        (
            s.to_backend.drain(..).collect(),
            s.closures.drain(..).collect(),
        )
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

    /// Tells the back-end the link's epoch (after the back-end announced itself: a
    /// back-end that started after the link missed [`Self::new_epoch`]'s announcement).
    pub fn announce_team(&self, epoch: u64) {
        let mut s = self.lock();
        let robot = u32::from(s.robot);
        s.to_backend.push_back(ToBackend {
            event: EnvelopeEvent::TeamStarted,
            peer_robot: robot,
            epoch,
            bytes: Vec::new(),
        });
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
            descriptors.push(q.clone());
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
        let Some(peer) = received.first().and_then(|d| key::robot(d.key)) else {
            return Vec::new();
        };
        let State {
            index,
            chains,
            settings,
            ..
        } = &mut *s;
        let chain = chains
            .entry(peer)
            .or_insert_with(|| CandidateChain::new(settings.chain.clone()));
        // One peer's descriptors per call (the protocol checks the batch's robot).
        let out = chain.push(index, received);
        s.stats.putative_pairs += out.len() as u64;
        out
    }

    fn verification_features(&mut self, k: u64) -> Option<VerificationFeatures> {
        let mut s = self.0.lock();
        if key::robot(k) != Some(s.robot) {
            return None;
        }
        let features = Shared::features_of(&mut s, key::index(k))?;
        match to_packet(k, &s.calib, &features, s.settings.max_packet_features) {
            Ok(p) => Some(p),
            Err(e) => {
                tracing::error!("verification packet of {}: {e}", key::label(k));
                None
            }
        }
    }
}

/// A keyframe feature (shared memory) as verification uses it: the depth σ of a
/// `disparity_sigma_px` disparity error, as the odometry's noise model.
fn frontend_feature(
    f: &Feature,
    calib: &StereoCalibration,
    disparity_sigma_px: f64,
) -> doorslam_frontend::Feature {
    let z = f64::from(f.point[2]);
    let depth_sigma = z * z * disparity_sigma_px / (calib.fx * calib.baseline_m);
    doorslam_frontend::Feature {
        pixel: f.uv,
        descriptor: f.descriptor,
        point: f.point,
        depth_sigma_m: depth_sigma as f32,
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
        let Some(own) = Shared::features_of(&mut s, key::index(m.query)) else {
            *s.stats
                .rejected
                .entry("unknown_keyframe".into())
                .or_default() += 1;
            return None;
        };
        let (remote_calib, remote) = from_packet(packet, s.settings.verify.disparity_sigma_px);
        let verified = match verify(&calib, &own, &remote_calib, &remote, &s.settings.verify) {
            Ok(v) => v,
            Err(r) => {
                tracing::debug!(peer = %peer, pair = %format!("{} - {}", key::label(m.query), key::label(m.candidate)), "verification: {r}");
                *s.stats.rejected.entry(r.name().into()).or_default() += 1;
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
        // The relay to the back-end carries at most an envelope. A peer's back-end sends
        // through the same envelope, so only a hostile or broken peer goes past it; writing
        // it would fail the relay, and the supervisor would restart this service for every
        // resend of it (a robot knocked off the team by one message).
        if bytes.len() > doorslam_ipc::MAX_ENVELOPE_BYTES {
            return Err(BackendRefusal(format!(
                "{} bytes, more than the back-end relay's envelope of {}",
                bytes.len(),
                doorslam_ipc::MAX_ENVELOPE_BYTES
            )));
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use doorslam_geometry::SE3;
    use doorslam_ipc::wire::{Header, Hello};
    use doorslam_ipc::{KeyframeSource, MAX_DESCRIPTOR_DIM, MAX_KEYFRAME_FEATURES};
    use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};

    fn calib() -> StereoCalibration {
        StereoCalibration {
            fx: 458.0,
            fy: 457.0,
            cx: 367.0,
            cy: 248.0,
            baseline_m: 0.11,
        }
    }

    /// A world of points with one distinct descriptor each.
    fn points() -> Vec<(Point3<f64>, [u8; 32])> {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        (0..300)
            .map(|_| {
                let u = |v: u64| (v % 10_000) as f64 / 10_000.0;
                let p = Point3::new(
                    u(next()) * 10.0 - 5.0,
                    u(next()) * 6.0 - 3.0,
                    4.0 + u(next()) * 12.0,
                );
                let d = std::array::from_fn(|_| (next() & 0xff) as u8);
                (p, d)
            })
            .collect()
    }

    /// The keyframe a camera at `pose` (camera-to-world) makes of the points.
    fn keyframe(robot: u32, id: u64, pose: &SE3) -> Box<Keyframe> {
        let c = calib();
        let mut kf = Box::new(Keyframe {
            robot,
            source: KeyframeSource::VisualOdometry as u32,
            id,
            frame_seq: id,
            stamp_ns: id,
            pose: doorslam_geometry::pose_to_array(pose),
            n_features: 0,
            reserved: 0,
            features: [Feature::default(); MAX_KEYFRAME_FEATURES],
        });
        let mut n = 0;
        for (p, d) in points() {
            let q = pose.inverse() * p;
            if q.z < 1.0 {
                continue;
            }
            let uv = [c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy];
            if !(0.0..752.0).contains(&uv[0]) || !(0.0..480.0).contains(&uv[1]) {
                continue;
            }
            kf.features[n] = Feature {
                uv: [uv[0] as f32, uv[1] as f32],
                point: [q.x as f32, q.y as f32, q.z as f32],
                descriptor: d,
            };
            n += 1;
        }
        kf.n_features = n as u32;
        kf
    }

    fn descriptor(robot: u32, keyframe: u64, v: &[f32]) -> Box<PlaceDescriptor> {
        let mut d = Box::new(PlaceDescriptor {
            robot,
            dim: v.len() as u32,
            keyframe,
            values: [0.0; MAX_DESCRIPTOR_DIM],
        });
        d.values[..v.len()].copy_from_slice(v);
        d
    }

    fn unit(i: usize) -> Vec<f32> {
        (0..DESCRIPTOR_DIM)
            .map(|k| if k == i { 1.0 } else { 0.0 })
            .collect()
    }

    #[test]
    fn descriptors_are_batched_by_keyframe_range_and_gaps_are_covered() {
        let s = Shared::new(0, calib(), MatchSettings::default());
        for id in [0, 1, 3] {
            s.add_descriptor(&descriptor(0, id, &unit(id as usize)))
                .unwrap();
        }
        let mut places = Places(s.clone());
        let b = places.descriptors_since(0, 2);
        assert_eq!(b.keyframes, 0..2);
        assert_eq!(b.descriptors.len(), 2);
        // Keyframe 2 has no descriptor (place recognition skipped it): covered by 3's.
        let b = places.descriptors_since(2, 16);
        assert_eq!(b.keyframes, 2..4);
        assert_eq!(b.descriptors.len(), 1);
        assert_eq!(b.descriptors[0].key, key::symbol(0, 3).unwrap());
        assert_eq!(places.descriptors_since(4, 16).keyframes, 4..4);
        // Another robot's or a wrong-size descriptor is refused, not stored.
        assert!(s.add_descriptor(&descriptor(1, 9, &unit(0))).is_err());
        assert!(s.add_descriptor(&descriptor(0, 9, &[1.0; 64])).is_err());
        assert_eq!(s.stats().refused_inputs, 2);
    }

    #[test]
    fn a_restarted_team_link_offers_its_earlier_keyframes_again() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("b").join("team.own");
        let x = SE3::identity();
        let before = {
            let s = Shared::new(1, calib(), MatchSettings::default());
            s.open_store(&path).unwrap();
            for id in 0..3 {
                s.add_keyframe(&keyframe(1, id, &x)).unwrap();
                s.add_descriptor(&descriptor(1, id, &unit(id as usize)))
                    .unwrap();
            }
            let packet = Places(s.clone())
                .verification_features(key::symbol(1, 2).unwrap())
                .unwrap();
            (Places(s).descriptors_since(0, 16), packet)
        };
        // The process dies mid-write: a torn record at the end.
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .unwrap();
        std::io::Write::write_all(&mut f, &[200, 1, 0, 0, 9, 9]).unwrap();
        drop(f);
        let s = Shared::new(1, calib(), nearest_only());
        s.open_store(&path).unwrap();
        assert_eq!(s.stats().restored_keyframes, 3);
        assert_eq!(s.stats().restored_descriptors, 3);
        assert_eq!(s.keyframes(), 3);
        let mut places = Places(s.clone());
        let again = places.descriptors_since(0, 16);
        assert_eq!(again.keyframes, before.0.keyframes);
        assert_eq!(again.descriptors, before.0.descriptors);
        // The packet made from the restored features is the one sent before.
        let packet = places
            .verification_features(key::symbol(1, 2).unwrap())
            .unwrap();
        assert_eq!(packet, before.1);
        // A received descriptor matches a restored keyframe.
        let near = Descriptor::quantize(key::symbol(0, 7).unwrap(), &unit(1)).unwrap();
        let m = places.match_descriptors(&RobotId::new("a").unwrap(), &[near]);
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].candidate, key::symbol(1, 1).unwrap());
        // New keyframes go on after the torn tail was cut off.
        s.add_descriptor(&descriptor(1, 3, &unit(3))).unwrap();
        let s2 = Shared::new(1, calib(), MatchSettings::default());
        s2.open_store(&path).unwrap();
        assert_eq!(s2.stats().restored_descriptors, 4);
        // Garbage in the middle of the file: an error naming the file and offset.
        std::fs::write(&path, [5, 0, 0, 0, 1, 2, 3, 4, 5]).unwrap();
        let e = Shared::new(1, calib(), MatchSettings::default())
            .open_store(&path)
            .unwrap_err()
            .to_string();
        assert!(e.contains("team.own") && e.contains("byte 0"), "{e}");
    }

    /// Settings with the chain cut down to the nearest candidate (tests of other parts).
    /// The back-end's messages for an absent peer, ten times `for_peer_limit` of them:
    /// state messages merge per slot (one waits, the newest), stream ones stop at the
    /// bound (the rest refused, counted), and the peer, when present, gets the first ones
    /// in order.
    #[test]
    fn messages_for_an_absent_peer_stay_within_their_bound() {
        use doorslam_ipc::wire::{Descriptors, Route};
        let settings = MatchSettings {
            for_peer_limit: 8,
            ..Default::default()
        };
        let s = Shared::new(0, calib(), settings);
        let header = Header {
            sender: RobotId::new("b").unwrap(),
            epoch: 1,
            sequence: 0,
        };
        for i in 0..80u64 {
            s.queue_for_peer(
                1,
                Message::new(
                    header.clone(),
                    Body::Route(Route {
                        path: vec![0],
                        subtree: 0,
                        session: i,
                    }),
                ),
            );
            s.queue_for_peer(
                1,
                Message::new(
                    header.clone(),
                    Body::Descriptors(Descriptors {
                        robot: 0,
                        keyframes: i..i + 1,
                        descriptors: Vec::new(),
                    }),
                ),
            );
        }
        let stats = s.stats();
        assert_eq!(stats.for_peer_superseded, 79);
        assert_eq!(
            stats.for_peer_refused, 73,
            "8 waiting: the route and 7 batches"
        );
        let peer = RobotId::new("b").unwrap();
        let mut relay = BackendRelay(s.clone());
        relay.presence(&peer, 1, 1, true);
        let bodies = relay.messages_for(&peer);
        assert_eq!(bodies.len(), 8);
        assert_eq!(
            bodies[0],
            Body::Route(Route {
                path: vec![0],
                subtree: 0,
                session: 79
            })
        );
        let starts: Vec<u64> = bodies[1..]
            .iter()
            .filter_map(|b| match b {
                Body::Descriptors(d) => Some(d.keyframes.start),
                _ => None,
            })
            .collect();
        assert_eq!(starts, (0..7).collect::<Vec<_>>());
    }

    fn nearest_only() -> MatchSettings {
        MatchSettings {
            chain: ChainConfig::top_k_only(1, 0.367),
            ..Default::default()
        }
    }

    #[test]
    fn received_descriptors_go_through_the_candidate_chain() {
        let s = Shared::new(1, calib(), MatchSettings::default());
        for id in 0..10 {
            s.add_descriptor(&descriptor(1, id, &unit(id as usize)))
                .unwrap();
        }
        let peer = RobotId::new("a").unwrap();
        let batch = |ids: &[(u64, usize)]| -> Vec<Descriptor> {
            ids.iter()
                .map(|&(k, u)| Descriptor::quantize(key::symbol(0, k).unwrap(), &unit(u)).unwrap())
                .collect()
        };
        // Robot a's keyframes 5, 6, 7 see b's 3, 4, 5: consecutive keyframes matching
        // consecutive keyframes, all confirmed.
        let m = Places(s.clone()).match_descriptors(&peer, &batch(&[(5, 3), (6, 4), (7, 5)]));
        let pairs: Vec<(u64, u64)> = m
            .iter()
            .map(|m| (key::index(m.query), key::index(m.candidate)))
            .collect();
        assert_eq!(pairs, vec![(5, 3), (6, 4), (7, 5)]);
        assert!(m.iter().all(|m| m.distance < 1e-3));
        // Keyframe 20 looks like b's keyframe 1, but its neighbours look like nothing b
        // has: no packet is asked for it.
        let m = Places(s.clone()).match_descriptors(
            &peer,
            &batch(&[(19, 50), (20, 1), (21, 60), (22, 70), (23, 80)]),
        );
        assert!(m.is_empty(), "{m:?}");
        let stats = s.stats();
        assert_eq!(stats.putative_pairs, 3);
        assert_eq!(
            (
                stats.chain.ranked,
                stats.chain.confirmed,
                stats.chain.unconfirmed
            ),
            (4, 3, 1)
        );
    }

    #[test]
    fn own_loops_are_verified_and_handed_to_the_back_end() {
        // Robot b flies along x (2 m per keyframe), and its keyframes 25..=27 come back to
        // where 2..=4 were: the same views, the same descriptors (a little off).
        let s = Shared::new(1, calib(), MatchSettings::default());
        let pose = |id: u64| {
            let at = if (25..=27).contains(&id) { id - 23 } else { id };
            SE3::translation(2.0 * at as f64, 0.0, 0.0)
        };
        for id in 0..28u64 {
            s.add_keyframe(&keyframe(1, id, &pose(id))).unwrap();
            let v = if (25..=27).contains(&id) {
                let mut v = unit((id - 23) as usize);
                v[100] = 0.05;
                v
            } else {
                unit(id as usize)
            };
            s.add_descriptor(&descriptor(1, id, &v)).unwrap();
        }
        let (_, closures) = s.take_for_backend();
        let pairs: Vec<(u32, u64, u32, u64)> = closures
            .iter()
            .map(|c| (c.robot_a, c.keyframe_a, c.robot_b, c.keyframe_b))
            .collect();
        assert_eq!(pairs, vec![(1, 25, 1, 2), (1, 26, 1, 3), (1, 27, 1, 4)]);
        for c in &closures {
            // The same place: the relative pose is the identity.
            let z = doorslam_geometry::pose_from_array(&c.relative).unwrap();
            assert!(z.translation.vector.norm() < 0.01, "{z:?}");
        }
        let own = s.stats().own_loops;
        assert_eq!((own.verified, own.closures), (3, 3), "{own:?}");
        // Counted apart from inter-robot closures.
        assert_eq!(s.stats().closures_to_backend, 0);
        // Off in the settings: none.
        let off = Shared::new(
            1,
            calib(),
            MatchSettings {
                own_loops: None,
                ..Default::default()
            },
        );
        for id in 0..28u64 {
            off.add_keyframe(&keyframe(1, id, &pose(id))).unwrap();
            off.add_descriptor(&descriptor(1, id, &unit((id % 25) as usize)))
                .unwrap();
        }
        assert!(off.take_for_backend().1.is_empty());
    }

    /// `features_in_memory` 4 over 28 keyframes, with the store: memory never holds more
    /// than 4, yet the own loops onto keyframes 2..=4 (long out of memory) close, a
    /// peer's packet is verified against an old keyframe, and its packet goes out, all
    /// read back from the store. Without a store the old keyframes are forgotten
    /// (counted) and their pairs do not verify.
    #[test]
    fn keyframes_beyond_features_in_memory_are_read_back_from_the_store() {
        let dir = tempfile::tempdir().unwrap();
        let settings = MatchSettings {
            features_in_memory: 4,
            ..Default::default()
        };
        let pose = |id: u64| {
            let at = if (25..=27).contains(&id) { id - 23 } else { id };
            SE3::translation(2.0 * at as f64, 0.0, 0.0)
        };
        let fly = |s: &Shared| {
            for id in 0..28u64 {
                s.add_keyframe(&keyframe(1, id, &pose(id))).unwrap();
                let v = if (25..=27).contains(&id) {
                    let mut v = unit((id - 23) as usize);
                    v[100] = 0.05;
                    v
                } else {
                    unit(id as usize)
                };
                s.add_descriptor(&descriptor(1, id, &v)).unwrap();
                assert!(s.stats().own_features.in_memory <= 4);
            }
        };
        let s = Shared::new(1, calib(), settings.clone());
        s.open_store(&dir.path().join("b").join("team.own"))
            .unwrap();
        fly(&s);
        let f = s.stats().own_features;
        assert_eq!((f.on_disk, f.forgotten, f.load_errors), (28, 0, 0), "{f:?}");
        assert!(f.evicted >= 24 && f.loaded >= 3, "{f:?}");
        assert_eq!(s.keyframes(), 28);
        let (_, closures) = s.take_for_backend();
        let pairs: Vec<(u64, u64)> = closures
            .iter()
            .map(|c| (c.keyframe_a, c.keyframe_b))
            .collect();
        assert_eq!(pairs, vec![(25, 2), (26, 3), (27, 4)]);
        // A peer (robot a) sends its packet of the place of b's keyframe 1, long out of
        // b's memory: verified against the features read back.
        let sa = Shared::new(0, calib(), MatchSettings::default());
        sa.add_keyframe(&keyframe(0, 7, &pose(1))).unwrap();
        let packet = Places(sa)
            .verification_features(key::symbol(0, 7).unwrap())
            .unwrap();
        let m = Match {
            query: key::symbol(1, 1).unwrap(),
            candidate: key::symbol(0, 7).unwrap(),
            distance: 0.1,
        };
        let peer = RobotId::new("a").unwrap();
        let loaded = s.stats().own_features.loaded;
        let closure = PnpVerifier(s.clone()).verify(&peer, &m, &packet).unwrap();
        assert!(closure.relative.se3().translation.vector.norm() < 0.01);
        assert_eq!(s.stats().own_features.loaded, loaded + 1);
        // b's packet of an old keyframe: the one it would have sent when it was new.
        let old = Places(s.clone())
            .verification_features(key::symbol(1, 0).unwrap())
            .unwrap();
        let fresh = Shared::new(1, calib(), MatchSettings::default());
        fresh.add_keyframe(&keyframe(1, 0, &pose(0))).unwrap();
        let want = Places(fresh)
            .verification_features(key::symbol(1, 0).unwrap())
            .unwrap();
        assert_eq!(old, want);
        assert!(s.stats().own_features.in_memory <= 4);

        // No store: what leaves memory is forgotten, and the loops onto it never close.
        let s = Shared::new(1, calib(), settings);
        fly(&s);
        let f = s.stats().own_features;
        assert_eq!((f.in_memory, f.on_disk, f.forgotten), (4, 0, 24), "{f:?}");
        assert!(s.take_for_backend().1.is_empty());
        assert!(PnpVerifier(s.clone()).verify(&peer, &m, &packet).is_none());
    }

    #[test]
    fn verification_recovers_the_relative_pose_in_the_closure_convention() {
        let x_a = SE3::identity();
        let x_b = SE3::from_parts(
            Translation3::new(0.6, -0.1, 0.4),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.08),
        );
        // Robot b's keyframe 5 is the candidate; robot a verifies it against its keyframe 2.
        let sb = Shared::new(1, calib(), MatchSettings::default());
        sb.add_keyframe(&keyframe(1, 5, &x_b)).unwrap();
        let packet = Places(sb.clone())
            .verification_features(key::symbol(1, 5).unwrap())
            .unwrap();
        assert!(packet.features.len() <= MatchSettings::default().max_packet_features);
        let sa = Shared::new(0, calib(), MatchSettings::default());
        sa.add_keyframe(&keyframe(0, 2, &x_a)).unwrap();
        let m = Match {
            query: key::symbol(0, 2).unwrap(),
            candidate: key::symbol(1, 5).unwrap(),
            distance: 0.1,
        };
        let peer = RobotId::new("b").unwrap();
        let closure = PnpVerifier(sa.clone()).verify(&peer, &m, &packet).unwrap();
        assert_eq!((closure.key_a, closure.key_b), (m.query, m.candidate));
        // z ≈ X_a⁻¹ X_b: the back-end's convention for an edge from key_a to key_b.
        let err = closure.relative.se3().inverse() * (x_a.inverse() * x_b);
        assert!(err.translation.vector.norm() < 0.01, "{err:?}");
        assert!(err.rotation.angle() < 0.002, "{err:?}");
        // An unknown own keyframe is a rejection, counted.
        let unknown = Match {
            query: key::symbol(0, 99).unwrap(),
            ..m
        };
        assert!(PnpVerifier(sa.clone())
            .verify(&peer, &unknown, &packet)
            .is_none());
        assert_eq!(sa.stats().rejected["unknown_keyframe"], 1);
    }

    /// A message the relay's envelope cannot carry (only a hostile or broken peer sends
    /// one) is refused by name, not handed on to fail the relay.
    #[test]
    fn the_relay_refuses_a_message_larger_than_its_envelope() {
        let s = Shared::new(0, calib(), MatchSettings::default());
        let mut relay = BackendRelay(s.clone());
        let peer = RobotId::new("bravo").unwrap();
        relay.presence(&peer, 1, 4, true);
        let header = Header {
            sender: peer.clone(),
            epoch: 4,
            sequence: 9,
        };
        let batch = |n: u64| {
            Body::Descriptors(Descriptors {
                robot: 1,
                keyframes: 0..n,
                descriptors: (0..n)
                    .map(|i| Descriptor {
                        key: key::symbol(1, i).unwrap(),
                        scale: 0.01,
                        values: [3; DESCRIPTOR_DIM],
                    })
                    .collect(),
            })
        };
        let big = Message::new(header.clone(), batch(4096)).encode().unwrap();
        assert!(
            big.len() > doorslam_ipc::MAX_ENVELOPE_BYTES
                && big.len() <= doorslam_ipc::wire::MAX_MESSAGE_BYTES,
            "{} bytes",
            big.len()
        );
        s.take_for_backend();
        let refused = relay.receive(&peer, &header, batch(4096)).unwrap_err();
        assert!(refused.0.contains("envelope"), "{refused}");
        assert!(s.take_for_backend().0.is_empty());
        // One that fits goes on.
        relay.receive(&peer, &header, batch(16)).unwrap();
        assert_eq!(s.take_for_backend().0.len(), 1);
    }

    #[test]
    fn the_relay_carries_presence_messages_and_closures() {
        let s = Shared::new(0, calib(), MatchSettings::default());
        let mut relay = BackendRelay(s.clone());
        let peer = RobotId::new("bravo").unwrap();
        let header = Header {
            sender: peer.clone(),
            epoch: 4,
            sequence: 9,
        };
        // Before the peer's Hello, its back-end messages are refused.
        assert!(relay
            .receive(
                &peer,
                &header,
                Body::Hello(Hello {
                    robot: 1,
                    heard: None,
                    base: 0
                })
            )
            .is_err());
        relay.presence(&peer, 1, 4, true);
        relay
            .receive(
                &peer,
                &header,
                Body::Hello(Hello {
                    robot: 1,
                    heard: None,
                    base: 0,
                }),
            )
            .unwrap();
        let closure = LoopClosure {
            key_a: key::symbol(0, 3).unwrap(),
            key_b: key::symbol(1, 8).unwrap(),
            relative: Pose::from_se3(&SE3::identity()).unwrap(),
            information: Information::from_matrix(
                &(doorslam_geometry::TangentMatrix::identity() * 50.0),
            )
            .unwrap(),
            inliers: 40,
        };
        relay.loop_closures(&peer, &[closure]);
        let (envelopes, closures) = s.take_for_backend();
        assert_eq!(envelopes.len(), 2);
        assert_eq!(envelopes[0].event, EnvelopeEvent::PeerPresent);
        assert_eq!((envelopes[0].peer_robot, envelopes[0].epoch), (1, 4));
        assert_eq!(envelopes[1].event, EnvelopeEvent::Message);
        assert_eq!(Message::decode(&envelopes[1].bytes).unwrap().header, header);
        assert_eq!(closures.len(), 1);
        assert_eq!((closures[0].robot_a, closures[0].keyframe_a), (0, 3));
        assert_eq!((closures[0].robot_b, closures[0].keyframe_b), (1, 8));
        // What the back-end queues for robot 1 goes to the peer that said it is robot 1.
        s.queue_for_peer(
            1,
            Message::new(
                header.clone(),
                Body::Hello(Hello {
                    robot: 0,
                    heard: None,
                    base: 0,
                }),
            ),
        );
        assert_eq!(relay.messages_for(&RobotId::new("other").unwrap()).len(), 0);
        assert_eq!(relay.messages_for(&peer).len(), 1);
        assert_eq!(relay.messages_for(&peer).len(), 0);
    }
}
