//! Distributed pose-graph optimization: each robot optimizes its own trajectory and
//! exchanges only the estimates of its separator poses (poses touched by inter-robot loop
//! closures), Choudhary et al. 2017's two-stage distributed Gauss-Seidel as DOOR-SLAM
//! uses it (paper §III-C), followed by a distributed nonlinear refinement.
//!
//! One [`Agent`] per robot, with no networking inside: the caller moves the messages it
//! returns ([`Agent::messages_for`]) to the neighbour's [`Agent::receive`] by any
//! transport (the team link, or [`runner`]'s emulated link), and calls [`Agent::step`]
//! when it wants the robot to iterate. Messages are the team's wire messages
//! (`PoseEstimates` and `Ack`), so every byte is the encoded size.
//!
//! ## The stages, per robot
//! 1. **Rotations** (chordal relaxation): one step solves the robot's rotation block of
//!    `Σ κ ‖Rⱼ − Rᵢ Zᵢⱼ‖²_F` exactly with the neighbours' latest relaxed rotations fixed
//!    (block Gauss-Seidel), over-relaxed by γ; until the change of the robot's relaxed
//!    rotations (Frobenius norm over all its poses) is below `rotation_change`.
//! 2. **Poses**: rotations projected onto SO(3) and fixed, one step solves the translation
//!    block of `Σ τ ‖tⱼ − tᵢ − Rᵢ tᵢⱼ‖²` with the neighbours' latest translations fixed;
//!    until the change is below `pose_change`. (The reference linearizes the full pose at
//!    the rotation estimate with zero translation, where rotation and translation
//!    decouple: its translation system is this one, and the rotation correction it adds
//!    is left to stage 3 here.)
//! 3. **Refinement**: block-coordinate descent on the full nonlinear cost — each step runs
//!    the back-end's Levenberg-Marquardt on the robot's poses with the neighbours' latest
//!    poses fixed (the exact cost, not a linearization), until the change is below
//!    `refine_change`. The two linear stages are only as accurate as the chordal
//!    relaxation; this stage is what reaches the centralized optimum.
//!
//! ## Gauge and flagged initialization
//! The robot with the lowest id of a connected team anchors the gauge (its first pose is
//! fixed where its odometry put it). Nobody knows the team: a robot takes itself as the
//! anchor only while no robot it shares a closure with has a lower id, and every message
//! names its sender's anchor, so a lower anchor spreads through the team and a robot that
//! hears of one re-initializes in that frame. A robot sends estimates only once they are
//! in its anchor's frame (it holds the gauge, or solved with a neighbour's estimates of
//! that frame), so neighbours never mix frames; a robot without such estimates waits.
//! This is the reference's "flagged initialization", without a fixed robot order.
//!
//! ## Messages and loss
//! A robot sends a neighbour only the separators it shares closures with, and only those
//! whose estimate moved by more than `send_rotation` / `send_pose` from what the
//! neighbour is known to hold. Each message is acknowledged (`Ack` of kind
//! `PoseEstimates`); a message not acknowledged when a later one was, or after
//! `resend_after` (seconds), is taken as lost and its values become due again. So a dropped
//! message costs a resend, never a stale neighbour estimate forever; a robot out of range
//! keeps the last estimates it received and resumes when it returns. Stale (older
//! sequence or generation), out-of-order and malformed messages are ignored or refused
//! without touching the estimate. Nothing assumes clocks agree: order is by the sender's
//! epoch and sequence.

pub mod condensed;
mod link;
pub mod local;
mod map;
pub mod runner;
mod team;

pub use map::TeamTrajectory;

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

use link::{Arrival, Received};

use nalgebra::{Matrix3, Translation3, Vector3};

use crate::graph::EdgeError;
use crate::init::isotropic_weights;
use crate::solver::{SolveError, SolverOptions};
use doorslam_geometry::information::{check_information, InformationCheck, InformationError};
use doorslam_geometry::{key, LieGroup, TangentMatrix, SE3, SO3};
use doorslam_ipc::wire::{
    Ack, Body, CompactPose, Estimate, Header, Kind, Message, PoseEstimate, PoseEstimates,
    QuantizeError, RelaxedRotation, RobotId, Stage, ESTIMATES_CONVERGED, MAX_POSE_ESTIMATES,
};

use local::{Fixed, OwnClosure, OwnEdge};

/// The largest diagonal entry of an information matrix the distributed back-end takes (own
/// edges, closures, a teammate's condensed graph): a standard deviation of a micrometre or
/// a microradian, finer than any sensor measures. A larger one is no measurement, and next
/// to real ones (10²–10⁶) it leaves the team's solve a system that does not factor: one
/// teammate's edge of information 10³⁰ would stop the team's solver at every step.
pub const MAX_INFORMATION: f64 = 1e12;

/// Failures of the distributed back-end.
#[derive(Debug, thiserror::Error)]
pub enum DpgoError {
    #[error("pose {key}: not a pose of robot {robot}")]
    NotOwn { key: String, robot: u8 },
    #[error("pose {0} has no robot letter: the distributed back-end needs multi-robot keys (GTSAM symbols, robot 'a' = 0)")]
    NoRobot(String),
    #[error("pose {0} is not known: add it before its edges")]
    UnknownPose(String),
    #[error("pose {key} is added after {last}: add a robot's poses in index order")]
    OutOfOrder { key: String, last: String },
    #[error("pose {0} is added twice")]
    DuplicatePose(String),
    #[error(
        "edge {from} -> {to}: both poses are this robot's: add it as odometry, not as a closure"
    )]
    NotInterRobot { from: String, to: String },
    #[error("edge {from} -> {to}: {source}")]
    Information {
        from: String,
        to: String,
        #[source]
        source: InformationError,
    },
    #[error("edge {from} -> {to}: information {value:e} on the diagonal, beyond {MAX_INFORMATION:e} (a micrometre / microradian)")]
    ImplausibleInformation {
        from: String,
        to: String,
        value: f64,
    },
    #[error(transparent)]
    Edge(#[from] EdgeError),
    #[error(transparent)]
    Solve(#[from] SolveError),
    #[error("estimate of {key} cannot be sent: {source}")]
    Quantize {
        key: String,
        #[source]
        source: QuantizeError,
    },
    #[error("PCM: {0}")]
    Pcm(String),
    #[error("message from robot {from}: {reason}")]
    BadMessage { from: u8, reason: String },
}

/// Options of an [`Agent`]. The defaults are tuned on the developer data (see
/// BENCHMARKS.md); [`AgentOptions::paper`] gives DOOR-SLAM's KITTI thresholds.
#[derive(Debug, Clone, PartialEq)]
pub struct AgentOptions {
    /// Over-relaxation γ of the two linear stages (1 = plain Gauss-Seidel) where each
    /// robot solves with its neighbours' estimates of the same round (the runner's direct
    /// link: Gauss-Seidel order).
    pub gamma: f64,
    /// γ of the two linear stages over a link that delivers estimates a round late or
    /// more (`link_delivers`: the team link, every robot's): there every robot solves at
    /// once on its neighbours' previous estimates — block Jacobi, not Gauss-Seidel — and
    /// two robots tied by closures, each moving all the way to the other's old estimate,
    /// swap places every step (on KITTI 00 a 350 m two-cycle, χ² 1e6 after 500 rounds:
    /// BENCHMARKS.md, "Where DGS fails on KITTI 00"). Half a step meets in the middle,
    /// which removes that two-cycle.
    pub async_gamma: f64,
    /// Over such a link, step fully (γ 1) and take `async_gamma` only on a step that
    /// reverses this robot's previous one (their dot product is negative): the swap of a
    /// two-cycle reverses every step, while a robot moving steadily towards its fixed
    /// point keeps its full steps; once a step reversed, the rest of the stage is damped
    /// (alternating full and half steps let KITTI 00's swap grow back). False (the
    /// default): `async_gamma` on every step. Measured over 500 rounds (BENCHMARKS.md,
    /// "Damped only after a reversal"): better on distributed_mapper's 4- and 9-robot
    /// teams and both KITTI 00 splits, worse on the held-out 16- and 25-robot teams.
    pub damp_on_reversal: bool,
    /// Stage 1 ends when the robot's relaxed rotations change by less than this
    /// (Frobenius norm over all its poses).
    pub rotation_change: f64,
    /// Stage 2 ends when its translations change by less than this (m, norm over poses).
    pub pose_change: f64,
    /// Stage 3 converges when its poses change by less than this (norm over poses of
    /// translation (m) and rotation (rad) change).
    pub refine_change: f64,
    /// A separator's relaxed rotation is resent when it moved more than this (Frobenius).
    pub send_rotation: f64,
    /// A separator's pose is resent when it moved more than this (m + rad).
    pub send_pose: f64,
    /// Time after which an unacknowledged message is taken as lost. Every timeout is
    /// time on the clock [`Agent::step`] is given, not a count of steps: on a robot a step
    /// is one back-end loop turn, taken as often as there is work, so a step count would
    /// mean anything from milliseconds to seconds.
    pub resend_after: Duration,
    /// How long a robot that converged in a stage waits for present neighbours that have
    /// not (yet) sent anything in its frame before it moves on without them (time summed
    /// over its converged steps); the condensed method's solver waits twice this for the
    /// graphs of robots that route to it.
    pub patience: Duration,
    /// Time (summed over the stage's solved steps) after which a stage ends even if it
    /// has not converged (the next stage starts from where it is; the refinement
    /// corrects it).
    pub max_stage: Duration,
    /// Levenberg-Marquardt iterations per refinement step.
    pub refine_iterations: usize,
    /// Nesterov momentum on every stage's block updates, restarted whenever the change
    /// grows (plain Gauss-Seidel / block-coordinate descent when false).
    pub momentum: bool,
    /// How the team's problem is solved.
    pub method: Method,
    /// PCM on the team's inter-robot closures before each solve (condensed method; no
    /// extra messages), or none (closures were checked before).
    pub pcm: Option<condensed::PcmSettings>,
    /// Condensed method: a chain segment is condensed again and sent when the model the
    /// team holds would cost more χ² at the current estimate (`condensed::model_change`)
    /// than this fraction of the robot's own χ² per segment.
    pub relinearize_fraction: f64,
    /// Condensed method: the solver sends a separator's new estimate when keeping the old
    /// one would cost more χ² than this fraction of the solve's χ² per separator (see
    /// `team::estimates_due`).
    pub send_fraction: f64,
    /// The solver of the separator graph (condensed method): its iteration limit and
    /// tolerances; its summary is [`Agent::last_solve`].
    pub solver: SolverOptions,
    /// Condensed method: send a neighbour that holds an older version of a graph only the
    /// key pairs that changed (false: always the whole graph, to measure the difference).
    pub graph_updates: bool,
    /// The transport delivers every message exactly once and in order per kind (the team
    /// link's delivery contract, `doorslam-team`'s `delivery`): a message handed over is
    /// settled at once as delivered ([`Agent::messages_for`]), the agent sends no
    /// acknowledgements and waits for none. False: the agent's own acknowledgements and
    /// resends over a lossy transport.
    pub link_delivers: bool,
    /// Condensed method: the solver copies its own graph to a standby robot, so that the
    /// robot that takes over when it leaves keeps its trajectory and closures (`team`'s
    /// "Standby copy"). On by default: the copy is the solver's trajectory alone (its
    /// closures are sent again by the robots above it once it left), sent when the solver
    /// is settled or `patience` behind, so it costs about the solver's condensed segments
    /// once (BENCHMARKS.md, "A standby copy on by default").
    pub standby_copy: bool,
}

/// The distributed solver.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The paper's two-stage distributed Gauss-Seidel, then block-coordinate refinement:
    /// neighbours exchange separator estimates every step.
    Dgs,
    /// Each robot condenses its trajectory onto its separators; the condensed graphs spread
    /// through the team and every robot solves the separator graph, then its interior
    /// ([`condensed`]).
    #[default]
    Condensed,
}

impl Default for AgentOptions {
    fn default() -> Self {
        Self {
            gamma: 1.0,
            async_gamma: 0.5,
            damp_on_reversal: false,
            rotation_change: 1e-2,
            pose_change: 1e-2,
            refine_change: 1e-3,
            send_rotation: 1e-3,
            send_pose: 1e-3,
            // The runner's default round (`runner::RunOptions::round`, 0.1 s) times the
            // step counts these were tuned as (4, 10 and 200 rounds), so runs on the
            // developer data are those of BENCHMARKS.md; a robot's `[backend]` section
            // sets its own (`resend_after_s`, `patience_s`, `max_stage_s`).
            resend_after: Duration::from_millis(400),
            patience: Duration::from_secs(1),
            max_stage: Duration::from_secs(20),
            refine_iterations: 10,
            momentum: true,
            method: Method::default(),
            pcm: None,
            graph_updates: true,
            link_delivers: false,
            standby_copy: true,
            // Each leaves out changes worth at most this fraction of the χ² in total (per
            // segment / separator times their count): 1e-5, ten times below the 1e-4 the
            // distributed estimate must stay within.
            relinearize_fraction: 1e-5,
            send_fraction: 1e-5,
            solver: SolverOptions::default(),
        }
    }
}

impl AgentOptions {
    /// DOOR-SLAM's thresholds for its KITTI run: rotation change 0.1, pose change 0.5.
    pub fn paper() -> Self {
        Self {
            rotation_change: 0.1,
            pose_change: 0.5,
            method: Method::Dgs,
            ..Self::default()
        }
    }
}

/// What the robot holds of one neighbour, and what it knows the neighbour holds of it.
#[derive(Debug, Default)]
struct Neighbor {
    /// Told by the caller (discovery): a neighbour out of range is not waited for.
    present: bool,
    /// The neighbour's latest state: (epoch, sequence) of the message that carried it.
    state: Option<PeerState>,
    /// The neighbour's separator estimates in its (= our) anchor frame.
    rotations: BTreeMap<u64, Matrix3<f64>>,
    poses: BTreeMap<u64, SE3>,
    /// The neighbour's `PoseEstimates` received, for acknowledgements.
    received: Received,
    ack_sequence: u64,
    /// Sending side: next sequence, messages in flight (sequence → time sent, contents),
    /// and what the neighbour is known to hold.
    next_sequence: u64,
    in_flight: BTreeMap<u64, (Duration, Sent)>,
    confirmed: Sent,
    /// The neighbour's epoch our confirmed state refers to (a restart forgets it).
    confirmed_epoch: Option<u64>,
    /// The condensed method's exchange with this neighbour.
    team: team::TeamLink,
    /// The team-map exchange with this neighbour.
    map: map::MapLink,
}

impl Neighbor {
    /// DGS: the messages in flight whose sequence `acked` are delivered (the neighbour
    /// holds what they carried); one not acknowledged while a later one was is lost (its
    /// separators are due again). The number lost.
    fn settle(&mut self, acked: impl Fn(u64) -> bool) -> u64 {
        let highest = self.in_flight.keys().copied().filter(|&s| acked(s)).max();
        let seqs: Vec<u64> = self.in_flight.keys().copied().collect();
        let mut lost = 0;
        for s in seqs {
            if acked(s) {
                if let Some((_, sent)) = self.in_flight.remove(&s) {
                    self.confirmed.flags = sent.flags.or(self.confirmed.flags);
                    self.confirmed.rotations.extend(sent.rotations);
                    self.confirmed.poses.extend(sent.poses);
                }
            } else if highest.is_some_and(|h| s < h) {
                self.in_flight.remove(&s);
                lost += 1;
            }
        }
        lost
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct PeerState {
    epoch: u64,
    sequence: u64,
    generation: u64,
    stage: Stage,
    converged: bool,
    anchor: u8,
}

/// The flags and values one message carried (or the neighbour holds).
#[derive(Debug, Clone, Default)]
struct Sent {
    flags: Option<(u64, Stage, bool, u8)>,
    rotations: BTreeMap<u64, Matrix3<f64>>,
    poses: BTreeMap<u64, SE3>,
}

/// Counters of one agent.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AgentStats {
    pub steps: u64,
    /// Steps that solved something (the others waited for a neighbour's estimates).
    pub updates: u64,
    pub messages_sent: u64,
    pub bytes_sent: u64,
    pub estimates_sent: u64,
    pub resent: u64,
    pub ignored_stale: u64,
    pub refused: u64,
    /// Re-initializations (a lower anchor heard, a neighbour's frame changed).
    pub reinitializations: u64,
    /// Inter-robot closures PCM left out of the last solve.
    pub rejected_closures: u64,
    /// Messages that arrived before the first closure with their sender, held
    /// ([`PARKED_MAX`]), and of them dropped because the hold was full.
    pub parked: u64,
    pub parked_dropped: u64,
}

/// One robot's share of the distributed pose-graph optimization.
#[derive(Debug)]
pub struct Agent {
    robot: u8,
    id: RobotId,
    epoch: u64,
    options: AgentOptions,
    keys: Vec<u64>,
    index: BTreeMap<u64, usize>,
    /// Current estimate: the anchor's frame once `anchored`, the odometry frame before.
    poses: Vec<SE3>,
    /// Stage-1 variables.
    relaxed: Vec<Matrix3<f64>>,
    /// Initial (odometry) estimate, to restart from when the frame changes.
    initial: Vec<SE3>,
    edges: Vec<OwnEdge>,
    closures: Vec<OwnClosure>,
    neighbors: BTreeMap<u8, Neighbor>,
    stage: Stage,
    /// Solved steps in the current stage (the `round` its messages carry).
    stage_steps: u64,
    /// Time spent in the current stage's solved steps, and of them converged (waiting for
    /// neighbours): each step adds the time since the previous step. (Time while the
    /// robot could not solve — nothing in its frame yet — or had not converged is not
    /// waiting: `patience` is time spent converged, `max_stage` time spent solving.)
    stage_time: Duration,
    waited: Duration,
    /// The time [`Self::step`] was last given (monotonic, caller's origin), and the time
    /// since the step before it (the first step: since the clock's origin).
    now: Duration,
    step_time: Duration,
    stage_converged: bool,
    anchored: bool,
    anchor: u8,
    generation: u64,
    /// Own poses solved in the anchor's frame (reachable from the gauge or a neighbour).
    in_frame: Vec<bool>,
    last_change: f64,
    /// Accelerated block-coordinate descent (Nesterov momentum with adaptive restart, as
    /// dpgo's RBCD++): the previous step's block solutions and the steps since a restart.
    solution_relaxed: Vec<Matrix3<f64>>,
    solution: Vec<SE3>,
    momentum_steps: u64,
    /// The previous undamped step of a linear stage (solve − x, flattened over the own
    /// poses), for [`AgentOptions::damp_on_reversal`].
    last_step: Vec<f64>,
    /// A step of this stage reversed the one before it.
    reversed_in_stage: bool,
    /// The condensed method's state ([`team`]); the own graph must be condensed again.
    team: team::TeamState,
    own_graph_dirty: bool,
    /// The neighbours' trajectories that arrived for the team map.
    team_map: BTreeMap<u8, TeamTrajectory>,
    /// Incremented whenever the estimate changes (the team map's version).
    estimate_version: u64,
    /// Inter-robot closures (key, key) PCM left out of the last solve.
    rejected: Vec<(u64, u64)>,
    /// Messages from robots this one shares no closure with yet, oldest first, taken in
    /// when the first closure with their sender arrives ([`PARKED_MAX`]).
    parked: VecDeque<(u8, Message)>,
    /// Presence heard of robots that are not neighbours yet (the link reports a peer
    /// when it appears, which can be before the first closure with it).
    heard_present: BTreeMap<u8, bool>,
    stats: AgentStats,
}

/// At most this many messages wait for the first closure with their sender (all senders
/// together; the oldest is dropped, counted in [`AgentStats::parked_dropped`]). The two
/// robots of a closure hear of it apart: the loop-closure message and the back-end's
/// messages travel as different kinds, so a neighbour's route, graph or estimates can
/// reach this robot first (seen after a restart: the solver's one route refused, the
/// robot left in its own frame). A team's back-end sends a few messages per neighbour
/// and round, so 64 holds several rounds from a handful of robots.
pub const PARKED_MAX: usize = 64;

impl Agent {
    /// An agent for robot `robot` (0 = 'a'), identified on the wire as `id`; `epoch` is
    /// its team-link epoch (incremented by the caller at every start).
    pub fn new(robot: u8, id: RobotId, epoch: u64, options: AgentOptions) -> Self {
        Self {
            robot,
            id,
            epoch,
            options,
            keys: Vec::new(),
            index: BTreeMap::new(),
            poses: Vec::new(),
            relaxed: Vec::new(),
            initial: Vec::new(),
            edges: Vec::new(),
            closures: Vec::new(),
            neighbors: BTreeMap::new(),
            stage: Stage::Rotation,
            stage_steps: 0,
            stage_time: Duration::ZERO,
            waited: Duration::ZERO,
            now: Duration::ZERO,
            step_time: Duration::ZERO,
            stage_converged: false,
            anchored: false,
            anchor: robot,
            generation: 0,
            in_frame: Vec::new(),
            last_change: f64::INFINITY,
            solution_relaxed: Vec::new(),
            solution: Vec::new(),
            momentum_steps: 0,
            last_step: Vec::new(),
            reversed_in_stage: false,
            team: team::TeamState {
                path: vec![robot],
                ..team::TeamState::default()
            },
            own_graph_dirty: true,
            team_map: BTreeMap::new(),
            estimate_version: 0,
            rejected: Vec::new(),
            parked: VecDeque::new(),
            heard_present: BTreeMap::new(),
            stats: AgentStats::default(),
        }
    }

    pub fn robot(&self) -> u8 {
        self.robot
    }

    fn own(&self, k: u64) -> Result<(), DpgoError> {
        if key::robot(k) == Some(self.robot) {
            Ok(())
        } else {
            Err(DpgoError::NotOwn {
                key: key::label(k),
                robot: self.robot,
            })
        }
    }

    /// Adds one of the robot's poses with its initial (odometry) estimate.
    pub fn add_pose(&mut self, k: u64, initial: SE3) -> Result<(), DpgoError> {
        self.own(k)?;
        if self.index.contains_key(&k) {
            return Err(DpgoError::DuplicatePose(key::label(k)));
        }
        // The first pose is the gauge and index-consecutive poses are the odometry chain
        // the condensed method compounds: poses come in index order.
        if let Some(&last) = self.keys.last() {
            if key::index(k) < key::index(last) {
                return Err(DpgoError::OutOfOrder {
                    key: key::label(k),
                    last: key::label(last),
                });
            }
        }
        // Once in the team frame, a new pose starts where its odometry puts it from the
        // last pose's team estimate.
        let start = match (self.anchored, self.poses.last(), self.initial.last()) {
            (true, Some(x), Some(x0)) => x.compose(&x0.inverse().compose(&initial)),
            _ => initial,
        };
        self.index.insert(k, self.keys.len());
        self.keys.push(k);
        self.poses.push(start);
        self.team.interior_dirty = true;
        self.initial.push(initial);
        self.relaxed
            .push(initial.rotation.to_rotation_matrix().into_inner());
        self.in_frame.push(false);
        self.solution.push(initial);
        self.solution_relaxed
            .push(initial.rotation.to_rotation_matrix().into_inner());
        Ok(())
    }

    fn checked_information(a: u64, b: u64, information: &TangentMatrix) -> Result<(), DpgoError> {
        check_information(information, 6, InformationCheck::PositiveDefinite).map_err(
            |source| DpgoError::Information {
                from: key::label(a),
                to: key::label(b),
                source,
            },
        )?;
        match information.diagonal().max() {
            value if value > MAX_INFORMATION => Err(DpgoError::ImplausibleInformation {
                from: key::label(a),
                to: key::label(b),
                value,
            }),
            _ => Ok(()),
        }
    }

    /// Adds an edge between two of the robot's poses (odometry or an intra-robot closure):
    /// `z ≈ X_a⁻¹ X_b`, information rotation-first.
    pub fn add_odometry(
        &mut self,
        a: u64,
        b: u64,
        z: SE3,
        information: TangentMatrix,
    ) -> Result<(), DpgoError> {
        let i = *self
            .index
            .get(&a)
            .ok_or_else(|| DpgoError::UnknownPose(key::label(a)))?;
        let j = *self
            .index
            .get(&b)
            .ok_or_else(|| DpgoError::UnknownPose(key::label(b)))?;
        if i == j {
            return Err(EdgeError::SelfLoop {
                index: i,
                label: key::label(a),
            }
            .into());
        }
        Self::checked_information(a, b, &information)?;
        let (kappa, tau) = isotropic_weights(&information, 3, 3);
        self.edges.push(OwnEdge {
            i,
            j,
            z,
            information,
            kappa,
            tau,
        });
        self.stage_converged = false;
        self.own_graph_dirty = true;
        self.team.interior_dirty = true;
        Ok(())
    }

    /// Adds an inter-robot loop closure `z ≈ X_a⁻¹ X_b` where one of `a`, `b` is this
    /// robot's (both robots of a closure add it). Accepted closures only: outlier
    /// rejection runs before (PCM).
    pub fn add_closure(
        &mut self,
        a: u64,
        b: u64,
        z: SE3,
        information: TangentMatrix,
    ) -> Result<(), DpgoError> {
        Self::checked_information(a, b, &information)?;
        let (ra, rb) = (key::robot(a), key::robot(b));
        if ra == rb {
            return Err(DpgoError::NotInterRobot {
                from: key::label(a),
                to: key::label(b),
            });
        }
        // Seen from this robot: own → other.
        let (own, other, z, information) = if ra == Some(self.robot) {
            (a, b, z, information)
        } else if rb == Some(self.robot) {
            let (z, information) = doorslam_geometry::reverse_measurement(&z, &information);
            (b, a, z, information)
        } else {
            return Err(DpgoError::NotOwn {
                key: key::label(a),
                robot: self.robot,
            });
        };
        let Some(neighbor) = key::robot(other) else {
            return Err(DpgoError::NotInterRobot {
                from: key::label(a),
                to: key::label(b),
            });
        };
        let own = *self
            .index
            .get(&own)
            .ok_or_else(|| DpgoError::UnknownPose(key::label(own)))?;
        let (kappa, tau) = isotropic_weights(&information, 3, 3);
        self.closures.push(OwnClosure {
            own,
            other,
            z,
            information,
            kappa,
            tau,
        });
        let new_neighbor = !self.neighbors.contains_key(&neighbor);
        let n = self.neighbors.entry(neighbor).or_default();
        if new_neighbor {
            n.present = self.heard_present.remove(&neighbor).unwrap_or(false);
        }
        self.stage_converged = false;
        self.own_graph_dirty = true;
        self.team.interior_dirty = true;
        // A new neighbour may have a lower id than our anchor.
        self.update_anchor();
        if new_neighbor {
            self.take_parked(neighbor);
        }
        Ok(())
    }

    /// Takes in, in arrival order, the messages `neighbor` sent before its first closure
    /// with this robot arrived. One refused now is counted as any refusal; the caller
    /// has long acknowledged it, so it is logged here.
    fn take_parked(&mut self, neighbor: u8) {
        let (theirs, others): (VecDeque<_>, VecDeque<_>) = std::mem::take(&mut self.parked)
            .into_iter()
            .partition(|(from, _)| *from == neighbor);
        self.parked = others;
        for (_, m) in theirs {
            if let Err(e) = self.receive(neighbor, &m) {
                tracing::warn!("distributed back-end: a held message refused: {e}");
            }
        }
    }

    /// Holds a message of a robot this one shares no closure with yet.
    fn park(&mut self, neighbor: u8, message: &Message) {
        if self.parked.len() >= PARKED_MAX {
            self.parked.pop_front();
            self.stats.parked_dropped += 1;
        }
        self.parked.push_back((neighbor, message.clone()));
        self.stats.parked += 1;
    }

    /// Discovery: a neighbour came into range (true) or left it (false). A neighbour out of
    /// range is not waited for; its last estimates stay in use.
    pub fn set_present(&mut self, neighbor: u8, present: bool) {
        match self.neighbors.get_mut(&neighbor) {
            Some(n) => n.present = present,
            None => {
                self.heard_present.insert(neighbor, present);
            }
        }
    }

    /// The link to `neighbor` restarted (a team link's new epoch, a back-end restarted
    /// behind it): what the neighbour was known to hold, or was sent and not yet taken by
    /// it, may be lost, so everything is due again at the next [`Self::messages_for`].
    pub fn link_restarted(&mut self, neighbor: u8) {
        if let Some(n) = self.neighbors.get_mut(&neighbor) {
            n.confirmed = Sent::default();
            n.confirmed_epoch = None;
            n.in_flight.clear();
            n.team.link_restarted();
            n.map.link_restarted();
        }
    }

    /// The robots this one shares closures with.
    pub fn neighbors(&self) -> impl Iterator<Item = u8> + '_ {
        self.neighbors.keys().copied()
    }

    pub fn stage(&self) -> Stage {
        self.stage
    }

    /// The change the last solved step made (what the stage's threshold tests; infinite
    /// before the first step of a stage).
    pub fn last_change(&self) -> f64 {
        self.last_change
    }

    /// The robot whose first pose fixes this robot's frame.
    pub fn anchor(&self) -> u8 {
        self.anchor
    }

    /// Whether the estimate is in the anchor's frame (see the module documentation).
    pub fn anchored(&self) -> bool {
        self.anchored
    }

    pub fn stats(&self) -> AgentStats {
        self.stats
    }

    /// The inter-robot closures (key, key) PCM left out of the last solve (condensed
    /// method with PCM in the loop).
    pub fn rejected_closures(&self) -> &[(u64, u64)] {
        &self.rejected
    }

    /// The summary of the last solve of the team's separator graph this robot ran (the
    /// condensed method's solver), `None` if it never solved one.
    pub fn last_solve(&self) -> Option<&crate::solver::Summary> {
        self.team.last_solve.as_ref()
    }

    /// How the team solve behind this robot's separator estimates stopped (condensed
    /// method): on the solver its own solve's, on every other robot the stop that came
    /// down with its estimates (the flags of `PoseEstimates`). `None` before any solution
    /// (or with DGS, which has no team solve).
    pub fn team_stop_reason(&self) -> Option<crate::solver::StopReason> {
        self.team.solutions.get(&self.robot).and_then(|s| s.stop)
    }

    /// The solve behind this robot's separator estimates (condensed method): the solver's
    /// solve count as it came down with them (`PoseEstimates::round`), on the solver its
    /// own count. `None` before any solution (or with DGS).
    pub fn team_round(&self) -> Option<u64> {
        self.team.solutions.get(&self.robot).map(|s| s.round)
    }

    /// Per robot this one hands estimates down to (the robots of each present child's
    /// subtree): the solve round of the estimates it handed to the link for that robot.
    /// Once they arrive, that robot's [`Self::team_round`] is this round; until then it
    /// still settles on an older solve — which [`Self::converged`] cannot see on either
    /// side, as the link, not the agent, delivers them (`link_delivers`).
    pub fn rounds_handed_down(&self) -> BTreeMap<u8, u64> {
        self.condensed_rounds_handed_down()
    }

    /// The robot's poses, in the team's frame once [`Self::anchored`].
    pub fn estimate(&self) -> impl Iterator<Item = (u64, &SE3)> + '_ {
        self.keys.iter().copied().zip(&self.poses)
    }

    /// Converged: refinement finished here and at every present neighbour of the same
    /// frame, and every neighbour holds our latest separators.
    pub fn converged(&self) -> bool {
        let maps_idle = self
            .neighbors
            .values()
            .all(|n| !n.present || (n.map.idle() && !n.map.ack_due()));
        if !maps_idle {
            return false;
        }
        if self.options.method == Method::Condensed {
            return self.condensed_converged();
        }
        let settled = self.stage == Stage::Refine && self.stage_converged;
        settled
            && self.neighbors.iter().all(|(_, n)| {
                let peer_done = match n.state {
                    Some(s) => s.anchor == self.anchor && s.stage == Stage::Refine && s.converged,
                    None => false,
                };
                !n.present || (peer_done && n.in_flight.is_empty())
            })
    }

    fn gauge(&self) -> Option<usize> {
        (self.anchor == self.robot && !self.keys.is_empty()).then_some(0)
    }

    /// Lowest of: this robot if no closure partner is lower, and every anchor heard of.
    fn update_anchor(&mut self) {
        let lowest_partner = self.neighbors.keys().next().copied();
        let mut anchor = match lowest_partner {
            Some(p) if p < self.robot => u8::MAX,
            _ => self.robot,
        };
        for n in self.neighbors.values() {
            if let Some(s) = n.state {
                anchor = anchor.min(s.anchor);
            }
        }
        if anchor == u8::MAX {
            // Waiting to hear the lower partner's frame; keep the current one meanwhile.
            anchor = self.anchor.min(lowest_partner.unwrap_or(self.robot));
        }
        if anchor != self.anchor {
            self.reinitialize(anchor);
        }
    }

    /// Starts over in another frame: stage 1 from the odometry estimate, nothing sent
    /// until the new frame reaches us, neighbours told by a new generation.
    fn reinitialize(&mut self, anchor: u8) {
        self.anchor = anchor;
        self.anchored = false;
        self.generation += 1;
        self.stage = Stage::Rotation;
        self.stage_steps = 0;
        self.stage_time = Duration::ZERO;
        self.waited = Duration::ZERO;
        self.stage_converged = false;
        self.poses.clone_from(&self.initial);
        self.relaxed = self
            .initial
            .iter()
            .map(|p| p.rotation.to_rotation_matrix().into_inner())
            .collect();
        self.in_frame.iter_mut().for_each(|f| *f = false);
        self.last_change = f64::INFINITY;
        self.reset_momentum();
        self.stats.reinitializations += 1;
        for n in self.neighbors.values_mut() {
            n.confirmed = Sent::default();
            n.in_flight.clear();
            // Estimates in another frame than the new anchor's are useless now.
            if n.state.is_some_and(|s| s.anchor != anchor) {
                n.rotations.clear();
                n.poses.clear();
            }
        }
    }

    /// The neighbour estimates usable in the current stage, per closure.
    fn fixed_rotations(&self) -> Vec<Option<Matrix3<f64>>> {
        self.closures
            .iter()
            .map(|c| {
                let n = self.neighbors.get(&key::robot(c.other)?)?;
                let s = n.state?;
                if s.anchor != self.anchor {
                    return None;
                }
                n.rotations.get(&c.other).copied().or_else(|| {
                    n.poses
                        .get(&c.other)
                        .map(|p| p.rotation.to_rotation_matrix().into_inner())
                })
            })
            .collect()
    }

    fn fixed_poses(&self) -> Vec<Option<SE3>> {
        self.closures
            .iter()
            .map(|c| {
                let n = self.neighbors.get(&key::robot(c.other)?)?;
                let s = n.state?;
                (s.anchor == self.anchor)
                    .then(|| n.poses.get(&c.other).copied())
                    .flatten()
            })
            .collect()
    }

    /// Own poses connected (through own edges) to the gauge or to a closure whose
    /// neighbour estimate is usable: the part of the trajectory a step can put in the
    /// anchor's frame.
    fn reachable(&self, seeds: impl Iterator<Item = usize>) -> Vec<bool> {
        let mut adj: Vec<Vec<usize>> = vec![Vec::new(); self.keys.len()];
        for e in &self.edges {
            adj[e.i].push(e.j);
            adj[e.j].push(e.i);
        }
        let mut seen = vec![false; self.keys.len()];
        let mut stack: Vec<usize> = seeds.collect();
        for &s in &stack {
            seen[s] = true;
        }
        while let Some(a) = stack.pop() {
            for &b in &adj[a] {
                if !seen[b] {
                    seen[b] = true;
                    stack.push(b);
                }
            }
        }
        seen
    }

    /// The own poses a step can solve in the anchor's frame: connected to the gauge or to a
    /// closure whose neighbour estimate (`other`, per closure) is known; `None` if none.
    fn active<T>(&self, gauge: Option<usize>, other: &[Option<T>]) -> Option<Vec<bool>> {
        let seeds = gauge.into_iter().chain(
            self.closures
                .iter()
                .zip(other)
                .filter(|(_, o)| o.is_some())
                .map(|(c, _)| c.own),
        );
        let active = self.reachable(seeds);
        active.iter().any(|a| *a).then_some(active)
    }

    /// One iteration of the current stage at time `now` (a monotonic clock of the
    /// caller's choosing, e.g. time since start; a robot passes its clock, the runner
    /// rounds × round length, so runs repeat exactly). Every timeout of
    /// [`AgentOptions`] is measured on it. Returns whether anything was solved.
    pub fn step(&mut self, now: Duration) -> Result<bool, DpgoError> {
        // A clock that went back (the caller's bug) must not make timeouts negative.
        self.step_time = now.saturating_sub(self.now);
        self.now = self.now.max(now);
        if self.options.method == Method::Condensed {
            return self.step_condensed();
        }
        self.stats.steps += 1;
        self.update_anchor();
        if self.keys.is_empty() {
            return Ok(false);
        }
        let gauge = self.gauge();
        let solved = match self.stage {
            Stage::Rotation => self.step_rotations(gauge)?,
            Stage::Pose => self.step_translations(gauge)?,
            Stage::Refine => self.step_refine(gauge)?,
        };
        if !solved {
            return Ok(false);
        }
        self.stats.updates += 1;
        self.estimate_version += 1;
        self.anchored = true;
        self.stage_steps += 1;
        self.stage_time += self.step_time;
        let threshold = match self.stage {
            Stage::Rotation => self.options.rotation_change,
            Stage::Pose => self.options.pose_change,
            Stage::Refine => self.options.refine_change,
        };
        self.stage_converged = self.last_change < threshold;
        tracing::trace!(robot = self.robot, stage = ?self.stage, change = self.last_change, "step");
        self.maybe_advance();
        Ok(true)
    }

    /// Whether the linear stages watch their steps for a reversal
    /// ([`AgentOptions::damp_on_reversal`] over a link that delivers late).
    fn watches_reversal(&self) -> bool {
        self.options.link_delivers && self.options.damp_on_reversal
    }

    /// γ of this step of a linear stage: Gauss-Seidel's over a link that delivers within
    /// the round, damped Jacobi's over one that delivers later
    /// ([`AgentOptions::async_gamma`]; with [`AgentOptions::damp_on_reversal`] only once a
    /// step of the stage reversed the one before it). `step`: solve − x over the own
    /// poses, given only when [`Agent::watches_reversal`].
    fn linear_gamma(&mut self, step: Option<Vec<f64>>) -> f64 {
        if !self.options.link_delivers {
            return self.options.gamma;
        }
        let Some(step) = step else {
            return self.options.async_gamma;
        };
        let reversed = self.last_step.len() == step.len()
            && self
                .last_step
                .iter()
                .zip(&step)
                .map(|(a, b)| a * b)
                .sum::<f64>()
                < 0.0;
        self.last_step = step;
        // Once reversed, damped for the rest of the stage: alternating full and half
        // steps lets the swap of a Jacobi two-cycle grow back.
        self.reversed_in_stage |= reversed;
        if self.reversed_in_stage {
            self.options.async_gamma
        } else {
            self.options.gamma
        }
    }

    /// The momentum weight of this step: Nesterov's (k − 1)/(k + 2), restarted (0) when the
    /// block change grew since the last step.
    fn momentum(&mut self, change: f64) -> f64 {
        if !self.options.momentum || change > self.last_change {
            self.momentum_steps = 0;
            return 0.0;
        }
        self.momentum_steps += 1;
        let k = self.momentum_steps as f64;
        (k - 1.0) / (k + 2.0)
    }

    /// Restart the momentum from the current estimate (a new stage or frame).
    fn reset_momentum(&mut self) {
        self.momentum_steps = 0;
        self.last_step.clear();
        self.reversed_in_stage = false;
        self.solution.clone_from(&self.poses);
        self.solution_relaxed.clone_from(&self.relaxed);
    }

    /// Next stage once converged here and at the present neighbours of this frame (or
    /// after `patience` of waiting, or `max_stage` in the stage).
    fn maybe_advance(&mut self) {
        if self.stage == Stage::Refine {
            return;
        }
        let forced = self.stage_time >= self.options.max_stage;
        if !self.stage_converged && !forced {
            return;
        }
        let neighbours_done = self.neighbors.values().all(|n| {
            !n.present
                || n.state.is_some_and(|s| {
                    s.anchor == self.anchor
                        && (s.stage > self.stage || (s.stage == self.stage && s.converged))
                })
        });
        self.waited += self.step_time;
        if neighbours_done || forced || self.waited > self.options.patience {
            tracing::debug!(
                robot = self.robot,
                stage = ?self.stage,
                steps = self.stage_steps,
                change = self.last_change,
                neighbours_done,
                forced,
                "stage done"
            );
            self.stage = match self.stage {
                Stage::Rotation => Stage::Pose,
                _ => Stage::Refine,
            };
            self.stage_steps = 0;
            self.stage_time = Duration::ZERO;
            self.waited = Duration::ZERO;
            self.stage_converged = false;
            self.last_change = f64::INFINITY;
            self.reset_momentum();
        }
    }

    fn step_rotations(&mut self, gauge: Option<usize>) -> Result<bool, DpgoError> {
        let other = self.fixed_rotations();
        let Some(active) = self.active(gauge, &other) else {
            return Ok(false);
        };
        let fixed_own: Vec<Option<Matrix3<f64>>> = (0..self.keys.len())
            .map(|p| (Some(p) == gauge).then(|| self.relaxed[p]))
            .collect();
        let new = local::solve_rotations(
            &active,
            &self.edges,
            &self.closures,
            Fixed {
                own: &fixed_own,
                other: &other,
            },
        )?;
        let step = self.watches_reversal().then(|| {
            new.iter()
                .enumerate()
                .flat_map(|(p, r)| {
                    let d = r
                        .as_ref()
                        .map_or_else(Matrix3::zeros, |r| r - self.relaxed[p]);
                    d.as_slice().to_vec()
                })
                .collect()
        });
        let gamma = self.linear_gamma(step);
        // x⁺ = x + γ(solve − x), change |x⁺ − x_prev|, then y = x⁺ + β(x⁺ − x_prev).
        let solved: Vec<(usize, Matrix3<f64>)> = new
            .into_iter()
            .enumerate()
            .filter_map(|(p, r)| Some((p, self.relaxed[p] + (r? - self.relaxed[p]) * gamma)))
            .collect();
        let change = solved
            .iter()
            .map(|(p, x)| (x - self.solution_relaxed[*p]).norm_squared())
            .sum::<f64>()
            .sqrt();
        let beta = self.momentum(change);
        for (p, x) in solved {
            self.relaxed[p] = x + (x - self.solution_relaxed[p]) * beta;
            self.solution_relaxed[p] = x;
            self.poses[p].rotation = SO3::from_matrix(&self.relaxed[p]).quaternion();
        }
        self.in_frame = active;
        self.last_change = change;
        Ok(true)
    }

    fn step_translations(&mut self, gauge: Option<usize>) -> Result<bool, DpgoError> {
        let other = self.fixed_poses();
        let Some(active) = self.active(gauge, &other) else {
            return Ok(false);
        };
        let rotations: Vec<Matrix3<f64>> = self
            .poses
            .iter()
            .map(|p| p.rotation.to_rotation_matrix().into_inner())
            .collect();
        let fixed_own: Vec<Option<Vector3<f64>>> = (0..self.keys.len())
            .map(|p| (Some(p) == gauge).then(|| self.poses[p].translation.vector))
            .collect();
        let other_t: Vec<Option<Vector3<f64>>> = other
            .iter()
            .map(|o| o.map(|p| p.translation.vector))
            .collect();
        let new = local::solve_translations(
            &active,
            &rotations,
            &self.edges,
            &self.closures,
            Fixed {
                own: &fixed_own,
                other: &other_t,
            },
        )?;
        let step = self.watches_reversal().then(|| {
            new.iter()
                .enumerate()
                .flat_map(|(p, t)| {
                    let d = t
                        .as_ref()
                        .map_or_else(Vector3::zeros, |t| t - self.poses[p].translation.vector);
                    [d.x, d.y, d.z]
                })
                .collect()
        });
        let gamma = self.linear_gamma(step);
        let solved: Vec<(usize, Vector3<f64>)> = new
            .into_iter()
            .enumerate()
            .filter_map(|(p, t)| {
                let now = self.poses[p].translation.vector;
                Some((p, now + (t? - now) * gamma))
            })
            .collect();
        let change = solved
            .iter()
            .map(|(p, x)| (x - self.solution[*p].translation.vector).norm_squared())
            .sum::<f64>()
            .sqrt();
        let beta = self.momentum(change);
        for (p, x) in solved {
            let prev = self.solution[p].translation.vector;
            self.poses[p].translation = Translation3::from(x + (x - prev) * beta);
            self.solution[p] = SE3::from_parts(Translation3::from(x), self.poses[p].rotation);
        }
        self.in_frame = active;
        self.last_change = change;
        Ok(true)
    }

    fn step_refine(&mut self, gauge: Option<usize>) -> Result<bool, DpgoError> {
        let other = self.fixed_poses();
        let Some(active) = self.active(gauge, &other) else {
            return Ok(false);
        };
        let options = SolverOptions {
            max_iterations: self.options.refine_iterations,
            ..SolverOptions::default()
        };
        let new = local::refine(
            &active,
            &self.poses,
            gauge,
            &self.edges,
            &self.closures,
            &other,
            &options,
        )?;
        let solved: Vec<(usize, SE3)> = new
            .into_iter()
            .enumerate()
            .filter_map(|(p, x)| Some((p, x?)))
            .collect();
        let change = solved
            .iter()
            .map(|(p, x)| self.solution[*p].inverse().compose(x).log().norm_squared())
            .sum::<f64>()
            .sqrt();
        let beta = self.momentum(change);
        for (p, x) in solved {
            // y = x ⊕ β (x ⊖ x_prev), along the step on the manifold.
            let step = self.solution[p].inverse().compose(&x).log();
            self.poses[p] = x.compose(&SE3::exp(&(step * beta)));
            self.solution[p] = x;
        }
        self.in_frame = active;
        self.last_change = change;
        Ok(true)
    }

    /// Own separator poses shared with `neighbor` that are in the anchor's frame.
    fn separators_for(&self, neighbor: u8) -> BTreeSet<usize> {
        self.closures
            .iter()
            .filter(|c| key::robot(c.other) == Some(neighbor) && self.in_frame[c.own])
            .map(|c| c.own)
            .collect()
    }

    fn flags(&self) -> (u64, Stage, bool, u8) {
        (
            self.generation,
            self.stage,
            self.stage_converged,
            self.anchor,
        )
    }

    /// The messages due to `neighbor` now: its acknowledgement if we received something,
    /// and our separator estimates that moved beyond the send threshold from what it
    /// holds (plus our state if it changed), resending what was lost.
    pub fn messages_for(&mut self, neighbor: u8) -> Result<Vec<Message>, DpgoError> {
        let mut out = match self.options.method {
            Method::Condensed => self.team_messages_for(neighbor)?,
            Method::Dgs => self.dgs_messages_for(neighbor)?,
        };
        out.extend(self.map_messages_for(neighbor)?);
        if self.options.link_delivers {
            out.retain(|m| !matches!(m.body, Body::Ack(_)));
            for m in &out {
                self.handed_over(neighbor, m)?;
            }
        }
        for m in &out {
            self.stats.messages_sent += 1;
            self.stats.bytes_sent += m.encoded_len() as u64;
        }
        Ok(out)
    }

    /// Under [`AgentOptions::link_delivers`]: `m` is handed to a transport that delivers
    /// it to `neighbor` exactly once, after every earlier message of its kind, so what it
    /// carries is what the neighbour holds once the transport is through — settled here as
    /// delivered, with the same bookkeeping as an acknowledgement of it and every earlier
    /// message of its kind. No message of the neighbour is made up: this is the agent's
    /// own record of what it handed over.
    fn handed_over(&mut self, neighbor: u8, m: &Message) -> Result<(), DpgoError> {
        let through = Ack {
            epoch: self.epoch,
            kind: m.kind(),
            next: m.header.sequence + 1,
            received: Vec::new(),
        };
        match m.kind() {
            Kind::TeamMap => self.map_ack(neighbor, &through).map(drop),
            _ if self.options.method == Method::Condensed => {
                self.team_ack(neighbor, &through).map(drop)
            }
            Kind::PoseEstimates => {
                if let Some(n) = self.neighbors.get_mut(&neighbor) {
                    n.settle(|s| s < through.next);
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }

    fn dgs_messages_for(&mut self, neighbor: u8) -> Result<Vec<Message>, DpgoError> {
        let now = self.now;
        let separators = self.separators_for(neighbor);
        let flags = self.flags();
        let stage = self.stage;
        let rotation_stage = stage == Stage::Rotation;
        let mut values: Vec<(u64, Estimate)> = Vec::new();
        let mut out = Vec::new();
        let mut carried = Sent::default();
        let (send_rotation, send_pose, resend_after) = (
            self.options.send_rotation,
            self.options.send_pose,
            self.options.resend_after,
        );
        let Some(n) = self.neighbors.get_mut(&neighbor) else {
            return Ok(out);
        };
        // Acknowledge what we received of the neighbour's current epoch.
        if let Some(ack) =
            n.received
                .take_ack(&self.id, self.epoch, n.ack_sequence, Kind::PoseEstimates)
        {
            n.ack_sequence += 1;
            out.push(ack);
        }
        // Lost: unacknowledged for `resend_after`.
        let lost: Vec<u64> = n
            .in_flight
            .iter()
            .filter(|(_, (sent, _))| now.saturating_sub(*sent) >= resend_after)
            .map(|(&s, _)| s)
            .collect();
        for s in lost {
            n.in_flight.remove(&s);
            self.stats.resent += 1;
        }
        if !self.anchored {
            return Ok(out);
        }
        // Latest value of each key as the neighbour holds it or will once in flight arrives.
        let mut view = n.confirmed.clone();
        for (_, sent) in n.in_flight.values() {
            view.flags = sent.flags.or(view.flags);
            view.rotations
                .extend(sent.rotations.iter().map(|(k, v)| (*k, *v)));
            view.poses.extend(sent.poses.iter().map(|(k, v)| (*k, *v)));
        }
        for &p in &separators {
            let k = self.keys[p];
            if rotation_stage {
                let r = self.relaxed[p];
                let due = view
                    .rotations
                    .get(&k)
                    .is_none_or(|held| (held - r).norm() > send_rotation);
                if due {
                    let q = RelaxedRotation::quantize(&matrix_rows(&r)).map_err(|source| {
                        DpgoError::Quantize {
                            key: key::label(k),
                            source,
                        }
                    })?;
                    carried.rotations.insert(k, matrix_from_rows(&q.matrix()));
                    values.push((k, Estimate::Rotation(q)));
                }
            } else {
                let x = self.poses[p];
                let due = view
                    .poses
                    .get(&k)
                    .is_none_or(|held| pose_distance(held, &x) > send_pose);
                if due {
                    let q = CompactPose::quantize(&x).map_err(|source| DpgoError::Quantize {
                        key: key::label(k),
                        source,
                    })?;
                    carried.poses.insert(k, *q.se3());
                    values.push((k, Estimate::Pose(q)));
                }
            }
        }
        if values.is_empty() && view.flags == Some(flags) {
            return Ok(out);
        }
        carried.flags = Some(flags);
        for chunk in values.chunks(MAX_POSE_ESTIMATES).chain(
            // An empty message still tells the neighbour our state.
            values.is_empty().then_some(&values[..0]),
        ) {
            let sequence = n.next_sequence;
            n.next_sequence += 1;
            let m = Message::new(
                Header {
                    sender: self.id.clone(),
                    epoch: self.epoch,
                    sequence,
                },
                Body::PoseEstimates(PoseEstimates {
                    optimization: self.generation,
                    round: self.stage_steps,
                    stage,
                    flags: if self.stage_converged {
                        ESTIMATES_CONVERGED
                    } else {
                        0
                    },
                    anchor: self.anchor,
                    estimates: chunk
                        .iter()
                        .map(|(key, value)| PoseEstimate {
                            key: *key,
                            value: value.clone(),
                        })
                        .collect(),
                }),
            );
            self.stats.estimates_sent += chunk.len() as u64;
            out.push(m);
        }
        // All chunks carry the same state; record the values once under the last sequence.
        if let Some(last) = n.next_sequence.checked_sub(1) {
            n.in_flight.insert(last, (now, carried));
        }
        Ok(out)
    }

    /// Takes one message from `neighbor`. Malformed input (estimates of another robot's
    /// poses, of poses we share no closure with, a message kind the back-end does not use)
    /// is refused with an error and changes nothing; stale or out-of-order messages are
    /// ignored (`Ok(false)`).
    pub fn receive(&mut self, neighbor: u8, message: &Message) -> Result<bool, DpgoError> {
        // A back-end message of a robot this one shares no closure with yet: the closure
        // may still be on its way (`PARKED_MAX`). Other kinds are refused below.
        if !self.neighbors.contains_key(&neighbor) && neighbor != self.robot {
            let backend_kind = match &message.body {
                Body::Ack(a) => matches!(
                    a.kind,
                    Kind::PoseEstimates | Kind::SeparatorGraph | Kind::Route | Kind::TeamMap
                ),
                Body::PoseEstimates(_)
                | Body::SeparatorGraph(_)
                | Body::Route(_)
                | Body::TeamMap(_) => true,
                _ => false,
            };
            if backend_kind {
                self.park(neighbor, message);
                return Ok(false);
            }
        }
        match &message.body {
            // A neighbour's (any other robot's was held above).
            Body::TeamMap(m) => {
                return self.map_receive(neighbor, &message.header, m);
            }
            Body::Ack(a) if a.kind == Kind::TeamMap => {
                return self.map_ack(neighbor, a);
            }
            _ if self.options.method == Method::Condensed => {
                return self.team_receive(neighbor, message);
            }
            _ => {}
        }
        let refuse = |reason: String| DpgoError::BadMessage {
            from: neighbor,
            reason,
        };
        let wanted: BTreeSet<u64> = self
            .closures
            .iter()
            .filter(|c| key::robot(c.other) == Some(neighbor))
            .map(|c| c.other)
            .collect();
        let Some(n) = self.neighbors.get_mut(&neighbor) else {
            self.stats.refused += 1;
            return Err(refuse("no closure with this robot".into()));
        };
        let h = &message.header;
        match &message.body {
            Body::Ack(a) => {
                if a.kind != Kind::PoseEstimates {
                    self.stats.refused += 1;
                    return Err(refuse(format!("ack of kind {}", a.kind.name())));
                }
                if a.epoch != self.epoch {
                    self.stats.ignored_stale += 1;
                    return Ok(false);
                }
                // The neighbour restarted since it confirmed anything: it holds nothing.
                if n.confirmed_epoch != Some(h.epoch) {
                    n.confirmed = Sent::default();
                    n.confirmed_epoch = Some(h.epoch);
                }
                let acked = |s: u64| s < a.next || a.received.iter().any(|r| r.contains(&s));
                self.stats.resent += n.settle(acked);
                Ok(true)
            }
            Body::PoseEstimates(p) => {
                if let Some(e) = p.estimates.iter().find(|e| !wanted.contains(&e.key)) {
                    self.stats.refused += 1;
                    return Err(refuse(format!(
                        "estimate of {}, which shares no closure with robot {}",
                        key::label(e.key),
                        self.robot
                    )));
                }
                // Acknowledge whatever we accept or ignore as stale: it arrived.
                match n.received.arrive(h.epoch, h.sequence) {
                    Arrival::Stale => {
                        self.stats.ignored_stale += 1;
                        return Ok(false);
                    }
                    Arrival::Restarted => {
                        n.confirmed = Sent::default();
                        n.in_flight.clear();
                    }
                    Arrival::Current => {}
                }
                // Within an epoch sequences only grow; a new epoch is a restart.
                let fresh = n
                    .state
                    .is_none_or(|s| (h.epoch, h.sequence) > (s.epoch, s.sequence));
                if !fresh {
                    self.stats.ignored_stale += 1;
                    return Ok(false);
                }
                let new_frame = n.state.is_none_or(|s| {
                    s.epoch != h.epoch || s.generation != p.optimization || s.anchor != p.anchor
                });
                tracing::trace!(
                    robot = self.robot,
                    from = neighbor,
                    sequence = h.sequence,
                    stage = ?p.stage,
                    estimates = p.estimates.len(),
                    new_frame,
                    "estimates received"
                );
                if new_frame {
                    n.rotations.clear();
                    n.poses.clear();
                }
                n.state = Some(PeerState {
                    epoch: h.epoch,
                    sequence: h.sequence,
                    generation: p.optimization,
                    stage: p.stage,
                    converged: p.flags & ESTIMATES_CONVERGED != 0,
                    anchor: p.anchor,
                });
                for e in &p.estimates {
                    match &e.value {
                        Estimate::Rotation(r) => {
                            n.rotations.insert(e.key, matrix_from_rows(&r.matrix()));
                        }
                        Estimate::Pose(q) => {
                            n.rotations.remove(&e.key);
                            n.poses.insert(e.key, *q.se3());
                        }
                    }
                }
                // A neighbour's move to a later stage or new values un-settle ours.
                if !p.estimates.is_empty() {
                    self.stage_converged = false;
                }
                self.update_anchor();
                Ok(true)
            }
            other => {
                self.stats.refused += 1;
                Err(refuse(format!(
                    "kind {} is not a back-end message",
                    other.kind().name()
                )))
            }
        }
    }
}

fn matrix_rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

fn matrix_from_rows(m: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::from_fn(|r, c| m[r][c])
}

/// Translation distance plus rotation angle.
fn pose_distance(a: &SE3, b: &SE3) -> f64 {
    (a.translation.vector - b.translation.vector).norm() + a.rotation.angle_to(&b.rotation)
}
