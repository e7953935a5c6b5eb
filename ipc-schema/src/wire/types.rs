//! The values messages are made of, in the exact form they travel: robot ids, multi-robot
//! keys, poses, information matrices, place descriptors and verification features.
//!
//! Each quantized type is built from the full-precision value by a constructor that
//! checks it with `doorslam-geometry`'s rules, and stores the bits that go on the wire, so
//! encoding cannot fail on it and a decoded value equals the encoded one exactly.

use doorslam_geometry::information::matrix_from_upper;
use doorslam_geometry::key;
use doorslam_geometry::{
    check_information, pose_from_array, InformationCheck, InformationError, PoseError,
    TangentMatrix, SE3,
};

use super::codec::{f16_from_f32, f32_from_f16, Reader, Sink};
use super::WireError;

/// Longest robot id (bytes), as for `robot.id` in robot.toml.
pub const MAX_ROBOT_ID_LEN: usize = 32;

/// A robot's id from its config: 1–32 characters of `[a-z0-9_-]`.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct RobotId(String);

/// Why a value cannot be put in a message.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QuantizeError {
    #[error("robot id {0:?}: use 1-32 characters of [a-z0-9_-]")]
    RobotId(String),
    #[error("{field} = {value} is not finite")]
    NonFinite { field: &'static str, value: f64 },
    #[error("{field} = {value} is outside {min}..{max}")]
    OutOfRange {
        field: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error("{field} has {got} values, the wire format carries {want}")]
    WrongLength {
        field: &'static str,
        got: usize,
        want: usize,
    },
}

fn valid_robot_id(id: &[u8]) -> bool {
    (1..=MAX_ROBOT_ID_LEN).contains(&id.len())
        && id
            .iter()
            .all(|&c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'_' || c == b'-')
}

impl RobotId {
    pub fn new(id: &str) -> Result<Self, QuantizeError> {
        if valid_robot_id(id.as_bytes()) {
            Ok(Self(id.to_owned()))
        } else {
            Err(QuantizeError::RobotId(id.to_owned()))
        }
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// One length byte, then the id's bytes.
    pub(crate) fn write(&self, s: &mut impl Sink) {
        s.u8(self.0.len() as u8);
        s.put(self.0.as_bytes());
    }

    pub(crate) fn read(r: &mut Reader<'_>) -> Result<Self, WireError> {
        let offset = r.offset();
        let len = r.u8("sender length")? as usize;
        if len > MAX_ROBOT_ID_LEN {
            return Err(WireError::TooLong {
                field: "sender length",
                offset,
                len: len as u64,
                max: MAX_ROBOT_ID_LEN as u64,
            });
        }
        let bytes = r.take("sender", len)?;
        if !valid_robot_id(bytes) {
            return Err(WireError::invalid(
                "sender",
                offset,
                "not 1-32 characters of [a-z0-9_-]",
            ));
        }
        // Checked ASCII above, so this cannot fail; map rather than unwrap all the same.
        let s = core::str::from_utf8(bytes).map_err(|e| WireError::invalid("sender", offset, e))?;
        Ok(Self(s.to_owned()))
    }
}

impl core::fmt::Display for RobotId {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(&self.0)
    }
}

/// A multi-robot key (`robot_char << 56 | index`, see `doorslam_geometry::key`) travels as
/// the robot number (one byte, 0 = 'a') and the index (varint): 2–4 bytes for a real
/// flight instead of the 9 a varint of the whole key takes. A plain single-robot index
/// cannot be sent: every key on the wire names its robot.
pub(crate) fn write_key(s: &mut impl Sink, field: &'static str, k: u64) -> Result<(), WireError> {
    let robot = key::robot(k).ok_or_else(|| {
        WireError::invalid(field, s.offset(), "not a multi-robot key (no robot letter)")
    })?;
    s.u8(robot);
    s.varint(key::index(k));
    Ok(())
}

pub(crate) fn read_key(r: &mut Reader<'_>, field: &'static str) -> Result<u64, WireError> {
    let offset = r.offset();
    let robot = r.u8(field)?;
    let index = r.varint(field)?;
    key::symbol(robot, index).map_err(|e| WireError::invalid(field, offset, e))
}

/// A pose `[x y z qx qy qz qw]` as seven f32 (28 bytes): translation in metres, rotation
/// a unit quaternion (checked by [`pose_from_array`] and normalized for use).
///
/// Why f32: at 1 km from the origin its resolution is 0.06 mm, and a quaternion
/// component's 6e-8 is 1e-7 rad; both are orders of magnitude below odometry and PnP
/// noise (centimetres, 0.1°) and below the consensus thresholds of the distributed
/// back-end, while f64 would cost 28 more bytes per pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Pose {
    raw: [f32; 7],
    se3: SE3,
}

impl Pose {
    /// From the wire values; refused unless [`pose_from_array`] accepts them.
    pub fn from_array(raw: [f32; 7]) -> Result<Self, PoseError> {
        let se3 = pose_from_array(&raw.map(f64::from))?;
        Ok(Self { raw, se3 })
    }

    /// Rounds a pose to the wire's f32.
    pub fn from_se3(p: &SE3) -> Result<Self, PoseError> {
        Self::from_array(doorslam_geometry::pose_to_array(p).map(|v| v as f32))
    }

    /// The values as sent, `[x y z qx qy qz qw]`.
    pub fn raw(&self) -> [f32; 7] {
        self.raw
    }

    /// The pose (quaternion normalized).
    pub fn se3(&self) -> &SE3 {
        &self.se3
    }

    pub(crate) fn write(&self, s: &mut impl Sink) {
        for v in self.raw {
            s.f32(v);
        }
    }

    pub(crate) fn read(r: &mut Reader<'_>, field: &'static str) -> Result<Self, WireError> {
        let offset = r.offset();
        let mut raw = [0f32; 7];
        for v in &mut raw {
            *v = r.f32(field)?;
        }
        Self::from_array(raw).map_err(|e| WireError::invalid(field, offset, e))
    }
}

/// Bytes of a [`Pose`] on the wire.
pub const POSE_BYTES: usize = 28;

/// An information matrix (rotation-first tangent order, as in `doorslam_geometry`) as its
/// Cholesky factor: `Ω = L Lᵀ`, `L` lower triangular, sent as one f32 scale and the 21
/// entries of `L / scale` (row-major lower triangle: (0,0), (1,0), (1,1), (2,0), ...) as
/// IEEE half floats: 46 bytes instead of 168 for 21 f64.
///
/// `L Lᵀ` is positive semi-definite whatever the bits; the decoder rebuilds Ω and checks it
/// with [`check_information`] (positive definite). Halves keep 11 significant bits of an
/// entry down to 6e-5 of the largest (Ω's entries keep about 3 significant digits: a noise
/// model needs no more); smaller entries are subnormal halves with an absolute step of
/// 6e-8 of the largest (0.3 % on Ω at a condition number of 1e10), and a matrix whose
/// smallest direction would round to zero (condition number beyond ~1e15) is refused by
/// [`Information::from_matrix`].
#[derive(Debug, Clone, PartialEq)]
pub struct Information {
    scale: f32,
    factor: [u16; 21],
    matrix: TangentMatrix,
}

/// Bytes of an [`Information`] on the wire.
pub const INFORMATION_BYTES: usize = 4 + 2 * 21;

impl Information {
    /// Factors and rounds `information`, which must pass [`check_information`] (positive
    /// definite) before and after rounding.
    pub fn from_matrix(information: &TangentMatrix) -> Result<Self, InformationError> {
        check_information(information, 6, InformationCheck::PositiveDefinite)?;
        let l = information
            .cholesky()
            .ok_or(InformationError::NotPositiveDefinite)?
            .l();
        let mut lower = [0f64; 21];
        let mut k = 0;
        for r in 0..6 {
            for c in 0..=r {
                lower[k] = l[(r, c)];
                k += 1;
            }
        }
        let max = lower.iter().fold(0f64, |m, v| m.max(v.abs()));
        let scale = max as f32;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(InformationError::NotPositiveDefinite);
        }
        let factor = lower.map(|v| f16_from_f32((v / f64::from(scale)) as f32));
        Self::from_parts(scale, factor)
    }

    /// From the upper triangle layout of `doorslam_geometry::information` (21 values).
    pub fn from_upper(upper: &[f64; 21]) -> Result<Self, InformationError> {
        Self::from_matrix(&matrix_from_upper(upper))
    }

    /// From the wire values: rebuilds Ω and checks it.
    pub fn from_parts(scale: f32, factor: [u16; 21]) -> Result<Self, InformationError> {
        if !scale.is_finite() {
            return Err(InformationError::NonFinite {
                row: 0,
                col: 0,
                value: f64::from(scale),
            });
        }
        let mut l = TangentMatrix::zeros();
        let mut k = 0;
        for r in 0..6 {
            for c in 0..=r {
                l[(r, c)] = f64::from(f32_from_f16(factor[k])) * f64::from(scale);
                k += 1;
            }
        }
        // Ω_rc = Σ_k L_rk L_ck, summed in the same order for (r, c) and (c, r): exactly
        // symmetric. Non-finite entries surface in the check below.
        let mut matrix = TangentMatrix::zeros();
        for r in 0..6 {
            for c in 0..6 {
                matrix[(r, c)] = (0..6).map(|k| l[(r, k)] * l[(c, k)]).sum();
            }
        }
        check_information(&matrix, 6, InformationCheck::PositiveDefinite)?;
        Ok(Self {
            scale,
            factor,
            matrix,
        })
    }

    /// Ω, 6×6, rotation first.
    pub fn matrix(&self) -> &TangentMatrix {
        &self.matrix
    }

    /// The wire values: scale and the half-float bits of `L / scale`.
    pub fn parts(&self) -> (f32, [u16; 21]) {
        (self.scale, self.factor)
    }

    pub(crate) fn write(&self, s: &mut impl Sink) {
        s.f32(self.scale);
        for h in self.factor {
            s.u16(h);
        }
    }

    pub(crate) fn read(r: &mut Reader<'_>, field: &'static str) -> Result<Self, WireError> {
        let offset = r.offset();
        let scale = r.f32(field)?;
        let mut factor = [0u16; 21];
        for h in &mut factor {
            *h = r.u16(field)?;
        }
        Self::from_parts(scale, factor).map_err(|e| WireError::invalid(field, offset, e))
    }
}

/// Dimension of a place descriptor on the wire (NetVLAD reduced by PCA, L2-normalized).
/// Another dimension is another wire version.
pub const DESCRIPTOR_DIM: usize = 128;

/// One keyframe's place descriptor, int8-quantized with one scale: value `i` is
/// `values[i] as f32 * scale`. With `scale = max |v| / 127` the rounding error of each
/// component is at most `scale / 2` (≤ 0.004 for an L2-normalized vector, against a match
/// threshold of 0.13–0.15 on the whole distance).
#[derive(Debug, Clone, PartialEq)]
pub struct Descriptor {
    /// Key of the keyframe (the sender's robot).
    pub key: u64,
    /// Size of one quantization step (≥ 0, finite).
    pub scale: f32,
    pub values: [i8; DESCRIPTOR_DIM],
}

impl Descriptor {
    /// Quantizes a `DESCRIPTOR_DIM`-long float descriptor.
    pub fn quantize(key: u64, v: &[f32]) -> Result<Self, QuantizeError> {
        if v.len() != DESCRIPTOR_DIM {
            return Err(QuantizeError::WrongLength {
                field: "descriptor",
                got: v.len(),
                want: DESCRIPTOR_DIM,
            });
        }
        if let Some(&x) = v.iter().find(|x| !x.is_finite()) {
            return Err(QuantizeError::NonFinite {
                field: "descriptor",
                value: f64::from(x),
            });
        }
        let max = v.iter().fold(0f32, |m, x| m.max(x.abs()));
        let scale = max / 127.0;
        let values = std::array::from_fn(|i| {
            if scale > 0.0 {
                (v[i] / scale).round().clamp(-127.0, 127.0) as i8
            } else {
                0
            }
        });
        Ok(Self { key, scale, values })
    }

    /// The dequantized descriptor.
    pub fn to_f32(&self) -> [f32; DESCRIPTOR_DIM] {
        self.values.map(|q| f32::from(q) * self.scale)
    }
}

/// Pixel coordinates travel in 1/16 pixel (u16): 0 to 4095.94 px, rounding error ≤ 1/32 px.
pub const PIXEL_STEPS: f32 = 16.0;
/// Disparities travel in 1/64 pixel (u16): 1/64 to 1023.98 px, rounding error ≤ 1/128 px.
pub const DISPARITY_STEPS: f32 = 64.0;

/// The rectified stereo camera a [`VerificationFeatures`](super::VerificationFeatures)
/// packet was measured with (20 bytes: five f32): what turns its pixels and disparities
/// into 3-D points and their covariances, so robots with different cameras can verify
/// each other's keyframes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerificationCamera {
    /// Focal lengths and principal point (px).
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Distance between the optical centres (m).
    pub baseline_m: f32,
}

/// Bytes of a [`VerificationCamera`] on the wire.
pub const VERIFICATION_CAMERA_BYTES: usize = 20;

impl VerificationCamera {
    /// Checked: every value finite, focal lengths and baseline > 0.
    pub fn new(fx: f32, fy: f32, cx: f32, cy: f32, baseline_m: f32) -> Result<Self, QuantizeError> {
        let camera = Self {
            fx,
            fy,
            cx,
            cy,
            baseline_m,
        };
        match camera.problem() {
            None => Ok(camera),
            Some((field, value)) => Err(QuantizeError::OutOfRange {
                field,
                value: f64::from(value),
                min: 0.0,
                max: f64::from(f32::MAX),
            }),
        }
    }

    /// The first value that breaks the rule, if any.
    fn problem(&self) -> Option<(&'static str, f32)> {
        [
            ("camera fx", self.fx, true),
            ("camera fy", self.fy, true),
            ("camera cx", self.cx, false),
            ("camera cy", self.cy, false),
            ("camera baseline", self.baseline_m, true),
        ]
        .into_iter()
        .find(|&(_, v, positive)| !v.is_finite() || (positive && v <= 0.0))
        .map(|(field, v, _)| (field, v))
    }

    pub(crate) fn write(&self, s: &mut impl Sink) {
        for v in [self.fx, self.fy, self.cx, self.cy, self.baseline_m] {
            s.f32(v);
        }
    }

    /// [`Self::new`]'s rule as a wire error at `offset`.
    pub(crate) fn check(&self, offset: usize) -> Result<(), WireError> {
        match self.problem() {
            None => Ok(()),
            Some((field, v)) => Err(WireError::invalid(
                field,
                offset,
                format!("{v}: must be finite (focal lengths and baseline > 0)"),
            )),
        }
    }

    pub(crate) fn read(r: &mut Reader<'_>) -> Result<Self, WireError> {
        let offset = r.offset();
        let camera = Self {
            fx: r.f32("camera fx")?,
            fy: r.f32("camera fy")?,
            cx: r.f32("camera cx")?,
            cy: r.f32("camera cy")?,
            baseline_m: r.f32("camera baseline")?,
        };
        camera.check(offset)?;
        Ok(camera)
    }
}

/// One feature for geometric verification (38 bytes): pixel in the left rectified image
/// (u16 in 1/16 px, x then y), disparity (u16 in 1/64 px, > 0) and the 32-byte ORB
/// descriptor.
///
/// Why pixel and disparity rather than a 3-D point: they are what stereo measures, the
/// point follows from them and the packet's [`VerificationCamera`] exactly (on the pixel's
/// ray), and so does its covariance (depth σ grows with z², from the disparity's σ). In
/// fixed point their rounding (≤ 1/32 px, ≤ 1/128 px) is a few percent of the
/// measurement noise (~0.5 px) at every depth, in 6 bytes instead of a point's 6 plus a
/// pixel's 4.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VerificationFeature {
    /// x, y in 1/16 px.
    pub pixel: [u16; 2],
    /// Disparity in 1/64 px (never 0).
    pub disparity: u16,
    pub descriptor: [u8; 32],
}

/// Bytes of a [`VerificationFeature`] on the wire.
pub const FEATURE_BYTES: usize = 4 + 2 + 32;

impl VerificationFeature {
    /// Rounds a stereo feature to the wire form; refused if a value is not finite, the
    /// pixel is outside 0..4096 or the disparity outside 1/64..1024 px.
    pub fn quantize(
        pixel: [f32; 2],
        disparity_px: f32,
        descriptor: [u8; 32],
    ) -> Result<Self, QuantizeError> {
        let fixed = |field: &'static str, v: f32, steps: f32, min: u16| {
            if !v.is_finite() {
                return Err(QuantizeError::NonFinite {
                    field,
                    value: f64::from(v),
                });
            }
            let q = (v * steps).round();
            if !(f32::from(min)..=f32::from(u16::MAX)).contains(&q) {
                return Err(QuantizeError::OutOfRange {
                    field,
                    value: f64::from(v),
                    min: f64::from(min) / f64::from(steps),
                    max: f64::from(u16::MAX) / f64::from(steps),
                });
            }
            Ok(q as u16)
        };
        Ok(Self {
            pixel: [
                fixed("feature pixel", pixel[0], PIXEL_STEPS, 0)?,
                fixed("feature pixel", pixel[1], PIXEL_STEPS, 0)?,
            ],
            disparity: fixed("feature disparity", disparity_px, DISPARITY_STEPS, 1)?,
            descriptor,
        })
    }

    /// The pixel (u, v) in px.
    pub fn pixel_px(&self) -> [f32; 2] {
        self.pixel.map(|p| f32::from(p) / PIXEL_STEPS)
    }

    /// The disparity in px.
    pub fn disparity_px(&self) -> f32 {
        f32::from(self.disparity) / DISPARITY_STEPS
    }

    pub(crate) fn write(&self, s: &mut impl Sink) {
        for p in self.pixel {
            s.u16(p);
        }
        s.u16(self.disparity);
        s.put(&self.descriptor);
    }

    pub(crate) fn read(r: &mut Reader<'_>) -> Result<Self, WireError> {
        let pixel = [r.u16("feature pixel")?, r.u16("feature pixel")?];
        let offset = r.offset();
        let disparity = r.u16("feature disparity")?;
        if disparity == 0 {
            return Err(WireError::invalid(
                "feature disparity",
                offset,
                "must be > 0",
            ));
        }
        let descriptor = r.array("feature descriptor")?;
        Ok(Self {
            pixel,
            disparity,
            descriptor,
        })
    }
}

/// Largest translation component a [`CompactPose`] carries: 1,000 km, in metres.
pub const MAX_COMPACT_TRANSLATION_M: f64 = 1.0e6;
/// Translation step of a [`CompactPose`]: 0.1 mm (rounding error ≤ 0.05 mm per axis).
pub const COMPACT_TRANSLATION_STEP_M: f64 = 1.0e-4;
/// Largest magnitude of a quaternion component in a [`CompactPose`]: 24-bit two's
/// complement.
pub const COMPACT_QUATERNION_MAX: i32 = (1 << 23) - 1;
/// Quaternion step of a [`CompactPose`]: the three smallest components in 1/11863282
/// (24 bits over ±1/√2, the most the three smaller components of a unit quaternion reach).
pub const COMPACT_QUATERNION_STEPS: f64 = COMPACT_QUATERNION_MAX as f64 * std::f64::consts::SQRT_2;
/// Step of a [`RelaxedRotation`] entry: 2⁻¹⁴ (rounding error ≤ 3.1e-5), range ±2.
pub const RELAXED_ROTATION_STEP: f64 = 1.0 / 16384.0;
/// Largest rotation error of a [`CompactPose`] (rad), see its documentation.
pub const COMPACT_ROTATION_ERROR_RAD: f64 = 1.0e-6;

/// A separator pose estimate as the distributed back-end sends it (and the relative pose of
/// a condensed graph's edge): translation in steps of 0.1 mm (three zigzag varints: 3 bytes
/// each within ±104 m of the origin, 4 within ±13 km) and the rotation as a unit quaternion
/// in "smallest three" form — which component is the largest in magnitude (one byte, 0–3
/// for x, y, z, w; its sign made positive, as q and -q are one rotation) and the other
/// three as 24-bit integers in steps of 1/11863282 (the largest is rebuilt as
/// √(1 − Σ others²) ≥ ½, so rounding is never amplified, unlike dropping w when w ≈ 0):
/// 13–25 bytes (19 for a pose within 104 m) instead of [`Pose`]'s 28.
///
/// The error is bounded and stated: ≤ 0.05 mm per translation axis and
/// ≤ [`COMPACT_ROTATION_ERROR_RAD`] (1 µrad) of rotation. Why this fine: the distributed
/// back-end's separators and condensed edges are solved against information of up to
/// ~3·10⁵ rad⁻² (KITTI 00's odometry), where the former 1 mm / 1e-4 rad steps alone cost
/// 0.015 % of the team's χ² (BENCHMARKS.md, "Distributed pose-graph optimization"), more
/// than the 1e-4 the back-end must stay within; these steps cost below 1e-6 of it.
#[derive(Debug, Clone, PartialEq)]
pub struct CompactPose {
    translation_steps: [i64; 3],
    largest: u8,
    rest: [i32; 3],
    se3: SE3,
}

impl CompactPose {
    /// Rounds a pose to the wire's steps; refused if not finite or a translation
    /// component is beyond ±[`MAX_COMPACT_TRANSLATION_M`].
    pub fn quantize(p: &SE3) -> Result<Self, QuantizeError> {
        let t = p.translation.vector;
        let mut translation_steps = [0i64; 3];
        for (k, v) in translation_steps.iter_mut().enumerate() {
            let x = t[k];
            if !x.is_finite() {
                return Err(QuantizeError::NonFinite {
                    field: "estimate translation",
                    value: x,
                });
            }
            if x.abs() > MAX_COMPACT_TRANSLATION_M {
                return Err(QuantizeError::OutOfRange {
                    field: "estimate translation",
                    value: x,
                    min: -MAX_COMPACT_TRANSLATION_M,
                    max: MAX_COMPACT_TRANSLATION_M,
                });
            }
            *v = (x / COMPACT_TRANSLATION_STEP_M).round() as i64;
        }
        let c = p.rotation.coords;
        let q = [c.x, c.y, c.z, c.w];
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(n.is_finite() && n > 0.0) {
            return Err(QuantizeError::NonFinite {
                field: "estimate rotation",
                value: n,
            });
        }
        let largest = (0..4)
            .max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs()))
            .unwrap_or(3);
        let sign = q[largest].signum() / n;
        let limit = f64::from(COMPACT_QUATERNION_MAX);
        let mut rest = [0i32; 3];
        for (slot, k) in rest.iter_mut().zip((0..4).filter(|&k| k != largest)) {
            *slot = (q[k] * sign * COMPACT_QUATERNION_STEPS)
                .round()
                .clamp(-limit, limit) as i32;
        }
        Self::from_parts(translation_steps, largest as u8, rest).map_err(|_| {
            QuantizeError::OutOfRange {
                field: "estimate rotation",
                value: n,
                min: 1.0,
                max: 1.0,
            }
        })
    }

    /// From the wire integers; refused if the largest component's index is above 3.
    pub fn from_parts(
        translation_steps: [i64; 3],
        largest: u8,
        rest: [i32; 3],
    ) -> Result<Self, &'static str> {
        let limit = (MAX_COMPACT_TRANSLATION_M / COMPACT_TRANSLATION_STEP_M) as i64;
        if translation_steps.iter().any(|t| t.abs() > limit) {
            return Err("translation beyond 1,000 km");
        }
        if largest > 3 {
            return Err("largest quaternion component index above 3");
        }
        if rest.iter().any(|c| c.abs() > COMPACT_QUATERNION_MAX) {
            return Err("quaternion component beyond 24 bits");
        }
        let others = rest.map(|c| f64::from(c) / COMPACT_QUATERNION_STEPS);
        let norm2: f64 = others.iter().map(|v| v * v).sum();
        // Three components of ≤ 1/√2 each can exceed 1 together only in corrupt input;
        // such a value is not the smallest three of any unit quaternion.
        if norm2 > 0.75 + 1e-4 {
            return Err("quaternion components inconsistent (the three smallest exceed 3/4)");
        }
        let mut q = [0.0; 4];
        let mut it = others.iter();
        for (k, v) in q.iter_mut().enumerate() {
            *v = if k == largest as usize {
                (1.0 - norm2).sqrt()
            } else {
                it.next().copied().unwrap_or(0.0)
            };
        }
        let t = translation_steps.map(|x| x as f64 * COMPACT_TRANSLATION_STEP_M);
        let se3 = pose_from_array(&[t[0], t[1], t[2], q[0], q[1], q[2], q[3]])
            .map_err(|_| "not a pose")?;
        Ok(Self {
            translation_steps,
            largest,
            rest,
            se3,
        })
    }

    /// The integers that travel: translation in 0.1 mm, index of the largest quaternion
    /// component, the other three in 1/11863282.
    pub fn parts(&self) -> ([i64; 3], u8, [i32; 3]) {
        (self.translation_steps, self.largest, self.rest)
    }

    /// The pose as the receiver uses it.
    pub fn se3(&self) -> &SE3 {
        &self.se3
    }

    pub(crate) fn write(&self, s: &mut impl Sink) {
        for t in self.translation_steps {
            s.zigzag(t);
        }
        s.u8(self.largest);
        for c in self.rest {
            // 24-bit two's complement, little-endian.
            let b = (c as u32).to_le_bytes();
            s.u8(b[0]);
            s.u8(b[1]);
            s.u8(b[2]);
        }
    }

    pub(crate) fn read(r: &mut Reader<'_>, field: &'static str) -> Result<Self, WireError> {
        let offset = r.offset();
        let mut t = [0i64; 3];
        for v in &mut t {
            *v = r.zigzag(field)?;
        }
        let largest = r.u8(field)?;
        let mut q = [0i32; 3];
        for c in &mut q {
            let b = [r.u8(field)?, r.u8(field)?, r.u8(field)?];
            // Sign-extend bit 23.
            *c = (i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8) >> 8;
        }
        Self::from_parts(t, largest, q).map_err(|e| WireError::invalid(field, offset, e))
    }
}

/// Fewest bytes of a [`CompactPose`] on the wire (three one-byte varints and 10 bytes).
pub const COMPACT_POSE_MIN_BYTES: usize = 3 + 10;

/// A rotation of stage 1 of the distributed back-end (chordal relaxation): a 3×3 matrix
/// that is only approximately orthogonal while the iterations run, so it travels whole,
/// as nine i16 in steps of [`RELAXED_ROTATION_STEP`] (18 bytes; error ≤ 3.1e-5 per entry,
/// entries clamped to ±2 — a relaxed rotation's entries stay within ±1 plus the relaxation
/// error).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RelaxedRotation([i16; 9]);

impl RelaxedRotation {
    /// Rounds a row-major 3×3 matrix; refused if an entry is not finite.
    pub fn quantize(m: &[[f64; 3]; 3]) -> Result<Self, QuantizeError> {
        let mut out = [0i16; 9];
        for (k, v) in out.iter_mut().enumerate() {
            let x = m[k / 3][k % 3];
            if !x.is_finite() {
                return Err(QuantizeError::NonFinite {
                    field: "relaxed rotation",
                    value: x,
                });
            }
            *v = (x / RELAXED_ROTATION_STEP).round().clamp(-32767.0, 32767.0) as i16;
        }
        Ok(Self(out))
    }

    /// The row-major matrix.
    pub fn matrix(&self) -> [[f64; 3]; 3] {
        std::array::from_fn(|r| {
            std::array::from_fn(|c| f64::from(self.0[3 * r + c]) * RELAXED_ROTATION_STEP)
        })
    }

    /// The integers that travel.
    pub fn parts(&self) -> [i16; 9] {
        self.0
    }

    pub(crate) fn write(&self, s: &mut impl Sink) {
        for v in self.0 {
            s.u16(v as u16);
        }
    }

    pub(crate) fn read(r: &mut Reader<'_>, field: &'static str) -> Result<Self, WireError> {
        let mut out = [0i16; 9];
        for v in &mut out {
            *v = r.u16(field)? as i16;
        }
        Ok(Self(out))
    }
}

/// Bytes of a [`RelaxedRotation`] on the wire.
pub const RELAXED_ROTATION_BYTES: usize = 18;
