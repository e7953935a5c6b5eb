//! The verification feature packet a robot sends for geometric verification at a
//! rendezvous (`doorslam_ipc::wire::VerificationFeatures`): the one conversion between a
//! keyframe's [`Feature`]s and the wire form, both ways.
//!
//! What travels is what stereo measured: the pixel, the disparity and the ORB descriptor
//! of at most [`MAX_PACKET_FEATURES`] features, the keyframe's best first (keyframes keep
//! their features strongest first), with the rectified camera they were measured with. The
//! receiver rebuilds each 3-D point on its pixel's ray (`z = fx·b / d`). Sizes: 20 bytes of
//! camera, 38 per feature, so a full packet is 19,038-19,086 bytes with its header (target
//! ≤ 20 kB); BENCHMARKS.md compares verification on the packet with verification on the
//! full-precision features.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use doorslam_dataset::StereoCalibration;
use doorslam_ipc::wire::{
    Body, Header, Message, QuantizeError, RobotId, VerificationCamera, VerificationFeature,
    VerificationFeatures, WireError,
};

use crate::keyframe::{Feature, Keyframe};
use doorslam_vision::triangulate;

/// Most features a packet carries: 500 × 38 bytes + camera + header ≤ 19.1 kB.
pub const MAX_PACKET_FEATURES: usize = 500;

/// Why a packet could not be made or read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PacketError {
    #[error("feature {index}: {source}")]
    Feature {
        index: usize,
        #[source]
        source: QuantizeError,
    },
    #[error("camera: {0}")]
    Camera(#[source] QuantizeError),
    #[error("sender: {0}")]
    Sender(#[source] QuantizeError),
    #[error("a feature's point has depth {z} m: not in front of the camera")]
    BehindCamera { z: f32 },
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("a {found} message, expected verification features")]
    WrongKind { found: &'static str },
    #[error("{path}: {msg}")]
    File { path: PathBuf, msg: String },
}

/// The wire form of a rectified camera (f32 is far finer than any calibration).
pub fn wire_camera(calib: &StereoCalibration) -> Result<VerificationCamera, PacketError> {
    VerificationCamera::new(
        calib.fx as f32,
        calib.fy as f32,
        calib.cx as f32,
        calib.cy as f32,
        calib.baseline_m as f32,
    )
    .map_err(PacketError::Camera)
}

/// The calibration a packet's camera describes.
pub fn calibration_of(camera: &VerificationCamera) -> StereoCalibration {
    StereoCalibration {
        fx: f64::from(camera.fx),
        fy: f64::from(camera.fy),
        cx: f64::from(camera.cx),
        cy: f64::from(camera.cy),
        baseline_m: f64::from(camera.baseline_m),
    }
}

/// The packet of keyframe `key` (a multi-robot key): its first `max_features` features
/// (best first), measured with `calib`.
pub fn to_packet(
    key: u64,
    calib: &StereoCalibration,
    features: &[Feature],
    max_features: usize,
) -> Result<VerificationFeatures, PacketError> {
    let camera = wire_camera(calib)?;
    let features = features
        .iter()
        .take(max_features)
        .enumerate()
        .map(|(index, f)| {
            if f.point[2].is_nan() || f.point[2] <= 0.0 {
                return Err(PacketError::BehindCamera { z: f.point[2] });
            }
            // The disparity the point was triangulated from: d = fx·b / z.
            let disparity = (calib.fx * calib.baseline_m / f64::from(f.point[2])) as f32;
            VerificationFeature::quantize(f.pixel, disparity, f.descriptor)
                .map_err(|source| PacketError::Feature { index, source })
        })
        .collect::<Result<_, _>>()?;
    Ok(VerificationFeatures {
        key,
        camera,
        features,
    })
}

/// The features of a received packet, with the calibration they were measured with:
/// points rebuilt on each pixel's ray, depth σ from `disparity_sigma_px` (the stereo
/// noise model, as the odometry's).
pub fn from_packet(
    packet: &VerificationFeatures,
    disparity_sigma_px: f64,
) -> (StereoCalibration, Vec<Feature>) {
    let calib = calibration_of(&packet.camera);
    let features = packet
        .features
        .iter()
        .map(|f| {
            let [u, v] = f.pixel_px();
            let d = f64::from(f.disparity_px());
            let p = triangulate(&calib, f64::from(u), f64::from(v), d);
            Feature {
                pixel: [u, v],
                descriptor: f.descriptor,
                point: [p.x as f32, p.y as f32, p.z as f32],
                depth_sigma_m: (p.z / d * disparity_sigma_px) as f32,
            }
        })
        .collect();
    (calib, features)
}

/// A keyframe packet file (`doorslam vo --keyframes`, read by `doorslam verify`): the
/// encoded wire message, exactly as it would cross the radio, from sender `sender`.
pub fn packet_file_bytes(
    sender: &RobotId,
    sequence: u64,
    packet: VerificationFeatures,
) -> Result<Vec<u8>, PacketError> {
    let header = Header {
        sender: sender.clone(),
        epoch: 0,
        sequence,
    };
    Ok(Message::new(header, packet).encode()?)
}

/// Reads a keyframe packet file's bytes (bounded decoding, as from another robot).
pub fn packet_from_file_bytes(bytes: &[u8]) -> Result<VerificationFeatures, PacketError> {
    match Message::decode(bytes)?.body {
        Body::VerificationFeatures(v) => Ok(v),
        other => Err(PacketError::WrongKind {
            found: other.kind().name(),
        }),
    }
}

/// Reads a keyframe packet file; errors name it.
pub fn read_packet_file(path: &Path) -> Result<VerificationFeatures, PacketError> {
    let file_err = |msg: String| PacketError::File {
        path: path.to_path_buf(),
        msg,
    };
    let bytes = std::fs::read(path).map_err(|e| file_err(e.to_string()))?;
    packet_from_file_bytes(&bytes).map_err(|e| file_err(e.to_string()))
}

/// The file name of keyframe `id`'s packet in a `--keyframes` folder.
pub fn packet_file_name(id: u64) -> String {
    format!("kf_{id:06}.bin")
}

/// Writes one packet file per keyframe into `dir` (created if missing), as robot 'a' with
/// sender id `vo`, plus `keyframes.txt` (`id frame segment` and the 12 numbers of the
/// KITTI pose per line). Returns the total bytes of the packets.
pub fn write_keyframe_packets(
    dir: &Path,
    calib: &StereoCalibration,
    keyframes: &[Keyframe],
) -> Result<u64, PacketError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |e: std::io::Error| PacketError::File {
            path,
            msg: e.to_string(),
        }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let sender = RobotId::new("vo").map_err(PacketError::Sender)?;
    let mut total = 0u64;
    let mut index = String::new();
    for kf in keyframes {
        let key = doorslam_geometry::key::symbol(0, kf.id).map_err(|e| PacketError::File {
            path: dir.to_path_buf(),
            msg: format!("keyframe {}: {e}", kf.id),
        })?;
        let packet = to_packet(key, calib, &kf.features, MAX_PACKET_FEATURES)?;
        let bytes = packet_file_bytes(&sender, kf.id, packet)?;
        let path = dir.join(packet_file_name(kf.id));
        std::fs::write(&path, &bytes).map_err(io(&path))?;
        total += bytes.len() as u64;
        let m = kf.pose.to_homogeneous();
        let _ = write!(index, "{} {} {}", kf.id, kf.frame, kf.segment);
        for r in 0..3 {
            for c in 0..4 {
                let _ = write!(index, " {:.9e}", m[(r, c)]);
            }
        }
        index.push('\n');
    }
    let path = dir.join("keyframes.txt");
    std::fs::write(&path, index).map_err(io(&path))?;
    Ok(total)
}
