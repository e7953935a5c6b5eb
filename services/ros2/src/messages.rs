//! The ROS messages of a robot's state, built the same way for the record, the replay and
//! the live publishers: paths of TUM poses, the latest pose, `team` → `<robot>/odom`, and
//! the loop closures as two `LINE_LIST` markers (kept green, rejected red).

use doorslam_ros2_wire::msgs::{
    ColorRgba, Header, Marker, MarkerArray, Path as RosPath, Point, PoseStamped, Quaternion,
    TfMessage, Time, Transform, TransformStamped, Vector3,
};
use nalgebra::Isometry3;

use crate::state::TumPose;

/// The frame every robot's team estimate is in.
pub const TEAM_FRAME: &str = "team";

/// A robot's odometry frame: `<robot>/odom`.
pub fn odometry_frame(robot: &str) -> String {
    format!("{robot}/odom")
}

pub fn stamp(ns: i64) -> Time {
    Time::from_nanos(ns)
}

fn header(ns: i64, frame: &str) -> Header {
    Header {
        stamp: stamp(ns),
        frame_id: frame.to_string(),
    }
}

/// `poses` as one path in `frame`, stamped with its last pose.
pub fn path_msg(frame: &str, poses: &[TumPose]) -> RosPath {
    RosPath {
        header: header(poses.last().map_or(0, |p| p.stamp_ns), frame),
        poses: poses.iter().map(|p| pose_msg(frame, p)).collect(),
    }
}

pub fn pose_msg(frame: &str, p: &TumPose) -> PoseStamped {
    PoseStamped {
        header: header(p.stamp_ns, frame),
        pose: p.pose(),
    }
}

/// `/tf` with the one transform `team` → `<robot>/odom` at `stamp_ns`.
pub fn team_to_odometry_msg(robot: &str, stamp_ns: i64, t: &Isometry3<f64>) -> TfMessage {
    let (v, q) = (t.translation.vector, t.rotation);
    TfMessage {
        transforms: vec![TransformStamped {
            header: header(stamp_ns, TEAM_FRAME),
            child_frame_id: odometry_frame(robot),
            transform: Transform {
                translation: Vector3 {
                    x: v.x,
                    y: v.y,
                    z: v.z,
                },
                rotation: Quaternion {
                    x: q.i,
                    y: q.j,
                    z: q.k,
                    w: q.w,
                },
            },
        }],
    }
}

fn line_list(id: i32, ns: &str, time_ns: i64, color: ColorRgba, points: Vec<Point>) -> Marker {
    Marker {
        header: header(time_ns, TEAM_FRAME),
        ns: ns.into(),
        id,
        kind: Marker::LINE_LIST,
        action: Marker::ADD,
        scale: Vector3 {
            x: 0.1,
            y: 0.0,
            z: 0.0,
        },
        color,
        points,
        ..Marker::default()
    }
}

/// Closures as segments (pairs of end points in the team frame): `kept` green, `rejected`
/// red, in the namespaces `kept` and `rejected`.
pub fn closures_msg(time_ns: i64, kept: Vec<Point>, rejected: Vec<Point>) -> MarkerArray {
    MarkerArray {
        markers: vec![
            line_list(
                0,
                "kept",
                time_ns,
                ColorRgba {
                    r: 0.1,
                    g: 0.8,
                    b: 0.1,
                    a: 1.0,
                },
                kept,
            ),
            line_list(
                1,
                "rejected",
                time_ns,
                ColorRgba {
                    r: 0.9,
                    g: 0.1,
                    b: 0.1,
                    a: 1.0,
                },
                rejected,
            ),
        ],
    }
}

pub fn point(v: &nalgebra::Vector3<f64>) -> Point {
    Point {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}
