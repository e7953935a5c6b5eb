//! What the back-end accepts from the other services, checked where it enters: a sample
//! that fails here is rejected, counted and logged with its robot, topic and field, and
//! never journaled (a journaled NaN would poison every later optimization, also after a
//! restart). The rules are the g2o reader's, from `doorslam-geometry`: finite values, unit
//! quaternions within [`doorslam_geometry::UNIT_QUATERNION_TOLERANCE`], symmetric
//! positive-definite information, ids that fit in a multi-robot key.

use doorslam_geometry::information::matrix_from_upper;
use doorslam_geometry::key::{self, MAX_INDEX};
use doorslam_geometry::{check_information, pose_from_array, InformationCheck, TangentMatrix, SE3};
use doorslam_ipc::{
    Keyframe, KeyframeSource, LoopClosure, OdometryEdge, Topic, MAX_KEYFRAME_FEATURES,
};

/// A received sample that is refused: which robot sent it on which topic, which field is
/// wrong and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{topic} sample from robot {robot}: field {field}: {reason}")]
pub struct InputError {
    pub topic: &'static str,
    /// The robot the sample claims to come from.
    pub robot: u32,
    pub field: &'static str,
    pub reason: String,
}

/// A keyframe that passed [`check_keyframe`].
#[derive(Debug, Clone, PartialEq)]
pub struct KeyframeInput {
    pub id: u64,
    pub stamp_ns: u64,
    pub pose: SE3,
    pub source: KeyframeSource,
}

/// An odometry edge that passed [`check_odometry`].
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryInput {
    pub from: u64,
    pub to: u64,
    pub relative: SE3,
    pub information: TangentMatrix,
}

/// A loop closure that passed [`check_closure`]: keys are multi-robot keys.
#[derive(Debug, Clone, PartialEq)]
pub struct ClosureInput {
    pub key_a: u64,
    pub key_b: u64,
    pub relative: SE3,
    pub information: TangentMatrix,
    pub inliers: u32,
}

struct Check {
    topic: Topic,
    robot: u32,
}

impl Check {
    fn fail(&self, field: &'static str, reason: impl Into<String>) -> InputError {
        InputError {
            topic: self.topic.as_str(),
            robot: self.robot,
            field,
            reason: reason.into(),
        }
    }
    /// The sample must come from the robot this back-end serves.
    fn robot_is(&self, expected: u32) -> Result<(), InputError> {
        if self.robot == expected {
            Ok(())
        } else {
            Err(self.fail(
                "robot",
                format!("this back-end serves robot {expected}, not {}", self.robot),
            ))
        }
    }
    fn id(&self, field: &'static str, id: u64) -> Result<u64, InputError> {
        if id <= MAX_INDEX {
            Ok(id)
        } else {
            Err(self.fail(
                field,
                format!("id {id} does not fit in a key (at most 2^56 - 1)"),
            ))
        }
    }
    fn pose(&self, field: &'static str, p: &[f64; 7]) -> Result<SE3, InputError> {
        pose_from_array(p).map_err(|e| self.fail(field, format!("{e} ({p:?})")))
    }
    fn information(
        &self,
        field: &'static str,
        upper: &[f64; 21],
    ) -> Result<TangentMatrix, InputError> {
        let m = matrix_from_upper(upper);
        check_information(&m, 6, InformationCheck::PositiveDefinite)
            .map_err(|e| self.fail(field, e.to_string()))?;
        Ok(m)
    }
}

/// Checks a keyframe for the back-end of robot `robot_index`.
pub fn check_keyframe(kf: &Keyframe, robot_index: u32) -> Result<KeyframeInput, InputError> {
    let c = Check {
        topic: Topic::Keyframes,
        robot: kf.robot,
    };
    c.robot_is(robot_index)?;
    let source = KeyframeSource::try_from(kf.source).map_err(|v| {
        c.fail(
            "source",
            format!("{v} is no keyframe source (0 = visual odometry, 1 = simulated truth)"),
        )
    })?;
    let id = c.id("id", kf.id)?;
    let pose = c.pose("pose", &kf.pose)?;
    let n = kf.n_features as usize;
    if n > MAX_KEYFRAME_FEATURES {
        return Err(c.fail(
            "n_features",
            format!("{n}, at most {MAX_KEYFRAME_FEATURES}"),
        ));
    }
    if let Some(k) = kf.features[..n]
        .iter()
        .position(|f| !f.uv.iter().chain(&f.point).all(|v| v.is_finite()))
    {
        return Err(c.fail(
            "features",
            format!("feature {k} has a non-finite pixel or point"),
        ));
    }
    Ok(KeyframeInput {
        id,
        stamp_ns: kf.stamp_ns,
        pose,
        source,
    })
}

/// Checks an odometry edge for the back-end of robot `robot_index`.
pub fn check_odometry(e: &OdometryEdge, robot_index: u32) -> Result<OdometryInput, InputError> {
    let c = Check {
        topic: Topic::Odometry,
        robot: e.robot,
    };
    c.robot_is(robot_index)?;
    odometry_fields(&c, e.from, e.to, &e.relative, &e.information)
}

/// The same rules for an edge read back from the journal (written by an older build,
/// before these checks existed).
pub(crate) fn check_journaled_odometry(
    robot_index: u32,
    from: u64,
    to: u64,
    relative: &[f64; 7],
    information: &[f64; 21],
) -> Result<OdometryInput, InputError> {
    let c = Check {
        topic: Topic::Odometry,
        robot: robot_index,
    };
    odometry_fields(&c, from, to, relative, information)
}

/// The same rules for a keyframe read back from the journal.
pub(crate) fn check_journaled_keyframe(
    robot_index: u32,
    id: u64,
    pose: &[f64; 7],
) -> Result<(u64, SE3), InputError> {
    let c = Check {
        topic: Topic::Keyframes,
        robot: robot_index,
    };
    Ok((c.id("id", id)?, c.pose("pose", pose)?))
}

fn odometry_fields(
    c: &Check,
    from: u64,
    to: u64,
    relative: &[f64; 7],
    information: &[f64; 21],
) -> Result<OdometryInput, InputError> {
    let from = c.id("from", from)?;
    let to = c.id("to", to)?;
    if from == to {
        return Err(c.fail("to", format!("edge from keyframe {from} to itself")));
    }
    Ok(OdometryInput {
        from,
        to,
        relative: c.pose("relative", relative)?,
        information: c.information("information", information)?,
    })
}

/// Checks a loop closure for the back-end of robot `robot_index`: the rules of
/// [`check_closure`], and one of its keyframes must be this robot's: an inter-robot
/// closure (the other keyframe another robot's) or one of this robot's own loops (both its
/// own: the team link's intra-robot chain).
pub fn check_own_closure(lc: &LoopClosure, robot_index: u32) -> Result<ClosureInput, InputError> {
    let c = check_closure(lc)?;
    own_closure_of(c, robot_index)
}

fn own_closure_of(c: ClosureInput, robot_index: u32) -> Result<ClosureInput, InputError> {
    let check = Check {
        topic: Topic::Closures,
        robot: robot_index,
    };
    let (ra, rb) = (key::robot(c.key_a), key::robot(c.key_b));
    let me = u8::try_from(robot_index).ok();
    if ra != me && rb != me {
        return Err(check.fail(
            "robot_a",
            format!(
                "neither {} nor {} is a keyframe of robot {robot_index}",
                key::label(c.key_a),
                key::label(c.key_b)
            ),
        ));
    }
    Ok(c)
}

/// The same rules for a closure read back from the journal.
pub(crate) fn check_journaled_closure(
    robot_index: u32,
    key_a: u64,
    key_b: u64,
    relative: &[f64; 7],
    information: &[f64; 21],
    inliers: u64,
) -> Result<ClosureInput, InputError> {
    let c = Check {
        topic: Topic::Closures,
        robot: robot_index,
    };
    let has_robot = |field, k: u64| {
        key::robot(k)
            .map(|_| k)
            .ok_or_else(|| c.fail(field, format!("{k:#x} is not a multi-robot key")))
    };
    let input = ClosureInput {
        key_a: has_robot("key_a", key_a)?,
        key_b: has_robot("key_b", key_b)?,
        relative: c.pose("relative", relative)?,
        information: c.information("information", information)?,
        inliers: u32::try_from(inliers).unwrap_or(u32::MAX),
    };
    own_closure_of(input, robot_index)
}

/// Checks a loop closure between keyframes of two robots of the team (or one).
pub fn check_closure(lc: &LoopClosure) -> Result<ClosureInput, InputError> {
    let c = Check {
        topic: Topic::Closures,
        robot: lc.robot_a,
    };
    let robot = |field, r: u32| key::robot_index(r).map_err(|e| c.fail(field, e.to_string()));
    let (ra, rb) = (robot("robot_a", lc.robot_a)?, robot("robot_b", lc.robot_b)?);
    let ka = key::symbol(ra, c.id("keyframe_a", lc.keyframe_a)?)
        .map_err(|e| c.fail("keyframe_a", e.to_string()))?;
    let kb = key::symbol(rb, c.id("keyframe_b", lc.keyframe_b)?)
        .map_err(|e| c.fail("keyframe_b", e.to_string()))?;
    if ka == kb {
        return Err(c.fail(
            "keyframe_b",
            format!("closure of {} with itself", key::label(ka)),
        ));
    }
    Ok(ClosureInput {
        key_a: ka,
        key_b: kb,
        relative: c.pose("relative", &lc.relative)?,
        information: c.information("information", &lc.information)?,
        inliers: lc.inliers,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use doorslam_geometry::information::upper_from_diagonal;
    use doorslam_ipc::Feature;

    fn keyframe() -> Keyframe {
        Keyframe {
            robot: 1,
            source: KeyframeSource::VisualOdometry as u32,
            id: 3,
            frame_seq: 30,
            stamp_ns: 5,
            pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            n_features: 0,
            reserved: 0,
            features: [Feature::default(); MAX_KEYFRAME_FEATURES],
        }
    }

    fn edge() -> OdometryEdge {
        OdometryEdge {
            robot: 1,
            reserved: 0,
            from: 2,
            to: 3,
            stamp_ns: 0,
            relative: [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            information: upper_from_diagonal([1e4, 1e4, 1e4, 1e2, 1e2, 1e2]),
        }
    }

    fn field_of<T: std::fmt::Debug>(r: Result<T, InputError>) -> &'static str {
        r.expect_err("must be rejected").field
    }

    #[test]
    fn keyframes() {
        assert_eq!(check_keyframe(&keyframe(), 1).unwrap().id, 3);
        assert_eq!(field_of(check_keyframe(&keyframe(), 0)), "robot");
        let mut k = keyframe();
        k.source = 7;
        let e = check_keyframe(&k, 1).unwrap_err();
        assert_eq!((e.topic, e.robot, e.field), ("keyframes", 1, "source"));
        let mut k = keyframe();
        k.pose = [0.0; 7];
        assert_eq!(field_of(check_keyframe(&k, 1)), "pose");
        let mut k = keyframe();
        k.pose[0] = f64::NAN;
        assert_eq!(field_of(check_keyframe(&k, 1)), "pose");
        let mut k = keyframe();
        k.id = 1 << 56;
        assert_eq!(field_of(check_keyframe(&k, 1)), "id");
        let mut k = keyframe();
        k.n_features = MAX_KEYFRAME_FEATURES as u32 + 1;
        assert_eq!(field_of(check_keyframe(&k, 1)), "n_features");
        let mut k = keyframe();
        k.n_features = 2;
        k.features[1].point[2] = f32::INFINITY;
        assert_eq!(field_of(check_keyframe(&k, 1)), "features");
        // Features beyond n_features are not looked at.
        k.n_features = 1;
        assert!(check_keyframe(&k, 1).is_ok());
    }

    #[test]
    fn odometry() {
        assert!(check_odometry(&edge(), 1).is_ok());
        let mut e = edge();
        e.to = e.from;
        assert_eq!(field_of(check_odometry(&e, 1)), "to");
        let mut e = edge();
        e.relative[6] = 0.0;
        assert_eq!(field_of(check_odometry(&e, 1)), "relative");
        let mut e = edge();
        e.information[0] = f64::NAN;
        assert_eq!(field_of(check_odometry(&e, 1)), "information");
        let mut e = edge();
        e.information[20] = -1.0; // last diagonal entry: indefinite
        assert_eq!(field_of(check_odometry(&e, 1)), "information");
        let mut e = edge();
        e.from = u64::MAX;
        assert_eq!(field_of(check_odometry(&e, 1)), "from");
    }

    #[test]
    fn closures() {
        let lc = LoopClosure {
            robot_a: 0,
            robot_b: 2,
            keyframe_a: 4,
            keyframe_b: 4,
            relative: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            information: upper_from_diagonal([1.0; 6]),
            inliers: 40,
            reserved: 0,
        };
        let ok = check_closure(&lc).unwrap();
        assert_eq!(key::label(ok.key_b), "c4");
        let mut bad = lc;
        bad.robot_b = 52;
        assert_eq!(field_of(check_closure(&bad)), "robot_b");
        let mut bad = lc;
        bad.robot_b = 0;
        assert_eq!(field_of(check_closure(&bad)), "keyframe_b");
        let mut bad = lc;
        bad.information = [0.0; 21];
        assert_eq!(field_of(check_closure(&bad)), "information");
    }
}
