//! The messages robots exchange, their header, and the encoder/decoder.

use super::backend::{
    read_graph, read_route, read_team_map, write_graph, write_route, write_team_map, Route,
    SeparatorGraph, TeamMap,
};
use super::codec::{Counter, Reader, Sink};
use super::types::{
    read_key, write_key, CompactPose, Descriptor, Information, Pose, RelaxedRotation, RobotId,
    VerificationCamera, VerificationFeature, COMPACT_POSE_MIN_BYTES, DESCRIPTOR_DIM, FEATURE_BYTES,
    INFORMATION_BYTES, POSE_BYTES, RELAXED_ROTATION_BYTES,
};
use super::WireError;
use crate::shm::MAX_KEYFRAME_FEATURES;

/// The wire version this build speaks. A message of any other version is refused with
/// [`WireError::UnknownVersion`]: a layout change bumps it (2: verification features carry
/// the camera, and a disparity instead of a 3-D point).
pub const WIRE_VERSION: u8 = 3;

/// Most descriptors in one [`Descriptors`] batch.
pub const MAX_DESCRIPTORS: usize = 4096;
/// Most pairs in one [`Matches`] message.
pub const MAX_MATCHES: usize = 4096;
/// Most features in one [`VerificationFeatures`] message (a keyframe's maximum).
pub const MAX_FEATURES: usize = MAX_KEYFRAME_FEATURES;
/// Most closures in one [`LoopClosures`] message.
pub const MAX_LOOP_CLOSURES: usize = 1024;
/// Most estimates in one [`PoseEstimates`] message.
pub const MAX_POSE_ESTIMATES: usize = 4096;
/// Most received-ahead ranges in one [`Ack`].
pub const MAX_ACK_RANGES: usize = 64;
/// Longest message a decoder accepts (a full descriptor batch is ~545 kB); checked first.
pub const MAX_MESSAGE_BYTES: usize = 1 << 20;

/// Why a robot byte is refused: robots are numbered below `key::MAX_ROBOTS` (52).
const _: () = assert!(doorslam_geometry::key::MAX_ROBOTS == 52);
pub(crate) const NOT_A_ROBOT: &str = "not a robot number (0..52: 'a'..'z', 'A'..'Z')";

/// Message kinds, the second byte of every message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(u8)]
pub enum Kind {
    Hello = 1,
    Descriptors = 2,
    Matches = 3,
    VerificationFeatures = 4,
    LoopClosures = 5,
    PoseEstimates = 6,
    Ack = 7,
    SeparatorGraph = 8,
    Route = 9,
    TeamMap = 10,
}

impl Kind {
    pub const ALL: [Kind; 10] = [
        Kind::Hello,
        Kind::Descriptors,
        Kind::Matches,
        Kind::VerificationFeatures,
        Kind::LoopClosures,
        Kind::PoseEstimates,
        Kind::Ack,
        Kind::SeparatorGraph,
        Kind::Route,
        Kind::TeamMap,
    ];

    /// Name for logs and the bandwidth ledger.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Hello => "hello",
            Kind::Descriptors => "descriptors",
            Kind::Matches => "matches",
            Kind::VerificationFeatures => "verification_features",
            Kind::LoopClosures => "loop_closures",
            Kind::PoseEstimates => "pose_estimates",
            Kind::Ack => "ack",
            Kind::SeparatorGraph => "separator_graph",
            Kind::Route => "route",
            Kind::TeamMap => "team_map",
        }
    }

    pub fn from_u8(v: u8) -> Option<Kind> {
        Kind::ALL.into_iter().find(|k| *k as u8 == v)
    }
}

/// The header of every message:
///
/// | bytes | field |
/// |---|---|
/// | 1 | version ([`WIRE_VERSION`]) |
/// | 1 | kind ([`Kind`]) |
/// | 1 + n | sender: length n (1–32), then the robot id (`[a-z0-9_-]`) |
/// | varint | epoch |
/// | varint | sequence |
///
/// The sender travels as its config id rather than a robot number: ids are what robots
/// discover each other by, and a number would have to be agreed on first (a stale or
/// misconfigured number would silently attribute data to the wrong robot); it costs
/// 2–33 bytes, amortized over batches. No field holds a time: clocks of different robots
/// never agree, so ordering is by sequence only.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    pub sender: RobotId,
    /// Incremented by the sender each time its team link starts (persisted by the sender);
    /// sequences restart at 0 in each epoch, so a receiver seeing a higher epoch knows the
    /// sender restarted and forgets the sender's old sequences.
    pub epoch: u64,
    /// Per (sender, epoch, kind): 0 for the first message of that kind, then +1 per
    /// message. [`Ack`] acknowledges these.
    pub sequence: u64,
}

/// Announces a robot to a peer at the start of a rendezvous, and starts the sender's
/// sequence session towards the peer's epoch it heard.
///
/// Layout: robot (u8), heard (varint: 0 = no epoch of the peer heard yet, else the epoch
/// + 1), base (varint).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Hello {
    /// The robot's number in multi-robot keys (0 = 'a', < 52): the robot byte of every key
    /// it sends.
    pub robot: u8,
    /// The receiver's epoch this Hello answers (None: none heard yet). A receiver takes
    /// the sender's other messages only after a Hello naming its current epoch: what the
    /// sender sent before it knew that epoch belongs to an older session.
    pub heard: Option<u64>,
    /// Every kind's sequences in that session start here (lower ones are older sessions').
    pub base: u64,
}

/// A batch of place descriptors (rendezvous step 1): those of the sender's keyframes with
/// indices in `keyframes`, in strictly increasing key order. The range says what the batch
/// covers even where a keyframe has no descriptor, so the receiver can acknowledge "every
/// descriptor of keyframes below `keyframes.end`" and the sender resumes from there at the
/// next meeting, whatever was lost or which epoch it was sent in.
///
/// Layout: robot (u8), range start and length (varints), count (varint), then per
/// descriptor the index (first: offset from the range start; then the difference from the
/// previous one, ≥ 1; varint), the scale (f32) and 128 int8 values: 133 bytes for
/// consecutive keyframes.
#[derive(Debug, Clone, PartialEq)]
pub struct Descriptors {
    /// The sender's robot number (0 = 'a'): the robot of every key in the batch.
    pub robot: u8,
    /// Keyframe indices covered, `start..end`.
    pub keyframes: core::ops::Range<u64>,
    pub descriptors: Vec<Descriptor>,
}

/// One putative place match found by the receiver of a descriptor batch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    /// Key of the keyframe whose descriptor was received.
    pub query: u64,
    /// Key of the matcher's own keyframe.
    pub candidate: u64,
    /// Euclidean distance between the two (dequantized) descriptors (finite, ≥ 0).
    pub distance: f32,
}

/// Putative pairs (rendezvous step 2). Layout: count (varint), then per pair the two keys
/// (robot byte + index varint each) and the distance (f32).
#[derive(Debug, Clone, PartialEq)]
pub struct Matches {
    pub matches: Vec<Match>,
}

/// Features of one of the sender's keyframes, for geometric verification of the putative
/// matches that name it (rendezvous step 2). Layout: key, the rectified camera (20 bytes,
/// [`VerificationCamera`]), count (varint), then 38 bytes per feature (see
/// [`VerificationFeature`]). The sender puts its best features first and at most as many
/// as fit its budget (the front-end: 500, 19.1 kB at most with the longest sender id).
#[derive(Debug, Clone, PartialEq)]
pub struct VerificationFeatures {
    pub key: u64,
    pub camera: VerificationCamera,
    pub features: Vec<VerificationFeature>,
}

/// A geometrically verified inter-robot loop closure.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopClosure {
    /// Key of the keyframe of the robot that verified it.
    pub key_a: u64,
    /// Key of the peer's keyframe.
    pub key_b: u64,
    /// `X_a⁻¹ X_b`: pose of keyframe b's camera in keyframe a's.
    pub relative: Pose,
    /// Information of `relative` (rotation first).
    pub information: Information,
    /// PnP-RANSAC inliers that supported it.
    pub inliers: u32,
}

/// Accepted loop closures (rendezvous step 3). Layout: count (varint), then per closure
/// two keys, the pose (28 bytes), the information (46 bytes) and the inliers (varint).
#[derive(Debug, Clone, PartialEq)]
pub struct LoopClosures {
    pub closures: Vec<LoopClosure>,
}

/// Stage of the distributed back-end: the two stages of distributed Gauss-Seidel, then
/// the nonlinear refinement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
#[repr(u8)]
pub enum Stage {
    /// Rotation estimation (chordal relaxation): estimates are [`RelaxedRotation`]s.
    Rotation = 0,
    /// Full poses given the rotation estimate: estimates are [`CompactPose`]s.
    Pose = 1,
    /// Nonlinear refinement (block-coordinate descent on the full cost): [`CompactPose`]s.
    Refine = 2,
}

impl Stage {
    fn from_u8(v: u8) -> Option<Stage> {
        [Stage::Rotation, Stage::Pose, Stage::Refine]
            .into_iter()
            .find(|s| *s as u8 == v)
    }
}

/// The value of one separator estimate: what its stage estimates.
#[derive(Debug, Clone, PartialEq)]
pub enum Estimate {
    Rotation(RelaxedRotation),
    Pose(CompactPose),
}

/// One separator pose estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseEstimate {
    /// Key of the pose (the sender's robot: a robot sends only its own separators).
    pub key: u64,
    /// In the frame of the message's `anchor` robot; must match the message's stage.
    pub value: Estimate,
}

/// Bit of [`PoseEstimates::flags`]: the sender's estimate stopped changing in this stage.
pub const ESTIMATES_CONVERGED: u8 = 1;

/// Bits of [`PoseEstimates::flags`] that say how the solve behind the estimates stopped
/// ([`SolveStop`], 0: not said). The flags byte is sent anyway, so the team's solver tells
/// every robot why its solve stopped at no byte's cost.
pub const ESTIMATES_STOP_MASK: u8 = 0b1_1110;
const ESTIMATES_STOP_SHIFT: u32 = 1;

/// How the solve that produced a message's estimates stopped: the back-end solver's stop
/// reasons, as the condensed method's team solver sends them down with the separators.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum SolveStop {
    ConvergedSmallCost = 1,
    ConvergedSmallDecrease = 2,
    ConvergedSmallPredictedDecrease = 3,
    MaxIterations = 4,
    NoDecrease = 5,
    NonFiniteStep = 6,
    Diverged = 7,
    GncNotSettled = 8,
    NegativeCost = 9,
}

impl SolveStop {
    const ALL: [SolveStop; 9] = [
        SolveStop::ConvergedSmallCost,
        SolveStop::ConvergedSmallDecrease,
        SolveStop::ConvergedSmallPredictedDecrease,
        SolveStop::MaxIterations,
        SolveStop::NoDecrease,
        SolveStop::NonFiniteStep,
        SolveStop::Diverged,
        SolveStop::GncNotSettled,
        SolveStop::NegativeCost,
    ];

    /// The flags bits that carry `stop` (0 for none).
    pub fn flags(stop: Option<SolveStop>) -> u8 {
        stop.map_or(0, |s| (s as u8) << ESTIMATES_STOP_SHIFT)
    }

    /// The stop carried by `flags`; `Err(code)` for a code that names no stop.
    pub fn from_flags(flags: u8) -> Result<Option<SolveStop>, u8> {
        let code = (flags & ESTIMATES_STOP_MASK) >> ESTIMATES_STOP_SHIFT;
        if code == 0 {
            return Ok(None);
        }
        Self::ALL
            .into_iter()
            .find(|s| *s as u8 == code)
            .map(Some)
            .ok_or(code)
    }
}

/// Checks the flags byte of estimates: known bits, and a stop code that names a stop.
fn check_estimate_flags(flags: u8, offset: usize) -> Result<(), WireError> {
    if flags & !(ESTIMATES_CONVERGED | ESTIMATES_STOP_MASK) != 0 {
        return Err(WireError::invalid(
            "estimate flags",
            offset,
            "unknown bits set",
        ));
    }
    SolveStop::from_flags(flags).map(drop).map_err(|code| {
        WireError::invalid(
            "estimate flags",
            offset,
            format!("solve stop code {code} names no stop (1-9)"),
        )
    })
}

/// Separator estimates for one round of the distributed back-end (step 4).
///
/// Layout: optimization (varint), round (varint), stage (u8), flags (u8), anchor (u8),
/// robot (u8), count (varint), then per estimate the gap from the previous index (the
/// first: the index itself; varint, ≥ 1 after the first) and its value: 18 bytes for a
/// relaxed rotation, 13–25 for a compact pose. Keys are the `robot`'s, strictly ascending,
/// so a key costs 1–2 bytes instead of 2–4.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseEstimates {
    /// The sender's initialization generation: incremented each time it re-initializes
    /// (a new anchor, a restart), so estimates of an abandoned frame are never mixed in.
    pub optimization: u64,
    /// The sender's iteration within the stage, from 0.
    pub round: u64,
    pub stage: Stage,
    /// [`ESTIMATES_CONVERGED`] and the solve's stop ([`ESTIMATES_STOP_MASK`],
    /// [`SolveStop::flags`]); the top three bits must be 0.
    pub flags: u8,
    /// The robot (0 = 'a') whose first pose fixes the gauge of these estimates: the lowest
    /// robot of the sender's connected team.
    pub anchor: u8,
    /// Ascending keys of one robot, values of the stage's kind.
    pub estimates: Vec<PoseEstimate>,
}

/// Acknowledges the messages of one kind received from the peer in one of its epochs.
///
/// Layout: epoch (varint), kind (u8), next (varint), count (varint), then per range the
/// gap from the end of the previous range (or from `next`) and its length (varints, ≥ 1).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ack {
    /// The acknowledged peer's epoch.
    pub epoch: u64,
    pub kind: Kind,
    /// Every sequence below `next` was received (0: none yet).
    pub next: u64,
    /// Further received sequences `start..end`, ascending, disjoint, not touching `next`
    /// or each other (so the encoding is unique).
    pub received: Vec<core::ops::Range<u64>>,
}

/// A message body: one of the kinds.
#[derive(Debug, Clone, PartialEq)]
pub enum Body {
    Hello(Hello),
    Descriptors(Descriptors),
    Matches(Matches),
    VerificationFeatures(VerificationFeatures),
    LoopClosures(LoopClosures),
    PoseEstimates(PoseEstimates),
    Ack(Ack),
    SeparatorGraph(SeparatorGraph),
    Route(Route),
    TeamMap(TeamMap),
}

impl Body {
    pub fn kind(&self) -> Kind {
        match self {
            Body::Hello(_) => Kind::Hello,
            Body::Descriptors(_) => Kind::Descriptors,
            Body::Matches(_) => Kind::Matches,
            Body::VerificationFeatures(_) => Kind::VerificationFeatures,
            Body::LoopClosures(_) => Kind::LoopClosures,
            Body::PoseEstimates(_) => Kind::PoseEstimates,
            Body::Ack(_) => Kind::Ack,
            Body::SeparatorGraph(_) => Kind::SeparatorGraph,
            Body::Route(_) => Kind::Route,
            Body::TeamMap(_) => Kind::TeamMap,
        }
    }
}

/// One inter-robot message: header and body.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    pub header: Header,
    pub body: Body,
}

pub(crate) fn check_count(
    s: &impl Sink,
    field: &'static str,
    n: usize,
    max: usize,
) -> Result<(), WireError> {
    if n > max {
        return Err(WireError::TooLong {
            field,
            offset: s.offset(),
            len: n as u64,
            max: max as u64,
        });
    }
    Ok(())
}

impl Message {
    pub fn new(header: Header, body: impl Into<Body>) -> Self {
        Self {
            header,
            body: body.into(),
        }
    }

    pub fn kind(&self) -> Kind {
        self.body.kind()
    }

    /// The encoded message. Refuses what the decoder would refuse (counts above the
    /// limits, keys without a robot, unordered descriptors or ranges, bad distances).
    pub fn encode(&self) -> Result<Vec<u8>, WireError> {
        let mut out = Vec::with_capacity(self.encoded_len());
        self.write(&mut out)?;
        Ok(out)
    }

    /// Exactly `encode().len()` for a message that encodes, computed without allocating
    /// (the encoder itself, writing to a byte counter).
    pub fn encoded_len(&self) -> usize {
        let mut c = Counter::default();
        // A message that does not encode has no length; the bytes up to the error are
        // as good as any other answer and never used.
        let _ = self.write(&mut c);
        c.0
    }

    fn write(&self, s: &mut impl Sink) -> Result<(), WireError> {
        s.u8(WIRE_VERSION);
        s.u8(self.kind() as u8);
        self.header.sender.write(s);
        s.varint(self.header.epoch);
        s.varint(self.header.sequence);
        match &self.body {
            Body::Hello(h) => {
                if h.robot >= doorslam_geometry::key::MAX_ROBOTS {
                    return Err(WireError::invalid("hello robot", s.offset(), NOT_A_ROBOT));
                }
                s.u8(h.robot);
                match h.heard {
                    None => s.varint(0),
                    Some(e) => {
                        let v = e.checked_add(1).ok_or_else(|| {
                            WireError::invalid("hello heard", s.offset(), "epoch at u64::MAX")
                        })?;
                        s.varint(v);
                    }
                }
                s.varint(h.base);
            }
            Body::Descriptors(d) => write_descriptors(s, d)?,
            Body::Matches(m) => {
                check_count(s, "match count", m.matches.len(), MAX_MATCHES)?;
                s.varint(m.matches.len() as u64);
                for p in &m.matches {
                    write_key(s, "match query", p.query)?;
                    write_key(s, "match candidate", p.candidate)?;
                    if !(p.distance.is_finite() && p.distance >= 0.0) {
                        return Err(WireError::invalid(
                            "match distance",
                            s.offset(),
                            "not finite and >= 0",
                        ));
                    }
                    s.f32(p.distance);
                }
            }
            Body::VerificationFeatures(v) => {
                write_key(s, "features key", v.key)?;
                // The fields are public: refuse on the way out what the decoder would.
                v.camera.check(s.offset())?;
                v.camera.write(s);
                check_count(s, "feature count", v.features.len(), MAX_FEATURES)?;
                s.varint(v.features.len() as u64);
                for f in &v.features {
                    f.write(s);
                }
            }
            Body::LoopClosures(l) => write_closures(s, &l.closures)?,
            Body::SeparatorGraph(g) => write_graph(s, g)?,
            Body::Route(r) => write_route(s, r)?,
            Body::TeamMap(m) => write_team_map(s, m)?,
            Body::PoseEstimates(p) => write_estimates(s, p)?,
            Body::Ack(a) => write_ack(s, a)?,
        }
        Ok(())
    }

    /// Decodes one message from untrusted bytes: version first (any other version is
    /// [`WireError::UnknownVersion`]), every count checked against its limit and against
    /// the bytes left before anything is allocated, every value checked (poses by
    /// `pose_from_array`, information by `check_information`, keys by `key::symbol`), and
    /// no byte left over.
    pub fn decode(bytes: &[u8]) -> Result<Message, WireError> {
        if bytes.len() > MAX_MESSAGE_BYTES {
            return Err(WireError::TooLong {
                field: "message",
                offset: 0,
                len: bytes.len() as u64,
                max: MAX_MESSAGE_BYTES as u64,
            });
        }
        let mut r = Reader::new(bytes);
        let version = r.u8("version")?;
        if version != WIRE_VERSION {
            return Err(WireError::unknown_version(version));
        }
        let kind = r.u8("kind")?;
        let kind = Kind::from_u8(kind).ok_or(WireError::UnknownKind { found: kind })?;
        let header = Header {
            sender: RobotId::read(&mut r)?,
            epoch: r.varint("epoch")?,
            sequence: r.varint("sequence")?,
        };
        let body = match kind {
            Kind::Hello => {
                let offset = r.offset();
                let robot = r.u8("hello robot")?;
                if robot >= doorslam_geometry::key::MAX_ROBOTS {
                    return Err(WireError::invalid("hello robot", offset, NOT_A_ROBOT));
                }
                let heard = r.varint("hello heard")?.checked_sub(1);
                let base = r.varint("hello base")?;
                Body::Hello(Hello { robot, heard, base })
            }
            Kind::Descriptors => Body::Descriptors(read_descriptors(&mut r)?),
            Kind::Matches => {
                let n = r.count("match count", MAX_MATCHES, 2 * 2 + 4)?;
                let mut matches = Vec::with_capacity(n);
                for _ in 0..n {
                    let query = read_key(&mut r, "match query")?;
                    let candidate = read_key(&mut r, "match candidate")?;
                    let offset = r.offset();
                    let distance = r.f32("match distance")?;
                    if !(distance.is_finite() && distance >= 0.0) {
                        return Err(WireError::invalid(
                            "match distance",
                            offset,
                            "not finite and >= 0",
                        ));
                    }
                    matches.push(Match {
                        query,
                        candidate,
                        distance,
                    });
                }
                Body::Matches(Matches { matches })
            }
            Kind::VerificationFeatures => {
                let key = read_key(&mut r, "features key")?;
                let camera = VerificationCamera::read(&mut r)?;
                let n = r.count("feature count", MAX_FEATURES, FEATURE_BYTES)?;
                let mut features = Vec::with_capacity(n);
                for _ in 0..n {
                    features.push(VerificationFeature::read(&mut r)?);
                }
                Body::VerificationFeatures(VerificationFeatures {
                    key,
                    camera,
                    features,
                })
            }
            Kind::LoopClosures => Body::LoopClosures(LoopClosures {
                closures: read_closures(&mut r)?,
            }),
            Kind::SeparatorGraph => Body::SeparatorGraph(read_graph(&mut r)?),
            Kind::Route => Body::Route(read_route(&mut r)?),
            Kind::TeamMap => Body::TeamMap(read_team_map(&mut r)?),
            Kind::PoseEstimates => Body::PoseEstimates(read_estimates(&mut r)?),
            Kind::Ack => Body::Ack(read_ack(&mut r)?),
        };
        r.finish()?;
        Ok(Message { header, body })
    }
}

fn write_closures(s: &mut impl Sink, closures: &[LoopClosure]) -> Result<(), WireError> {
    check_count(s, "closure count", closures.len(), MAX_LOOP_CLOSURES)?;
    s.varint(closures.len() as u64);
    for c in closures {
        write_key(s, "closure key a", c.key_a)?;
        write_key(s, "closure key b", c.key_b)?;
        c.relative.write(s);
        c.information.write(s);
        s.varint(u64::from(c.inliers));
    }
    Ok(())
}

fn read_closures(r: &mut Reader<'_>) -> Result<Vec<LoopClosure>, WireError> {
    let min = 2 * 2 + POSE_BYTES + INFORMATION_BYTES + 1;
    let n = r.count("closure count", MAX_LOOP_CLOSURES, min)?;
    let mut closures = Vec::with_capacity(n);
    for _ in 0..n {
        let key_a = read_key(r, "closure key a")?;
        let key_b = read_key(r, "closure key b")?;
        let relative = Pose::read(r, "closure pose")?;
        let information = Information::read(r, "closure information")?;
        let offset = r.offset();
        let inliers = r.varint("closure inliers")?;
        let inliers = u32::try_from(inliers).map_err(|_| WireError::TooLong {
            field: "closure inliers",
            offset,
            len: inliers,
            max: u64::from(u32::MAX),
        })?;
        closures.push(LoopClosure {
            key_a,
            key_b,
            relative,
            information,
            inliers,
        });
    }
    Ok(closures)
}

fn write_estimates(s: &mut impl Sink, p: &PoseEstimates) -> Result<(), WireError> {
    s.varint(p.optimization);
    s.varint(p.round);
    s.u8(p.stage as u8);
    check_estimate_flags(p.flags, s.offset())?;
    s.u8(p.flags);
    if p.anchor >= doorslam_geometry::key::MAX_ROBOTS {
        return Err(WireError::invalid(
            "estimate anchor",
            s.offset(),
            NOT_A_ROBOT,
        ));
    }
    s.u8(p.anchor);
    let robot = match p.estimates.first() {
        Some(e) => doorslam_geometry::key::robot(e.key).ok_or_else(|| {
            WireError::invalid("estimate key", s.offset(), "not a multi-robot key")
        })?,
        None => 0,
    };
    s.u8(robot);
    check_count(s, "estimate count", p.estimates.len(), MAX_POSE_ESTIMATES)?;
    s.varint(p.estimates.len() as u64);
    let mut previous: Option<u64> = None;
    for e in &p.estimates {
        if doorslam_geometry::key::robot(e.key) != Some(robot) {
            return Err(WireError::invalid(
                "estimate key",
                s.offset(),
                "keys of more than one robot in one message",
            ));
        }
        let index = doorslam_geometry::key::index(e.key);
        let gap = match previous {
            None => Some(index),
            Some(prev) => index.checked_sub(prev).filter(|&g| g > 0),
        };
        let gap = gap.ok_or_else(|| {
            WireError::invalid("estimate key", s.offset(), "keys not strictly ascending")
        })?;
        previous = Some(index);
        s.varint(gap);
        match (&e.value, p.stage) {
            (Estimate::Rotation(r), Stage::Rotation) => r.write(s),
            (Estimate::Pose(q), Stage::Pose | Stage::Refine) => q.write(s),
            _ => {
                return Err(WireError::invalid(
                    "estimate value",
                    s.offset(),
                    "value kind does not match the stage",
                ))
            }
        }
    }
    Ok(())
}

fn read_estimates(r: &mut Reader<'_>) -> Result<PoseEstimates, WireError> {
    let optimization = r.varint("optimization")?;
    let round = r.varint("round")?;
    let offset = r.offset();
    let stage = r.u8("stage")?;
    let stage = Stage::from_u8(stage).ok_or_else(|| {
        WireError::invalid(
            "stage",
            offset,
            format!("{stage} is not 0 (rotation), 1 (pose) or 2 (refine)"),
        )
    })?;
    let offset = r.offset();
    let flags = r.u8("estimate flags")?;
    check_estimate_flags(flags, offset)?;
    let offset = r.offset();
    let anchor = r.u8("estimate anchor")?;
    if anchor >= doorslam_geometry::key::MAX_ROBOTS {
        return Err(WireError::invalid("estimate anchor", offset, NOT_A_ROBOT));
    }
    let offset = r.offset();
    let robot = r.u8("estimate robot")?;
    if robot >= doorslam_geometry::key::MAX_ROBOTS {
        return Err(WireError::invalid("estimate robot", offset, NOT_A_ROBOT));
    }
    let min = 1 + match stage {
        Stage::Rotation => RELAXED_ROTATION_BYTES,
        Stage::Pose | Stage::Refine => COMPACT_POSE_MIN_BYTES,
    };
    let count_at = r.offset();
    let n = r.count("estimate count", MAX_POSE_ESTIMATES, min)?;
    if n == 0 && robot != 0 {
        // The robot byte names the keys' robot; without keys it is 0, so the encoding
        // stays canonical.
        return Err(WireError::invalid(
            "estimate robot",
            count_at - 1,
            "must be 0 when no estimate follows",
        ));
    }
    let mut estimates = Vec::with_capacity(n);
    let mut index: Option<u64> = None;
    for _ in 0..n {
        let offset = r.offset();
        let gap = r.varint("estimate key")?;
        let next = match index {
            None => Some(gap),
            Some(prev) => prev.checked_add(gap).filter(|_| gap > 0),
        };
        let key = next
            .ok_or_else(|| {
                WireError::invalid("estimate key", offset, "keys not strictly ascending")
            })
            .and_then(|i| {
                doorslam_geometry::key::symbol(robot, i)
                    .map_err(|e| WireError::invalid("estimate key", offset, e))
            })?;
        index = next;
        let value = match stage {
            Stage::Rotation => Estimate::Rotation(RelaxedRotation::read(r, "estimate rotation")?),
            Stage::Pose | Stage::Refine => Estimate::Pose(CompactPose::read(r, "estimate pose")?),
        };
        estimates.push(PoseEstimate { key, value });
    }
    Ok(PoseEstimates {
        optimization,
        round,
        stage,
        flags,
        anchor,
        estimates,
    })
}

fn write_descriptors(s: &mut impl Sink, d: &Descriptors) -> Result<(), WireError> {
    let range = &d.keyframes;
    if d.robot >= doorslam_geometry::key::MAX_ROBOTS
        || range.end < range.start
        || range.end > doorslam_geometry::key::MAX_INDEX + 1
    {
        return Err(WireError::invalid(
            "descriptor range",
            s.offset(),
            "robot not a robot number (0..52), or not a range of key indices",
        ));
    }
    s.u8(d.robot);
    s.varint(range.start);
    s.varint(range.end - range.start);
    check_count(s, "descriptor count", d.descriptors.len(), MAX_DESCRIPTORS)?;
    s.varint(d.descriptors.len() as u64);
    let mut previous: Option<u64> = None;
    for e in &d.descriptors {
        let index = doorslam_geometry::key::index(e.key);
        let step = match previous {
            None => index.checked_sub(range.start),
            Some(p) => index.checked_sub(p).filter(|&step| step > 0),
        };
        let (Some(step), true) = (
            step,
            doorslam_geometry::key::robot(e.key) == Some(d.robot) && range.contains(&index),
        ) else {
            return Err(WireError::invalid(
                "descriptor key",
                s.offset(),
                "keys must be of the batch's robot, in its range, strictly increasing",
            ));
        };
        s.varint(step);
        previous = Some(index);
        if !(e.scale.is_finite() && e.scale >= 0.0) {
            return Err(WireError::invalid(
                "descriptor scale",
                s.offset(),
                "not finite and >= 0",
            ));
        }
        s.f32(e.scale);
        s.put(&e.values.map(|v| v as u8));
    }
    Ok(())
}

fn read_descriptors(r: &mut Reader<'_>) -> Result<Descriptors, WireError> {
    let offset = r.offset();
    let robot = r.u8("descriptor robot")?;
    if robot >= doorslam_geometry::key::MAX_ROBOTS {
        return Err(WireError::invalid("descriptor robot", offset, NOT_A_ROBOT));
    }
    let offset = r.offset();
    let start = r.varint("descriptor range")?;
    let len = r.varint("descriptor range")?;
    let end = start
        .checked_add(len)
        .filter(|&end| end <= doorslam_geometry::key::MAX_INDEX + 1)
        .ok_or_else(|| {
            WireError::invalid("descriptor range", offset, "beyond the largest key index")
        })?;
    let n = r.count("descriptor count", MAX_DESCRIPTORS, 1 + 4 + DESCRIPTOR_DIM)?;
    let mut descriptors = Vec::with_capacity(n);
    let mut index = start;
    for i in 0..n {
        let offset = r.offset();
        let step = r.varint("descriptor key")?;
        match index.checked_add(step) {
            Some(next) if next < end && (i == 0 || step > 0) => index = next,
            _ => {
                return Err(WireError::invalid(
                    "descriptor key",
                    offset,
                    "keys must be in the batch's range, strictly increasing",
                ))
            }
        }
        let key = doorslam_geometry::key::symbol(robot, index)
            .map_err(|e| WireError::invalid("descriptor key", offset, e))?;
        let offset = r.offset();
        let scale = r.f32("descriptor scale")?;
        if !(scale.is_finite() && scale >= 0.0) {
            return Err(WireError::invalid(
                "descriptor scale",
                offset,
                "not finite and >= 0",
            ));
        }
        let values = r
            .array::<DESCRIPTOR_DIM>("descriptor values")?
            .map(|b| b as i8);
        descriptors.push(Descriptor { key, scale, values });
    }
    Ok(Descriptors {
        robot,
        keyframes: start..end,
        descriptors,
    })
}

fn write_ack(s: &mut impl Sink, a: &Ack) -> Result<(), WireError> {
    s.varint(a.epoch);
    s.u8(a.kind as u8);
    s.varint(a.next);
    check_count(s, "ack range count", a.received.len(), MAX_ACK_RANGES)?;
    s.varint(a.received.len() as u64);
    let mut end = a.next;
    for range in &a.received {
        // Each range starts past a gap of at least one missing sequence and is non-empty.
        if range.start <= end || range.end <= range.start {
            return Err(WireError::invalid(
                "ack range",
                s.offset(),
                "ranges must be ascending, disjoint, non-empty and not touch",
            ));
        }
        s.varint(range.start - end);
        s.varint(range.end - range.start);
        end = range.end;
    }
    Ok(())
}

fn read_ack(r: &mut Reader<'_>) -> Result<Ack, WireError> {
    let epoch = r.varint("ack epoch")?;
    let offset = r.offset();
    let kind = r.u8("ack kind")?;
    let kind = Kind::from_u8(kind)
        .ok_or_else(|| WireError::invalid("ack kind", offset, format!("unknown kind {kind}")))?;
    let next = r.varint("ack next")?;
    let n = r.count("ack range count", MAX_ACK_RANGES, 2)?;
    let mut received = Vec::with_capacity(n);
    let mut end = next;
    for _ in 0..n {
        let offset = r.offset();
        let gap = r.varint("ack range")?;
        let len = r.varint("ack range")?;
        let start = end.checked_add(gap);
        let stop = start.and_then(|s| s.checked_add(len));
        match (start, stop) {
            (Some(start), Some(stop)) if gap > 0 && len > 0 => {
                received.push(start..stop);
                end = stop;
            }
            _ => {
                return Err(WireError::invalid(
                    "ack range",
                    offset,
                    "empty, touching or overflowing range",
                ))
            }
        }
    }
    Ok(Ack {
        epoch,
        kind,
        next,
        received,
    })
}

macro_rules! into_body {
    ($($t:ident),*) => {$(
        impl From<$t> for Body {
            fn from(b: $t) -> Body {
                Body::$t(b)
            }
        }
    )*};
}
into_body!(
    Hello,
    Descriptors,
    Matches,
    VerificationFeatures,
    LoopClosures,
    PoseEstimates,
    Ack,
    SeparatorGraph,
    Route,
    TeamMap
);
