//! Structured messages built from the fuzz input through the public constructors (which
//! quantize and validate): whatever they accept encodes, `encoded_len` is exact, and the
//! decoder returns the same message.
#![no_main]

use doorslam_geometry::key::symbol;
use doorslam_ipc::wire::*;
use libfuzzer_sys::arbitrary::{Result, Unstructured};
use libfuzzer_sys::fuzz_target;

fn key(u: &mut Unstructured<'_>) -> Result<u64> {
    let robot = u.int_in_range(0..=51u8)?;
    let index = u.int_in_range(0..=doorslam_geometry::key::MAX_INDEX)?;
    Ok(symbol(robot, index).expect("in range"))
}

fn pose(u: &mut Unstructured<'_>) -> Result<Option<Pose>> {
    let raw: [f32; 7] = u.arbitrary()?;
    Ok(Pose::from_array(raw).ok())
}

fn information(u: &mut Unstructured<'_>) -> Result<Option<Information>> {
    let l: [[f32; 6]; 6] = u.arbitrary()?;
    // Ω = L Lᵀ of a lower-triangular L, upper triangle row-major.
    let mut upper = [0f64; 21];
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            upper[k] = (0..=r)
                .map(|i| f64::from(l[r][i]) * f64::from(l[c][i]))
                .sum();
            k += 1;
        }
    }
    Ok(Information::from_upper(&upper).ok())
}

fn body(u: &mut Unstructured<'_>) -> Result<Option<Body>> {
    Ok(Some(match u.int_in_range(0..=9u8)? {
        0 => Body::Hello(Hello {
            robot: u.int_in_range(0..=51)?,
            heard: if u.arbitrary()? {
                Some(u.int_in_range(0..=u64::MAX - 1)?)
            } else {
                None
            },
            base: u.arbitrary()?,
        }),
        1 => {
            let robot = u.int_in_range(0..=51u8)?;
            let start = u.int_in_range(0..=1u64 << 40)?;
            let mut index = start;
            let mut descriptors = Vec::new();
            for i in 0..u.int_in_range(0..=20)? {
                index += u.int_in_range(u64::from(i > 0)..=1000)?;
                let v: Vec<f32> = (0..DESCRIPTOR_DIM)
                    .map(|_| u.arbitrary())
                    .collect::<Result<_>>()?;
                match Descriptor::quantize(symbol(robot, index).expect("in range"), &v) {
                    Ok(d) => descriptors.push(d),
                    Err(_) => return Ok(None),
                }
            }
            let end = index + 1 + u.int_in_range(0..=1000)?;
            Body::Descriptors(Descriptors {
                robot,
                keyframes: start..end,
                descriptors,
            })
        }
        2 => {
            let mut matches = Vec::new();
            for _ in 0..u.int_in_range(0..=50)? {
                matches.push(Match {
                    query: key(u)?,
                    candidate: key(u)?,
                    distance: u.int_in_range(0..=1 << 20)? as f32 / 1024.0,
                });
            }
            Body::Matches(Matches { matches })
        }
        3 => {
            let key = key(u)?;
            let Ok(camera) = VerificationCamera::new(
                u.arbitrary()?,
                u.arbitrary()?,
                u.arbitrary()?,
                u.arbitrary()?,
                u.arbitrary()?,
            ) else {
                return Ok(None);
            };
            let mut features = Vec::new();
            for _ in 0..u.int_in_range(0..=MAX_FEATURES)? {
                match VerificationFeature::quantize(u.arbitrary()?, u.arbitrary()?, u.arbitrary()?) {
                    Ok(f) => features.push(f),
                    Err(_) => return Ok(None),
                }
            }
            Body::VerificationFeatures(VerificationFeatures {
                key,
                camera,
                features,
            })
        }
        4 => {
            let mut closures = Vec::new();
            for _ in 0..u.int_in_range(0..=8)? {
                let (key_a, key_b) = (key(u)?, key(u)?);
                let (Some(relative), Some(information)) = (pose(u)?, information(u)?) else {
                    return Ok(None);
                };
                closures.push(LoopClosure {
                    key_a,
                    key_b,
                    relative,
                    information,
                    inliers: u.arbitrary()?,
                });
            }
            if u.arbitrary()? {
                Body::LoopClosures(LoopClosures { closures })
            } else {
                // A separator graph: key a of every edge is the origin's, poses compact,
                // informations shared as the wire shares them.
                let origin = u.int_in_range(0..=51u8)?;
                let version = u.int_in_range(1..=u64::MAX)?;
                let base = if u.arbitrary()? { 0 } else { u.int_in_range(0..=version - 1)? };
                let mut removed = Vec::new();
                if base > 0 {
                    for _ in 0..u.int_in_range(0..=4)? {
                        let a = symbol(origin, u.int_in_range(0..=1u64 << 40)?).expect("in range");
                        removed.push((a, key(u)?));
                    }
                }
                let mut edges: Vec<GraphEdge> = Vec::new();
                for c in closures {
                    let key_a = symbol(origin, doorslam_geometry::key::index(c.key_a)).expect("in range");
                    let Ok(relative) = CompactPose::quantize(c.relative.se3()) else {
                        return Ok(None);
                    };
                    let information = match edges.last() {
                        Some(l) if l.information.parts() == c.information.parts() => {
                            std::sync::Arc::clone(&l.information)
                        }
                        _ => std::sync::Arc::new(c.information),
                    };
                    edges.push(GraphEdge {
                        key_a,
                        key_b: c.key_b,
                        relative,
                        information,
                    });
                }
                Body::SeparatorGraph(SeparatorGraph {
                    origin,
                    version,
                    base,
                    removed,
                    edges,
                })
            }
        }
        6 => {
            let mut path = Vec::new();
            let mut seen = 0u64;
            for _ in 0..u.int_in_range(1..=52)? {
                let r = u.int_in_range(0..=51u8)?;
                if seen & (1 << r) == 0 {
                    seen |= 1 << r;
                    path.push(r);
                }
            }
            Body::Route(Route {
                path,
                subtree: u.int_in_range(0..=(1u64 << 52) - 1)?,
                session: u.arbitrary()?,
            })
        }
        7 => {
            if u.arbitrary()? {
                Body::TeamMap(TeamMap::Request {
                    known: u.arbitrary()?,
                })
            } else {
                let robot = u.int_in_range(0..=51u8)?;
                let mut index = u.int_in_range(0..=1u64 << 40)?;
                let mut poses = Vec::new();
                for _ in 0..u.int_in_range(0..=50)? {
                    index += u.int_in_range(1..=1000u64)?;
                    let Some(pose) = pose(u)? else {
                        return Ok(None);
                    };
                    let Ok(c) = CompactPose::quantize(pose.se3()) else {
                        return Ok(None);
                    };
                    poses.push((symbol(robot, index).expect("in range"), c));
                }
                Body::TeamMap(TeamMap::Trajectory(Trajectory {
                    anchor: u.int_in_range(0..=51u8)?,
                    version: u.arbitrary()?,
                    total: u.int_in_range(poses.len() as u64..=u64::MAX)?,
                    poses,
                }))
            }
        }
        8 => {
            let (optimization, round) = (u.arbitrary()?, u.arbitrary()?);
            let stage = [Stage::Rotation, Stage::Pose, Stage::Refine][u.int_in_range(0..=2usize)?];
            let flags = if u.arbitrary()? { ESTIMATES_CONVERGED } else { 0 };
            let anchor = u.int_in_range(0..=51u8)?;
            let robot = u.int_in_range(0..=51u8)?;
            let mut index = u.int_in_range(0..=1u64 << 40)?;
            let mut estimates = Vec::new();
            for _ in 0..u.int_in_range(0..=50)? {
                index += u.int_in_range(1..=1000u64)?;
                let key = symbol(robot, index).expect("in range");
                let value = if stage == Stage::Rotation {
                    let m: [[f64; 3]; 3] = [
                        [u.arbitrary()?, u.arbitrary()?, u.arbitrary()?],
                        [u.arbitrary()?, u.arbitrary()?, u.arbitrary()?],
                        [u.arbitrary()?, u.arbitrary()?, u.arbitrary()?],
                    ];
                    match RelaxedRotation::quantize(&m) {
                        Ok(r) => Estimate::Rotation(r),
                        Err(_) => return Ok(None),
                    }
                } else {
                    let Some(pose) = pose(u)? else {
                        return Ok(None);
                    };
                    match CompactPose::quantize(pose.se3()) {
                        Ok(c) => Estimate::Pose(c),
                        Err(_) => return Ok(None),
                    }
                };
                estimates.push(PoseEstimate { key, value });
            }
            Body::PoseEstimates(PoseEstimates {
                optimization,
                round,
                stage,
                flags,
                anchor,
                estimates,
            })
        }
        _ => {
            let epoch = u.arbitrary()?;
            let kind = Kind::ALL[u.int_in_range(0..=Kind::ALL.len() - 1)?];
            let next = u.int_in_range(0..=1u64 << 50)?;
            let mut end = next;
            let mut received = Vec::new();
            for _ in 0..u.int_in_range(0..=MAX_ACK_RANGES)? {
                let start = end + u.int_in_range(1..=1000u64)?;
                end = start + u.int_in_range(1..=1000u64)?;
                received.push(start..end);
            }
            Body::Ack(Ack {
                epoch,
                kind,
                next,
                received,
            })
        }
    }))
}

fn message(u: &mut Unstructured<'_>) -> Result<Option<Message>> {
    let len = u.int_in_range(1..=MAX_ROBOT_ID_LEN)?;
    let alphabet = b"abcdefghijklmnopqrstuvwxyz0123456789_-";
    let id: String = (0..len)
        .map(|_| u.choose(alphabet).map(|&c| c as char))
        .collect::<Result<_>>()?;
    let header = Header {
        sender: RobotId::new(&id).expect("valid id"),
        epoch: u.arbitrary()?,
        sequence: u.arbitrary()?,
    };
    Ok(body(u)?.map(|body| Message { header, body }))
}

fuzz_target!(|data: &[u8]| {
    let mut u = Unstructured::new(data);
    let Ok(Some(m)) = message(&mut u) else {
        return;
    };
    let b = m
        .encode()
        .expect("a message built by the constructors encodes");
    assert_eq!(m.encoded_len(), b.len());
    assert_eq!(Message::decode(&b).expect("decodes"), m);
});
