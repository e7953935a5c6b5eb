//! Fixed-size shared-memory payloads.
//!
//! Sizes are fixed at compile time from the maxima below; a smaller camera uses the
//! leading `width * height` bytes of each image buffer (row-major, no padding).

use core::mem::MaybeUninit;

use iceoryx2::prelude::*;

/// Largest image width any camera on the robot may deliver (pixels).
pub const MAX_FRAME_WIDTH: usize = 1280;
/// Largest image height any camera on the robot may deliver (pixels).
pub const MAX_FRAME_HEIGHT: usize = 720;
/// Bytes of one 8-bit grayscale image at the maximum resolution.
pub const MAX_FRAME_PIXELS: usize = MAX_FRAME_WIDTH * MAX_FRAME_HEIGHT;

/// Version of the shared-memory layout. It is part of every type name registered with
/// iceoryx2, so a process built against another layout cannot open the services: iceoryx2
/// refuses the mismatched type and [`crate::IpcError::SchemaMismatch`] says so.
pub const SCHEMA_VERSION: u32 = 1;

/// `FrameHeader::flags` bit: `truth_pose` holds the ground-truth pose (replay/simulation).
pub const FRAME_HAS_TRUTH: u32 = 1;

/// Metadata stamped on every frame by the camera (or replay) service.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::FrameHeader")]
pub struct FrameHeader {
    /// Sequence number, strictly increasing per camera, starting at 0.
    pub seq: u64,
    /// Capture time in nanoseconds (camera clock or dataset time).
    pub stamp_ns: u64,
    /// Robot index (0 = 'a', 1 = 'b', ...), as in the multi-robot key convention.
    pub robot: u32,
    /// Camera index on the robot.
    pub camera: u32,
    /// Image width in pixels (<= [`MAX_FRAME_WIDTH`]).
    pub width: u32,
    /// Image height in pixels (<= [`MAX_FRAME_HEIGHT`]).
    pub height: u32,
    /// Bit set of `FRAME_*` flags.
    pub flags: u32,
    pub reserved: u32,
    /// Ground-truth pose of the left camera in the world (x y z qx qy qz qw), valid when
    /// `flags & FRAME_HAS_TRUTH`: datasets and simulation carry it, cameras do not.
    pub truth_pose: [f64; 7],
}

/// A rectified grayscale stereo pair, both images in one shared-memory sample.
///
/// The image buffers are `MaybeUninit` because a smaller camera fills only the leading
/// `width * height` bytes and nothing should pay for zeroing the rest on every frame.
/// The fields are private: [`StereoFrame::write`] is the only way to fill a frame, and it
/// guarantees that the bytes the accessors expose were written.
#[repr(C)]
#[derive(ZeroCopySend)]
#[type_name("doorslam::v1::StereoFrame")]
pub struct StereoFrame {
    header: FrameHeader,
    left: [MaybeUninit<u8>; MAX_FRAME_PIXELS],
    right: [MaybeUninit<u8>; MAX_FRAME_PIXELS],
}

// The layout is part of the contract between processes built separately.
const _: () = assert!(core::mem::size_of::<FrameHeader>() == 96);
const _: () = assert!(core::mem::size_of::<StereoFrame>() == 96 + 2 * MAX_FRAME_PIXELS);

/// A frame that does not fit the compile-time maxima or whose images disagree with it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("frame {width}x{height} exceeds the maximum {MAX_FRAME_WIDTH}x{MAX_FRAME_HEIGHT}")]
    TooLarge { width: u32, height: u32 },
    #[error("{side} image has {got} bytes, header {width}x{height} needs {want}")]
    WrongLength {
        side: &'static str,
        got: usize,
        want: usize,
        width: u32,
        height: u32,
    },
    #[error("{side} image: more than the {want} bytes of a {width}x{height} image written")]
    Overflow {
        side: &'static str,
        want: usize,
        width: u32,
        height: u32,
    },
}

/// Appends the bytes of one image straight into a loaned frame, never past its end; the
/// frame is only sent if both images were filled exactly (see [`StereoFrame::write_with`]).
pub struct ImageWriter<'a> {
    side: &'static str,
    dst: &'a mut [MaybeUninit<u8>],
    len: usize,
    width: u32,
    height: u32,
}

impl ImageWriter<'_> {
    fn overflow(&self) -> FrameError {
        FrameError::Overflow {
            side: self.side,
            want: self.dst.len(),
            width: self.width,
            height: self.height,
        }
    }

    /// Appends `src` (one memcpy).
    pub fn extend_from_slice(&mut self, src: &[u8]) -> Result<(), FrameError> {
        let end = self.len + src.len();
        let Some(dst) = self.dst.get_mut(self.len..end) else {
            return Err(self.overflow());
        };
        // SAFETY: `dst` has exactly src.len() elements; u8 and MaybeUninit<u8> have the
        // same layout; the source is an ordinary slice, so the two cannot overlap.
        unsafe { core::ptr::copy_nonoverlapping(src.as_ptr(), dst.as_mut_ptr().cast(), src.len()) };
        self.len = end;
        Ok(())
    }

    /// Appends every byte of `bytes` (e.g. every other byte of a YUYV row: its luma).
    pub fn extend(&mut self, bytes: impl IntoIterator<Item = u8>) -> Result<(), FrameError> {
        for b in bytes {
            let Some(slot) = self.dst.get_mut(self.len) else {
                return Err(self.overflow());
            };
            slot.write(b);
            self.len += 1;
        }
        Ok(())
    }

    /// Bytes written so far.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Nothing written yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl FrameHeader {
    /// Pixels in one image of this frame, or an error if the size exceeds the maxima.
    pub fn pixels(&self) -> Result<usize, FrameError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if w <= MAX_FRAME_WIDTH && h <= MAX_FRAME_HEIGHT {
            Ok(w * h)
        } else {
            Err(FrameError::TooLarge {
                width: self.width,
                height: self.height,
            })
        }
    }
}

impl core::fmt::Debug for StereoFrame {
    // The images are megabytes: show the header only.
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("StereoFrame")
            .field("header", &self.header)
            .finish_non_exhaustive()
    }
}

impl StereoFrame {
    /// Writes a frame in place into uninitialized (shared) memory: the header and the two
    /// images, each `width * height` bytes, row-major. This is the one copy a frame ever
    /// gets: from the capture (or decode) buffer into the loaned sample.
    pub fn write(
        slot: &mut MaybeUninit<StereoFrame>,
        header: FrameHeader,
        left: &[u8],
        right: &[u8],
    ) -> Result<(), FrameError> {
        Self::write_with(slot, header, |l, r| {
            l.extend_from_slice(left)?;
            r.extend_from_slice(right)
        })
    }

    /// As [`Self::write`], with the images produced in place by `fill` (e.g. the luma of
    /// a camera's YUYV buffer, or the halves of a side-by-side image): no intermediate
    /// buffer. Fails unless `fill` wrote exactly `width * height` bytes to each image.
    pub fn write_with<E: From<FrameError>>(
        slot: &mut MaybeUninit<StereoFrame>,
        header: FrameHeader,
        fill: impl FnOnce(&mut ImageWriter<'_>, &mut ImageWriter<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        let n = header.pixels()?;
        let p = slot.as_mut_ptr();
        // SAFETY: `p` points to a valid (uninitialized) StereoFrame; the two image arrays
        // are disjoint fields of it, each MAX_FRAME_PIXELS >= n elements of MaybeUninit<u8>
        // (any bit pattern, so forming slices over them is sound).
        let (left, right) = unsafe {
            (
                core::slice::from_raw_parts_mut(core::ptr::addr_of_mut!((*p).left).cast(), n),
                core::slice::from_raw_parts_mut(core::ptr::addr_of_mut!((*p).right).cast(), n),
            )
        };
        let writer = |side, dst| ImageWriter {
            side,
            dst,
            len: 0,
            width: header.width,
            height: header.height,
        };
        let (mut l, mut r) = (writer("left", left), writer("right", right));
        fill(&mut l, &mut r)?;
        for w in [&l, &r] {
            if w.len != n {
                return Err(FrameError::WrongLength {
                    side: w.side,
                    got: w.len,
                    want: n,
                    width: header.width,
                    height: header.height,
                }
                .into());
            }
        }
        // SAFETY: as above; the header is plain data written in place. Only now, with
        // both images complete, does the frame get a header that makes them readable.
        unsafe { core::ptr::addr_of_mut!((*p).header).write(header) };
        Ok(())
    }

    /// The frame's header.
    pub fn header(&self) -> &FrameHeader {
        &self.header
    }

    /// The left image (`width * height` bytes, row-major).
    pub fn left_image(&self) -> Result<&[u8], FrameError> {
        let n = self.header.pixels()?;
        // SAFETY: frames are only filled by `write_with`, which checks that the first `n` bytes
        // of each image were written before it writes the header that declares them.
        Ok(unsafe { core::slice::from_raw_parts(self.left.as_ptr() as *const u8, n) })
    }

    /// The right image (`width * height` bytes, row-major).
    pub fn right_image(&self) -> Result<&[u8], FrameError> {
        let n = self.header.pixels()?;
        // SAFETY: as for `left_image`.
        Ok(unsafe { core::slice::from_raw_parts(self.right.as_ptr() as *const u8, n) })
    }
}

/// Most features a keyframe carries.
pub const MAX_KEYFRAME_FEATURES: usize = 1000;
/// Largest global place descriptor (floats).
pub const MAX_DESCRIPTOR_DIM: usize = 4096;

/// Where a keyframe comes from. Simulated keyframes are never visual odometry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum KeyframeSource {
    VisualOdometry = 0,
    /// Ground-truth poses forwarded from a dataset or simulation (no VO involved).
    SimulatedTruth = 1,
}

impl TryFrom<u32> for KeyframeSource {
    /// The value received, which names no source this schema knows.
    type Error = u32;
    fn try_from(v: u32) -> Result<Self, u32> {
        match v {
            0 => Ok(Self::VisualOdometry),
            1 => Ok(Self::SimulatedTruth),
            other => Err(other),
        }
    }
}

/// One feature of a keyframe: pixel, 3-D point in the camera frame, ORB descriptor.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::Feature")]
pub struct Feature {
    pub uv: [f32; 2],
    pub point: [f32; 3],
    pub descriptor: [u8; 32],
}

/// A keyframe: pose estimate and features. `source` is a [`KeyframeSource`] value.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::Keyframe")]
pub struct Keyframe {
    pub robot: u32,
    pub source: u32,
    /// Keyframe index on this robot, consecutive from 0.
    pub id: u64,
    /// Sequence number of the frame it was made from.
    pub frame_seq: u64,
    pub stamp_ns: u64,
    /// World pose estimate (x y z qx qy qz qw).
    pub pose: [f64; 7],
    pub n_features: u32,
    pub reserved: u32,
    pub features: [Feature; MAX_KEYFRAME_FEATURES],
}

impl Keyframe {
    /// Zeroes a loaned keyframe sample in place and hands it out to be filled field by
    /// field: a producer never builds the 52 kB value on its stack and copies it in. All
    /// fields are plain numbers, so all-zero bytes are a valid keyframe (no features).
    pub fn zeroed_in(slot: &mut MaybeUninit<Keyframe>) -> &mut Keyframe {
        // SAFETY: `slot` is valid for one Keyframe; every field of Keyframe (and of Feature)
        // is an integer, a float or an array of them, for which the all-zero bit pattern
        // is a valid value, so after write_bytes the value is fully initialized.
        unsafe {
            core::ptr::write_bytes(slot.as_mut_ptr(), 0, 1);
            slot.assume_init_mut()
        }
    }
}

/// Relative pose between two keyframes of one robot, information rotation-first
/// (upper triangle, row-major, 21 values).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::OdometryEdge")]
pub struct OdometryEdge {
    pub robot: u32,
    pub reserved: u32,
    pub from: u64,
    pub to: u64,
    pub stamp_ns: u64,
    /// `X_from⁻¹ X_to` (x y z qx qy qz qw).
    pub relative: [f64; 7],
    pub information: [f64; 21],
}

/// Global place descriptor of a keyframe (`dim` leading values used).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::PlaceDescriptor")]
pub struct PlaceDescriptor {
    pub robot: u32,
    pub dim: u32,
    pub keyframe: u64,
    pub values: [f32; MAX_DESCRIPTOR_DIM],
}

/// A verified loop closure between keyframes (of one robot or two).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::LoopClosure")]
pub struct LoopClosure {
    pub robot_a: u32,
    pub robot_b: u32,
    pub keyframe_a: u64,
    pub keyframe_b: u64,
    pub relative: [f64; 7],
    pub information: [f64; 21],
    /// PnP-RANSAC inliers that supported it.
    pub inliers: u32,
    pub reserved: u32,
}

/// The back-end's current estimate of one keyframe pose.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("doorslam::v1::PoseEstimate")]
pub struct PoseEstimate {
    pub robot: u32,
    pub reserved: u32,
    pub keyframe: u64,
    pub stamp_ns: u64,
    pub pose: [f64; 7],
}

/// Largest encoded wire message relayed between the team link and the back-end (a
/// `SeparatorGraph` of the wire's most edges, 1024 × 82 B, fits with room to spare).
pub const MAX_ENVELOPE_BYTES: usize = 256 * 1024;

/// What a [`WireEnvelope`] says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum EnvelopeEvent {
    /// One encoded wire message (`doorslam_ipc::wire::Message`): from the peer (team-in,
    /// with the header the peer's team link sent) or for the peer (team-out).
    Message = 0,
    /// Team-in: the peer said Hello; `epoch` is the peer's team-link epoch.
    PeerPresent = 1,
    /// Team-in: the peer left radio range (or stopped).
    PeerAbsent = 2,
    /// Team-in: the team link (re)started with epoch `epoch`; whatever it had not yet
    /// delivered is lost, so the back-end sends its state again.
    TeamStarted = 3,
    /// Team-out: the back-end (re)started with epoch `epoch`; the team link starts a new
    /// epoch of its own so that peers send their state again.
    BackendStarted = 4,
}

impl TryFrom<u32> for EnvelopeEvent {
    /// The value received, which names no event this schema knows.
    type Error = u32;
    fn try_from(v: u32) -> Result<Self, u32> {
        Ok(match v {
            0 => Self::Message,
            1 => Self::PeerPresent,
            2 => Self::PeerAbsent,
            3 => Self::TeamStarted,
            4 => Self::BackendStarted,
            other => return Err(other),
        })
    }
}

/// Relay between the team link and the back-end of one robot (topics `team-in`,
/// `team-out`): presence of peers and the distributed back-end's wire messages. The bytes
/// are `MaybeUninit` (like [`StereoFrame`]'s images) so that a 100-byte message does not
/// pay for zeroing 256 KiB; [`WireEnvelope::write`] is the only way to fill one.
#[repr(C)]
#[derive(ZeroCopySend)]
#[type_name("doorslam::v1::WireEnvelope")]
pub struct WireEnvelope {
    /// An [`EnvelopeEvent`] value.
    pub event: u32,
    /// The peer's robot number (0 = 'a'); for `TeamStarted`/`BackendStarted`, this robot's.
    pub peer_robot: u32,
    /// See [`EnvelopeEvent`]: a team-link or back-end epoch.
    pub epoch: u64,
    len: u32,
    reserved: u32,
    bytes: [MaybeUninit<u8>; MAX_ENVELOPE_BYTES],
}

/// A message too long for a [`WireEnvelope`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("wire message of {len} bytes exceeds the envelope's {MAX_ENVELOPE_BYTES}")]
pub struct EnvelopeTooLong {
    pub len: usize,
}

impl core::fmt::Debug for WireEnvelope {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("WireEnvelope")
            .field("event", &self.event)
            .field("peer_robot", &self.peer_robot)
            .field("epoch", &self.epoch)
            .field("len", &self.len)
            .finish_non_exhaustive()
    }
}

impl WireEnvelope {
    /// Fills a loaned sample in place: the fields and `bytes` (one copy).
    pub fn write(
        slot: &mut MaybeUninit<WireEnvelope>,
        event: EnvelopeEvent,
        peer_robot: u32,
        epoch: u64,
        bytes: &[u8],
    ) -> Result<(), EnvelopeTooLong> {
        if bytes.len() > MAX_ENVELOPE_BYTES {
            return Err(EnvelopeTooLong { len: bytes.len() });
        }
        let p = slot.as_mut_ptr();
        // SAFETY: `p` points to a valid (uninitialized) WireEnvelope; `bytes` fits in the
        // array (checked above); the fields are plain data written in place. The length is
        // written last, with the bytes it declares already there.
        unsafe {
            core::ptr::copy_nonoverlapping(
                bytes.as_ptr(),
                core::ptr::addr_of_mut!((*p).bytes).cast::<u8>(),
                bytes.len(),
            );
            core::ptr::addr_of_mut!((*p).event).write(event as u32);
            core::ptr::addr_of_mut!((*p).peer_robot).write(peer_robot);
            core::ptr::addr_of_mut!((*p).epoch).write(epoch);
            core::ptr::addr_of_mut!((*p).reserved).write(0);
            core::ptr::addr_of_mut!((*p).len).write(bytes.len() as u32);
        }
        Ok(())
    }

    /// The event, or the unknown value.
    pub fn event(&self) -> Result<EnvelopeEvent, u32> {
        EnvelopeEvent::try_from(self.event)
    }

    /// The message bytes (empty for presence events).
    pub fn bytes(&self) -> &[u8] {
        let n = (self.len as usize).min(MAX_ENVELOPE_BYTES);
        // SAFETY: envelopes are only filled by `write`, which wrote the first `len` bytes
        // (at most MAX_ENVELOPE_BYTES) before it wrote `len`.
        unsafe { core::slice::from_raw_parts(self.bytes.as_ptr() as *const u8, n) }
    }
}

const _: () = assert!(core::mem::size_of::<Feature>() == 52);
const _: () = assert!(core::mem::size_of::<Keyframe>() == 96 + 52 * MAX_KEYFRAME_FEATURES);
const _: () = assert!(core::mem::size_of::<OdometryEdge>() == 32 + 8 * 28);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keyframe_zeroed_in_place_over_garbage() {
        // A loaned sample holds whatever the last user left: all 0xFF here.
        let mut slot = Box::new(MaybeUninit::<Keyframe>::uninit());
        // SAFETY: writing bytes into the MaybeUninit's own storage.
        unsafe { core::ptr::write_bytes(slot.as_mut_ptr(), 0xFF, 1) };
        let kf = Keyframe::zeroed_in(&mut slot);
        assert_eq!((kf.id, kf.n_features, kf.pose), (0, 0, [0.0; 7]));
        assert!(kf.features.iter().all(|f| *f == Feature::default()));
        kf.features[3].uv = [1.5, 2.5];
        assert_eq!(kf.features[3].uv, [1.5, 2.5]);
    }
}
