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

/// Metadata stamped on every frame by the camera (or replay) service.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("doorslam::FrameHeader")]
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
}

/// A rectified grayscale stereo pair, both images in one shared-memory sample.
///
/// The image buffers are `MaybeUninit` because a smaller camera fills only the leading
/// `width * height` bytes and nothing should pay for zeroing the rest on every frame.
/// The fields are private: [`StereoFrame::write`] is the only way to fill a frame, and it
/// guarantees that the bytes the accessors expose were written.
#[repr(C)]
#[derive(ZeroCopySend)]
#[type_name("doorslam::StereoFrame")]
pub struct StereoFrame {
    header: FrameHeader,
    left: [MaybeUninit<u8>; MAX_FRAME_PIXELS],
    right: [MaybeUninit<u8>; MAX_FRAME_PIXELS],
}

// The layout is part of the contract between processes built separately.
const _: () = assert!(core::mem::size_of::<FrameHeader>() == 32);
const _: () = assert!(core::mem::size_of::<StereoFrame>() == 32 + 2 * MAX_FRAME_PIXELS);

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
        let n = header.pixels()?;
        for (side, img) in [("left", left), ("right", right)] {
            if img.len() != n {
                return Err(FrameError::WrongLength {
                    side,
                    got: img.len(),
                    want: n,
                    width: header.width,
                    height: header.height,
                });
            }
        }
        let p = slot.as_mut_ptr();
        // SAFETY: `p` points to a valid (uninitialized) StereoFrame; we only write through
        // raw pointers, `n` <= MAX_FRAME_PIXELS was checked, and the sources do not overlap
        // the destination (they are ordinary slices, the destination is the sample).
        unsafe {
            core::ptr::addr_of_mut!((*p).header).write(header);
            let l = core::ptr::addr_of_mut!((*p).left) as *mut u8;
            core::ptr::copy_nonoverlapping(left.as_ptr(), l, n);
            let r = core::ptr::addr_of_mut!((*p).right) as *mut u8;
            core::ptr::copy_nonoverlapping(right.as_ptr(), r, n);
        }
        Ok(())
    }

    /// The frame's header.
    pub fn header(&self) -> &FrameHeader {
        &self.header
    }

    /// The left image (`width * height` bytes, row-major).
    pub fn left_image(&self) -> Result<&[u8], FrameError> {
        let n = self.header.pixels()?;
        // SAFETY: frames are only filled by `write`, which initialized the first `n` bytes.
        Ok(unsafe { core::slice::from_raw_parts(self.left.as_ptr() as *const u8, n) })
    }

    /// The right image (`width * height` bytes, row-major).
    pub fn right_image(&self) -> Result<&[u8], FrameError> {
        let n = self.header.pixels()?;
        // SAFETY: as for `left_image`.
        Ok(unsafe { core::slice::from_raw_parts(self.right.as_ptr() as *const u8, n) })
    }
}
