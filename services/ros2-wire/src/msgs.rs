//! The messages doorslam publishes, as plain structs, each with its CDR encoding (fields in
//! the order of its [`TypeDef`]; the byte-exact fixture tests check both against an
//! encoder that is not ours).

use crate::cdr::CdrWriter;
use crate::types::{self, TypeDef};
use crate::WireError;

/// A ROS 2 message: its type and its CDR fields.
pub trait RosMessage {
    const TYPE: &'static TypeDef;

    /// Writes the fields (no header: [`RosMessage::to_cdr`] adds it).
    fn write(&self, w: &mut CdrWriter);

    /// The whole CDR payload, encapsulation header included.
    fn to_cdr(&self) -> Result<Vec<u8>, WireError> {
        let mut w = CdrWriter::new();
        self.write(&mut w);
        w.finish()
    }
}

fn seq<T: RosMessage>(w: &mut CdrWriter, items: &[T]) {
    w.seq_len(items.len());
    for x in items {
        x.write(w);
    }
}

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// From nanoseconds since the epoch of the clock (negative times floor to a negative
    /// `sec` with a positive `nanosec`, as ROS does); outside `i32` seconds it saturates.
    pub fn from_nanos(ns: i64) -> Self {
        let sec = ns.div_euclid(1_000_000_000);
        let nanosec = ns.rem_euclid(1_000_000_000) as u32;
        match i32::try_from(sec) {
            Ok(sec) => Self { sec, nanosec },
            Err(_) if sec < 0 => Self {
                sec: i32::MIN,
                nanosec: 0,
            },
            Err(_) => Self {
                sec: i32::MAX,
                nanosec: 999_999_999,
            },
        }
    }

    /// Nanoseconds since the epoch of the clock.
    pub fn nanos(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

impl RosMessage for Time {
    const TYPE: &'static TypeDef = &types::TIME;
    fn write(&self, w: &mut CdrWriter) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

impl RosMessage for Duration {
    const TYPE: &'static TypeDef = &types::DURATION;
    fn write(&self, w: &mut CdrWriter) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

impl RosMessage for Header {
    const TYPE: &'static TypeDef = &types::HEADER;
    fn write(&self, w: &mut CdrWriter) {
        self.stamp.write(w);
        w.string(&self.frame_id);
    }
}

/// `std_msgs/msg/ColorRGBA`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ColorRgba {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

impl RosMessage for ColorRgba {
    const TYPE: &'static TypeDef = &types::COLOR_RGBA;
    fn write(&self, w: &mut CdrWriter) {
        for v in [self.r, self.g, self.b, self.a] {
            w.f32(v);
        }
    }
}

/// `geometry_msgs/msg/Point`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl RosMessage for Point {
    const TYPE: &'static TypeDef = &types::POINT;
    fn write(&self, w: &mut CdrWriter) {
        for v in [self.x, self.y, self.z] {
            w.f64(v);
        }
    }
}

/// `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl RosMessage for Vector3 {
    const TYPE: &'static TypeDef = &types::VECTOR3;
    fn write(&self, w: &mut CdrWriter) {
        for v in [self.x, self.y, self.z] {
            w.f64(v);
        }
    }
}

/// `geometry_msgs/msg/Quaternion` (ROS's default is the identity, `w = 1`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

impl RosMessage for Quaternion {
    const TYPE: &'static TypeDef = &types::QUATERNION;
    fn write(&self, w: &mut CdrWriter) {
        for v in [self.x, self.y, self.z, self.w] {
            w.f64(v);
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

impl RosMessage for Pose {
    const TYPE: &'static TypeDef = &types::POSE;
    fn write(&self, w: &mut CdrWriter) {
        self.position.write(w);
        self.orientation.write(w);
    }
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

impl RosMessage for PoseStamped {
    const TYPE: &'static TypeDef = &types::POSE_STAMPED;
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        self.pose.write(w);
    }
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

impl RosMessage for Transform {
    const TYPE: &'static TypeDef = &types::TRANSFORM;
    fn write(&self, w: &mut CdrWriter) {
        self.translation.write(w);
        self.rotation.write(w);
    }
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

impl RosMessage for TransformStamped {
    const TYPE: &'static TypeDef = &types::TRANSFORM_STAMPED;
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.string(&self.child_frame_id);
        self.transform.write(w);
    }
}

/// `nav_msgs/msg/Path`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Path {
    pub header: Header,
    pub poses: Vec<PoseStamped>,
}

impl RosMessage for Path {
    const TYPE: &'static TypeDef = &types::PATH;
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        seq(w, &self.poses);
    }
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

impl RosMessage for TfMessage {
    const TYPE: &'static TypeDef = &types::TF_MESSAGE;
    fn write(&self, w: &mut CdrWriter) {
        seq(w, &self.transforms);
    }
}

/// `sensor_msgs/msg/CompressedImage` (a marker's texture; doorslam leaves it empty).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    pub data: Vec<u8>,
}

impl RosMessage for CompressedImage {
    const TYPE: &'static TypeDef = &types::COMPRESSED_IMAGE;
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.string(&self.format);
        w.bytes(&self.data);
    }
}

/// `visualization_msgs/msg/UVCoordinate`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct UvCoordinate {
    pub u: f32,
    pub v: f32,
}

impl RosMessage for UvCoordinate {
    const TYPE: &'static TypeDef = &types::UV_COORDINATE;
    fn write(&self, w: &mut CdrWriter) {
        w.f32(self.u);
        w.f32(self.v);
    }
}

/// `visualization_msgs/msg/MeshFile`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MeshFile {
    pub filename: String,
    pub data: Vec<u8>,
}

impl RosMessage for MeshFile {
    const TYPE: &'static TypeDef = &types::MESH_FILE;
    fn write(&self, w: &mut CdrWriter) {
        w.string(&self.filename);
        w.bytes(&self.data);
    }
}

/// `visualization_msgs/msg/Marker` (Jazzy's fields).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Marker {
    pub header: Header,
    pub ns: String,
    pub id: i32,
    pub kind: i32,
    pub action: i32,
    pub pose: Pose,
    pub scale: Vector3,
    pub color: ColorRgba,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub points: Vec<Point>,
    pub colors: Vec<ColorRgba>,
    pub texture_resource: String,
    pub texture: CompressedImage,
    pub uv_coordinates: Vec<UvCoordinate>,
    pub text: String,
    pub mesh_resource: String,
    pub mesh_file: MeshFile,
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// `type`: a line segment between every two points.
    pub const LINE_LIST: i32 = 5;
    /// `action`.
    pub const ADD: i32 = 0;
    pub const DELETEALL: i32 = 3;
}

impl RosMessage for Marker {
    const TYPE: &'static TypeDef = &types::MARKER;
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.string(&self.ns);
        w.i32(self.id);
        w.i32(self.kind);
        w.i32(self.action);
        self.pose.write(w);
        self.scale.write(w);
        self.color.write(w);
        self.lifetime.write(w);
        w.bool(self.frame_locked);
        seq(w, &self.points);
        seq(w, &self.colors);
        w.string(&self.texture_resource);
        self.texture.write(w);
        seq(w, &self.uv_coordinates);
        w.string(&self.text);
        w.string(&self.mesh_resource);
        self.mesh_file.write(w);
        w.bool(self.mesh_use_embedded_materials);
    }
}

/// `visualization_msgs/msg/MarkerArray`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MarkerArray {
    pub markers: Vec<Marker>,
}

impl RosMessage for MarkerArray {
    const TYPE: &'static TypeDef = &types::MARKER_ARRAY;
    fn write(&self, w: &mut CdrWriter) {
        seq(w, &self.markers);
    }
}

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

impl RosMessage for KeyValue {
    const TYPE: &'static TypeDef = &types::KEY_VALUE;
    fn write(&self, w: &mut CdrWriter) {
        w.string(&self.key);
        w.string(&self.value);
    }
}

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    pub const OK: u8 = 0;
}

impl RosMessage for DiagnosticStatus {
    const TYPE: &'static TypeDef = &types::DIAGNOSTIC_STATUS;
    fn write(&self, w: &mut CdrWriter) {
        w.u8(self.level);
        w.string(&self.name);
        w.string(&self.message);
        w.string(&self.hardware_id);
        seq(w, &self.values);
    }
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

impl RosMessage for DiagnosticArray {
    const TYPE: &'static TypeDef = &types::DIAGNOSTIC_ARRAY;
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        seq(w, &self.status);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_from_nanos_floors_like_ros() {
        assert_eq!(
            Time::from_nanos(1_500_000_000),
            Time {
                sec: 1,
                nanosec: 500_000_000
            }
        );
        assert_eq!(
            Time::from_nanos(-1),
            Time {
                sec: -1,
                nanosec: 999_999_999
            }
        );
        assert_eq!(Time::from_nanos(i64::MAX).sec, i32::MAX);
        assert_eq!(Time::from_nanos(123_456_789_012).nanos(), 123_456_789_012);
    }
}
