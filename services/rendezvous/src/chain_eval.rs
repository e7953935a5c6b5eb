//! The whole candidate chain offline (`doorslam place eval DIR... --verify`): descriptors →
//! top-k → temporal check → PnP verification on the front-end's keyframe features, against
//! ground truth, with the bytes the rendezvous protocol would send.
//!
//! Every pair of robots α < β meets once, after the flight: α sends all its descriptors,
//! β runs the [`CandidateChain`] over them against its own keyframes and sends back the
//! confirmed pairs and, once per candidate keyframe, its verification packet (the wire
//! form: at most `max_packet_features` features); α verifies each pair on its own
//! keyframe's full features (the front-end's PnP-RANSAC, as the team link does) and sends
//! the accepted closures. A verified closure is **false** when its relative pose is more
//! than [`FALSE_M`] or [`FALSE_DEG`] from the true one (`X_c⁻¹ X_q` from ground truth),
//! **aliased** when, in addition, its pair is an `aliased` row of `closures.csv` (copies of
//! one building); a true **overlap** (an `overlap` row, widened as the place-eval
//! positives) is **found** when a true verified closure joins its two sides.
//! `bytes_per_true_closure` divides every byte the exchange would send (descriptors,
//! matches, packets, closures; message headers included, acknowledgements and Zenoh's
//! framing not) by the true verified closures.

use std::collections::{BTreeMap, BTreeSet, HashSet};

use doorslam_backend::outliers::{maximum_clique, CliqueOptions, ConsistencyGraph};
use doorslam_dataset::StereoCalibration;
use doorslam_frontend::verify_bench::pose_error;
use doorslam_frontend::{from_packet, to_packet, verify, Feature, VerifyConfig};
use doorslam_geometry::{key, reverse_measurement};
use doorslam_ipc::wire::{
    Body, Descriptor, Descriptors, Header, Information, LoopClosure, LoopClosures, Matches,
    Message, Pose, RobotId, MAX_DESCRIPTORS, MAX_LOOP_CLOSURES, MAX_MATCHES,
};
use serde::Serialize;

use doorslam_place_recognition::candidates::{CandidateChain, ChainConfig, ChainStats};
use doorslam_place_recognition::eval::{EvalError, EvalSet};
use doorslam_place_recognition::index::MatchIndex;

/// A verified closure further than this from the truth is false (metres, degrees).
pub const FALSE_M: f64 = 2.0;
pub const FALSE_DEG: f64 = 15.0;

/// A false closure whose two cameras are truly within this distance saw (part of) the
/// same place: PnP found a wrong pose on a true neighbour, not a look-alike elsewhere.
pub const NEAR_M: f64 = 10.0;

/// Pairwise consistency of two closures of one robot pair (the back-end's PCM cycle,
/// DOOR-SLAM eq. 1, with metric bounds instead of a Mahalanobis gate): the cycle through
/// both closures and each robot's odometry may miss the identity by at most
/// `CONSENSUS_M + CONSENSUS_DRIFT ×` (odometry length of the cycle) and `CONSENSUS_DEG`.
/// Chosen a priori (PnP's worst true error was 0.57 m / 1.6°, VO drift ≈ 1 %), not fitted.
pub const CONSENSUS_M: f64 = 1.0;
pub const CONSENSUS_DRIFT: f64 = 0.03;
pub const CONSENSUS_DEG: f64 = 5.0;
/// A robot pair's closures are accepted only as a consistent set of at least this many
/// (a lone closure cannot be checked against anything; the back-end's `min_clique`).
pub const CONSENSUS_MIN: usize = 2;

/// What `--verify` measures.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ChainReport {
    /// The chain's stages, summed over the robot pairs.
    pub chain: ChainStats,
    /// Pairs sent to verification (the chain's confirmed pairs).
    pub verification_requests: u64,
    /// Distinct candidate keyframes whose packet was sent.
    pub packets: u64,
    pub verified: u64,
    pub verified_true: u64,
    pub verified_false: u64,
    pub verified_aliased: u64,
    /// False verified closures that are not aliased copies, by the true distance of their
    /// cameras: within [`NEAR_M`] (a wrong pose on a true neighbour) or beyond.
    pub verified_false_near: u64,
    pub verified_false_far: u64,
    /// After the pair consensus (the largest pairwise-consistent set of each robot pair's
    /// verified closures, at least [`CONSENSUS_MIN`]): closures kept, false and aliased
    /// among them, and the true overlaps they still join.
    pub accepted: u64,
    pub accepted_false: u64,
    pub accepted_aliased: u64,
    pub accepted_recall: f64,
    /// Verification refusals by reason.
    pub rejected: BTreeMap<String, u64>,
    pub true_overlaps: u64,
    pub true_overlaps_found: u64,
    pub verified_recall: f64,
    pub bytes: ChainBytes,
    /// `bytes.total / verified_true` (`None` without a true closure).
    pub bytes_per_true_closure: Option<f64>,
    /// Largest error of a true verified closure (m, degrees).
    pub worst_true_error_m: f64,
    pub worst_true_error_deg: f64,
    /// Time of the verifications (ms, one thread).
    pub ms_per_verification: f64,
}

/// Bytes of each message kind of the exchange (encoded messages, headers included).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ChainBytes {
    pub descriptors: u64,
    pub matches: u64,
    pub packets: u64,
    pub closures: u64,
    pub total: u64,
}

/// The inputs of one keyframe: its wire descriptor and its front-end features.
#[derive(Debug, Clone)]
pub struct ChainInput<'a> {
    pub set: &'a EvalSet,
    /// Wire-form descriptor of every keyframe of `set` (128 values).
    pub descriptors: &'a [Vec<f32>],
    /// The front-end's keyframe features of every keyframe (strongest first).
    pub features: &'a [Vec<Feature>],
    /// Rectified camera of each keyframe's robot.
    pub calibration: &'a [StereoCalibration],
}

/// Robots of the set in name order, and each keyframe's robot number and id (its frame).
fn robots(set: &EvalSet) -> (Vec<String>, Vec<(u8, u64)>) {
    let names: Vec<String> = set
        .keyframes
        .iter()
        .map(|k| k.robot.clone())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    let of = |r: &str| names.iter().position(|n| n == r).unwrap_or(0) as u8;
    let ids = set
        .keyframes
        .iter()
        .map(|k| (of(&k.robot), k.frame as u64))
        .collect();
    (names, ids)
}

/// Encoded size of a message from robot `robot` (ids "r0".."r51").
fn encoded(robot: u8, body: impl Into<Body>) -> Result<u64, String> {
    let sender = RobotId::new(&format!("r{robot}")).map_err(|e| e.to_string())?;
    let header = Header {
        sender,
        epoch: 1,
        sequence: 1,
    };
    Ok(Message::new(header, body).encoded_len() as u64)
}

/// Runs the chain over every pair of robots; errors only on inputs that cannot be encoded
/// (a descriptor that is not 128 finite values, an id beyond the key space).
pub fn evaluate_chain(
    input: &ChainInput<'_>,
    chain_config: &ChainConfig,
    verify_config: &VerifyConfig,
    max_packet_features: usize,
) -> Result<ChainReport, String> {
    let set = input.set;
    let (names, ids) = robots(set);
    let mut report = ChainReport::default();
    let by_key: BTreeMap<u64, usize> = ids
        .iter()
        .enumerate()
        .map(|(i, &(r, f))| key::symbol(r, f).map(|k| (k, i)))
        .collect::<Result<_, _>>()
        .map_err(|e| e.to_string())?;
    let wire = |i: usize| -> Result<Descriptor, String> {
        let k = key::symbol(ids[i].0, ids[i].1).map_err(|e| e.to_string())?;
        Descriptor::quantize(k, &input.descriptors[i]).map_err(|e| format!("keyframe {i}: {e}"))
    };
    let mut found: HashSet<(usize, usize)> = HashSet::new();
    let mut accepted_found: HashSet<(usize, usize)> = HashSet::new();
    let mut verify_ms = Vec::new();
    for beta in 0..names.len() as u8 {
        let own: Vec<usize> = (0..ids.len()).filter(|&i| ids[i].0 == beta).collect();
        let mut index = MatchIndex::new(beta, chain_config.max_distance, 0);
        for &i in &own {
            index.insert(wire(i)?).map_err(|e| e.to_string())?;
        }
        for alpha in 0..beta {
            let queries: Vec<usize> = (0..ids.len()).filter(|&i| ids[i].0 == alpha).collect();
            let received = queries
                .iter()
                .map(|&i| wire(i))
                .collect::<Result<Vec<_>, _>>()?;
            for chunk in received.chunks(MAX_DESCRIPTORS) {
                let range = key::index(chunk[0].key)..key::index(chunk[chunk.len() - 1].key) + 1;
                report.bytes.descriptors += encoded(
                    alpha,
                    Descriptors {
                        robot: alpha,
                        keyframes: range,
                        descriptors: chunk.to_vec(),
                    },
                )?;
            }
            let mut chain = CandidateChain::new(chain_config.clone());
            let mut pairs = chain.push(&index, &received);
            pairs.extend(chain.flush());
            add_stats(&mut report.chain, chain.stats());
            for chunk in pairs.chunks(MAX_MATCHES) {
                report.bytes.matches += encoded(
                    beta,
                    Matches {
                        matches: chunk.to_vec(),
                    },
                )?;
            }
            report.verification_requests += pairs.len() as u64;
            let mut packets = BTreeMap::new();
            let mut closures = Vec::new();
            let mut pair_verified: Vec<Verified> = Vec::new();
            for m in &pairs {
                let (q, c) = (by_key[&m.query], by_key[&m.candidate]);
                if let std::collections::btree_map::Entry::Vacant(slot) = packets.entry(c) {
                    let packet = to_packet(
                        m.candidate,
                        &input.calibration[c],
                        &input.features[c],
                        max_packet_features,
                    )
                    .map_err(|e| format!("packet of keyframe {c}: {e}"))?;
                    report.bytes.packets += encoded(beta, packet.clone())?;
                    slot.insert(packet);
                }
                let (remote_calib, remote) =
                    from_packet(&packets[&c], verify_config.disparity_sigma_px);
                let start = std::time::Instant::now();
                let outcome = verify(
                    &input.calibration[q],
                    &input.features[q],
                    &remote_calib,
                    &remote,
                    verify_config,
                );
                verify_ms.push(start.elapsed().as_secs_f64() * 1e3);
                let verified = match outcome {
                    Ok(v) => v,
                    Err(r) => {
                        *report.rejected.entry(r.name().into()).or_default() += 1;
                        continue;
                    }
                };
                report.verified += 1;
                // X_c⁻¹ X_q: the query's camera in the candidate's frame.
                let truth = set.keyframes[c].pose.inverse() * set.keyframes[q].pose;
                let (deg, m_err) = pose_error(&truth, &verified.relative);
                let is_false = m_err > FALSE_M || deg > FALSE_DEG;
                let aliased = set.aliased.contains(&(q, c));
                pair_verified.push(Verified {
                    q,
                    c,
                    relative: verified.relative,
                    is_false,
                    aliased,
                });
                if is_false {
                    report.verified_false += 1;
                    if aliased {
                        report.verified_aliased += 1;
                    } else if truth.translation.vector.norm() <= NEAR_M {
                        report.verified_false_near += 1;
                    } else {
                        report.verified_false_far += 1;
                    }
                } else {
                    report.verified_true += 1;
                    report.worst_true_error_m = report.worst_true_error_m.max(m_err);
                    report.worst_true_error_deg = report.worst_true_error_deg.max(deg);
                    found.insert((q, c));
                }
                // The closure α sends: from its keyframe to β's (as the team link does).
                let (z, information) =
                    reverse_measurement(&verified.relative, &verified.information);
                if let (Ok(relative), Ok(information)) =
                    (Pose::from_se3(&z), Information::from_matrix(&information))
                {
                    closures.push(LoopClosure {
                        key_a: m.query,
                        key_b: m.candidate,
                        relative,
                        information,
                        inliers: verified.inliers as u32,
                    });
                }
            }
            for &i in &consensus(set, &pair_verified) {
                let v = &pair_verified[i];
                report.accepted += 1;
                if v.is_false {
                    report.accepted_false += 1;
                    report.accepted_aliased += u64::from(v.aliased);
                } else {
                    accepted_found.insert((v.q, v.c));
                }
            }
            report.packets += packets.len() as u64;
            for chunk in closures.chunks(MAX_LOOP_CLOSURES) {
                report.bytes.closures += encoded(
                    alpha,
                    LoopClosures {
                        closures: chunk.to_vec(),
                    },
                )?;
            }
        }
    }
    report.true_overlaps = set.overlaps.len() as u64;
    let joined = |found: &HashSet<(usize, usize)>| {
        set.overlaps
            .iter()
            .filter(|(a, b)| {
                a.iter().any(|&q| {
                    b.iter()
                        .any(|&c| found.contains(&(q, c)) || found.contains(&(c, q)))
                })
            })
            .count() as u64
    };
    report.true_overlaps_found = joined(&found);
    report.verified_recall =
        report.true_overlaps_found as f64 / (report.true_overlaps as f64).max(1.0);
    report.accepted_recall =
        joined(&accepted_found) as f64 / (report.true_overlaps as f64).max(1.0);
    let b = &mut report.bytes;
    b.total = b.descriptors + b.matches + b.packets + b.closures;
    report.bytes_per_true_closure =
        (report.verified_true > 0).then(|| b.total as f64 / report.verified_true as f64);
    report.ms_per_verification = median(&mut verify_ms);
    Ok(report)
}

/// A verified closure of one robot pair: query and candidate keyframes, the measured
/// `X_c⁻¹ X_q`, and what ground truth says of it.
struct Verified {
    q: usize,
    c: usize,
    relative: doorslam_geometry::SE3,
    is_false: bool,
    aliased: bool,
}

/// Whether two closures of one robot pair agree: the cycle `(X_c1⁻¹ X_c2) z₂ (X_q2⁻¹ X_q1)
/// z₁⁻¹` (each robot's odometry between its two keyframes, here its trajectory) is the
/// identity within the [`CONSENSUS_M`] / [`CONSENSUS_DRIFT`] / [`CONSENSUS_DEG`] bounds.
/// Ground truth enters only as the robots' odometry, never as the closures' truth.
fn consistent(set: &EvalSet, a: &Verified, b: &Verified) -> bool {
    let pose = |i: usize| &set.keyframes[i].pose;
    let odo_c = pose(a.c).inverse() * pose(b.c);
    let odo_q = pose(b.q).inverse() * pose(a.q);
    let cycle = odo_c * b.relative * odo_q * a.relative.inverse();
    let lever = odo_c.translation.vector.norm() + odo_q.translation.vector.norm();
    cycle.translation.vector.norm() <= CONSENSUS_M + CONSENSUS_DRIFT * lever
        && cycle.rotation.angle().to_degrees() <= CONSENSUS_DEG
}

/// The largest pairwise-consistent set of a robot pair's closures, or nothing below
/// [`CONSENSUS_MIN`]. Look-alike places (the aliased building copies) each imply another
/// offset between the two robots' frames, so they disagree with the true closures.
fn consensus(set: &EvalSet, closures: &[Verified]) -> Vec<usize> {
    largest_consistent_set(closures.len(), |i, j| {
        consistent(set, &closures[i], &closures[j])
    })
}

/// The maximum clique of the agreement graph of `n` closures (`agree(i, j)` for `i < j`),
/// found by the back-end's PCM search ([`maximum_clique`]: exact, deterministic), sorted;
/// empty when it has fewer than [`CONSENSUS_MIN`] closures. Exact matters: a greedy pass
/// that starts from the closure with most partners can be led by one closure that agrees
/// with members of two rival sets into keeping neither whole (the test below).
fn largest_consistent_set(n: usize, agree: impl Fn(usize, usize) -> bool) -> Vec<usize> {
    let mut graph = ConsistencyGraph::new(n);
    for i in 0..n {
        for j in i + 1..n {
            if agree(i, j) {
                // Both indices are below n: add_edge cannot fail.
                let _ = graph.add_edge(i, j);
            }
        }
    }
    let mut kept = maximum_clique(&graph, &CliqueOptions::default()).vertices;
    if kept.len() < CONSENSUS_MIN {
        kept.clear();
    }
    kept
}

fn add_stats(total: &mut ChainStats, s: &ChainStats) {
    total.queries += s.queries;
    total.ranked += s.ranked;
    total.confirmed += s.confirmed;
    total.unconfirmed += s.unconfirmed;
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Per keyframe its features and rectified camera, and the milliseconds per keyframe.
pub type KeyframeFeatures = (Vec<Vec<Feature>>, Vec<StereoCalibration>, f64);

/// The front-end's keyframe features of every keyframe of `set` (GFTT + ORB with a stereo
/// match, strongest first: what a `Keyframe` sample carries), the rectified camera of each,
/// and the milliseconds per keyframe; `progress(done, total)` hears about each.
pub fn keyframe_features(
    set: &EvalSet,
    vo: &doorslam_frontend::VoConfig,
    progress: &dyn Fn(usize, usize),
) -> Result<KeyframeFeatures, EvalError> {
    let mut cameras: BTreeMap<String, (StereoCalibration, doorslam_frontend::StereoVo)> =
        BTreeMap::new();
    let input = |path: &std::path::Path, msg: String| EvalError::Input {
        path: path.to_path_buf(),
        msg,
    };
    let (mut features, mut calibration) = (Vec::new(), Vec::new());
    let mut seconds = 0.0;
    for (i, k) in set.keyframes.iter().enumerate() {
        if !cameras.contains_key(&k.robot) {
            let dir = set
                .robot_dirs
                .get(&k.robot)
                .ok_or_else(|| input(&k.image, format!("no folder for robot {}", k.robot)))?;
            let camera = doorslam_dataset::Dataset::open(dir)?.stereo()?;
            if camera.rectifier.is_some() {
                return Err(input(
                    dir,
                    "raw (EuRoC) frames need rectifying: --verify reads rectified \
                     KITTI-layout folders and `sim world` outputs"
                        .into(),
                ));
            }
            let calib = camera.calibration;
            let stereo = doorslam_frontend::StereoVo::new(calib, vo.clone())
                .map_err(|e| input(dir, e.to_string()))?;
            cameras.insert(k.robot.clone(), (calib, stereo));
        }
        let (calib, stereo) = cameras
            .get_mut(&k.robot)
            .ok_or_else(|| input(&k.image, "no camera".into()))?;
        let right = k
            .right
            .as_ref()
            .ok_or_else(|| input(&k.image, "no right image: --verify needs stereo".into()))?;
        let (w, h, left_px) = doorslam_dataset::read_gray_png(&k.image)?;
        let (wr, hr, right_px) = doorslam_dataset::read_gray_png(right)?;
        if (w, h) != (wr, hr) {
            return Err(input(
                right,
                format!("{wr}x{hr}, the left image is {w}x{h}"),
            ));
        }
        let start = std::time::Instant::now();
        let bad = |e: doorslam_vision::VisionError| input(&k.image, e.to_string());
        let left = doorslam_frontend::Gray::new(w as usize, h as usize, &left_px).map_err(bad)?;
        let right = doorslam_frontend::Gray::new(w as usize, h as usize, &right_px).map_err(bad)?;
        let f = stereo
            .keyframe_features(&left, &right)
            .map_err(|e| input(&k.image, e.to_string()))?;
        seconds += start.elapsed().as_secs_f64();
        features.push(f);
        calibration.push(*calib);
        progress(i + 1, set.keyframes.len());
    }
    Ok((
        features,
        calibration,
        1e3 * seconds / set.keyframes.len().max(1) as f64,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The agreement of a trap for a greedy pass: closures 1-4 agree with one another (the
    /// true offset between two robots); closure 0 agrees with 1 and with 5-8, which agree
    /// with nothing else (each a look-alike place implying its own offset). 0 has the most
    /// partners, so a greedy pass by degree keeps 0, then 1, and then nothing else agrees
    /// with both.
    fn trap(i: usize, j: usize) -> bool {
        let (i, j) = (i.min(j), i.max(j));
        let truth = |v: usize| (1..=4).contains(&v);
        (truth(i) && truth(j)) || (i == 0 && (j == 1 || (5..=8).contains(&j)))
    }

    /// The greedy pass this stage used before: closures by descending number of partners,
    /// each kept if it agrees with all kept so far.
    fn greedy(n: usize, agree: impl Fn(usize, usize) -> bool) -> Vec<usize> {
        let degree: Vec<usize> = (0..n)
            .map(|i| (0..n).filter(|&j| j != i && agree(i, j)).count())
            .collect();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&i| (std::cmp::Reverse(degree[i]), i));
        let mut kept: Vec<usize> = Vec::new();
        for i in order {
            if kept.iter().all(|&k| agree(i, k)) {
                kept.push(i);
            }
        }
        kept.sort_unstable();
        kept
    }

    #[test]
    fn the_consensus_is_the_maximum_clique_where_a_greedy_pass_is_trapped() {
        assert_eq!(
            greedy(9, trap),
            vec![0, 1],
            "the scene must trap the greedy pass"
        );
        assert_eq!(largest_consistent_set(9, trap), vec![1, 2, 3, 4]);
    }

    #[test]
    fn fewer_than_the_minimum_agreeing_closures_keep_nothing() {
        // No two closures agree: every clique is a single closure.
        assert!(largest_consistent_set(5, |_, _| false).is_empty());
        assert!(largest_consistent_set(0, |_, _| true).is_empty());
        assert_eq!(largest_consistent_set(2, |_, _| true), vec![0, 1]);
    }
}
