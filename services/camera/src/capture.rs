//! v4l2 stereo capture into the robot's frame service: two devices (left, right) or one
//! side-by-side device. Frames are requested as 8-bit grey (`GREY`), else YUYV, whose luma
//! is used. Each published frame costs one copy: from the driver's mmap buffer straight
//! into the loaned shared-memory sample (de-interleaving YUYV or side-by-side on the way).
//! Two free-running cameras are paired by timestamp: the older capture is dropped until
//! the two are within half a frame period.
//!
//! The capture loop needs a camera, which CI machines do not have: the no-camera path, the
//! luma extraction and the pairing rule are tested; the loop itself has not yet run on
//! hardware.

use std::time::Duration;

use doorslam_ipc::{create_node, FrameHeader, ImageWriter, Lifecycle, Sender, StereoFrame, Topic};
use v4l::buffer::Type;
use v4l::io::traits::CaptureStream;
use v4l::prelude::*;
use v4l::video::Capture;
use v4l::{Format, FourCC};

use crate::{open_devices, CameraConfig, CameraError};

/// `V4L2_CID_EXPOSURE_ABSOLUTE` (units of 100 µs).
const EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;

fn device_error(path: &std::path::Path, e: impl std::fmt::Display) -> CameraError {
    CameraError::Device {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

/// Sets the format (grey, else YUYV) and rate; returns the format the driver accepted.
fn configure(
    dev: &Device,
    path: &std::path::Path,
    width: u32,
    height: u32,
    config: &CameraConfig,
) -> Result<Format, CameraError> {
    let mut accepted = None;
    for code in [b"GREY", b"YUYV"] {
        let f = dev
            .set_format(&Format::new(width, height, FourCC::new(code)))
            .map_err(|e| device_error(path, e))?;
        if f.fourcc == FourCC::new(code) && f.width == width && f.height == height {
            accepted = Some(f);
            break;
        }
    }
    let format = accepted.ok_or_else(|| {
        device_error(
            path,
            format!("does not deliver {width}x{height} as GREY or YUYV"),
        )
    })?;
    dev.set_params(&v4l::video::capture::Parameters::with_fps(config.fps))
        .map_err(|e| device_error(path, e))?;
    if let Some(exposure) = config.exposure_100us {
        dev.set_control(v4l::Control {
            id: EXPOSURE_ABSOLUTE,
            value: v4l::control::Value::Integer(exposure as i64),
        })
        .map_err(|e| device_error(path, format!("setting exposure: {e}")))?;
    }
    Ok(format)
}

/// Luma of one image region, columns `x0..x0+w` of the first `h` rows, from a GREY or
/// YUYV buffer (Y0 U Y1 V: luma is every other byte), appended to `out`.
fn luma(
    buf: &[u8],
    format: &Format,
    x0: u32,
    w: u32,
    h: u32,
    out: &mut ImageWriter<'_>,
) -> Result<(), String> {
    let bpp = if format.fourcc == FourCC::new(b"YUYV") {
        2
    } else {
        1
    };
    if x0 + w > format.width || h > format.height {
        return Err(format!(
            "region {w}x{h} at column {x0} outside the {}x{} image",
            format.width, format.height
        ));
    }
    let row_bytes = (format.width * bpp) as usize;
    let stride = if format.stride > 0 {
        format.stride as usize
    } else {
        row_bytes
    };
    for y in 0..h as usize {
        let row = buf
            .get(y * stride..y * stride + row_bytes)
            .ok_or_else(|| format!("short frame from the driver: {} bytes", buf.len()))?;
        let region = &row[(x0 * bpp) as usize..((x0 + w) * bpp) as usize];
        let written = if bpp == 1 {
            out.extend_from_slice(region)
        } else {
            out.extend(region.iter().step_by(2).copied())
        };
        written.map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Two free-running cameras: whether their latest captures form a stereo pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pairing {
    /// Within `tolerance` of each other.
    Pair,
    /// The left capture is older than the right by more than `tolerance`: take a newer left.
    NewerLeft,
    /// The right capture is older: take a newer right.
    NewerRight,
}

fn pairing(left_ns: u64, right_ns: u64, tolerance_ns: u64) -> Pairing {
    if left_ns.abs_diff(right_ns) <= tolerance_ns {
        Pairing::Pair
    } else if left_ns < right_ns {
        Pairing::NewerLeft
    } else {
        Pairing::NewerRight
    }
}

fn stamp_ns(meta: &v4l::buffer::Metadata) -> u64 {
    meta.timestamp.sec as u64 * 1_000_000_000 + meta.timestamp.usec as u64 * 1000
}

/// Captures a pair after this many unpaired captures gives up on the pair (and says so):
/// cameras further apart than that are not a stereo rig.
const MAX_PAIRING_ATTEMPTS: usize = 8;

/// Captures until SIGTERM/SIGINT.
pub fn run(config: &CameraConfig, robot: &str, robot_index: u32) -> Result<(), CameraError> {
    let devices = open_devices(config)?;
    let paths = config.devices();
    let (w, h) = (config.width, config.height);
    let side_by_side = devices.len() == 1;
    let formats: Vec<Format> = devices
        .iter()
        .zip(&paths)
        .map(|(d, p)| configure(d, p, if side_by_side { 2 * w } else { w }, h, config))
        .collect::<Result<_, _>>()?;
    let mut streams: Vec<MmapStream> = devices
        .iter()
        .zip(&paths)
        .map(|(d, p)| {
            MmapStream::with_buffers(d, Type::VideoCapture, 4).map_err(|e| device_error(p, e))
        })
        .collect::<Result<_, _>>()?;
    let (node, _) = create_node("doorslam-camera")?;
    let sender = Sender::<StereoFrame>::new(&node, robot, Topic::Frames)?;
    let mut lifecycle = Lifecycle::new();
    lifecycle.ready(&format!("capturing {w}x{h} stereo at {} fps", config.fps));
    tracing::info!(devices = ?paths, side_by_side, ?formats, "camera: capturing");
    let mut seq = 0u64;
    let mut unpaired = 0u64;
    let mut last_warning: Option<std::time::Instant> = None;
    let tolerance_ns = Duration::from_secs_f64(0.5 / config.fps as f64).as_nanos() as u64;
    let (first, rest) = streams.split_at_mut(1);
    let (left_stream, mut right_stream) = (&mut first[0], rest.first_mut());
    while lifecycle.keep_going(&node) {
        let (mut buf_l, meta_l) = left_stream.next().map_err(|e| device_error(paths[0], e))?;
        let mut stamp_l = stamp_ns(meta_l);
        let header = |stamp_ns| FrameHeader {
            seq,
            stamp_ns,
            robot: robot_index,
            camera: 0,
            width: w,
            height: h,
            ..Default::default()
        };
        let Some(right_stream) = right_stream.as_deref_mut() else {
            // One side-by-side device: both halves of one capture.
            sender.send_with(|slot| {
                StereoFrame::write_with(slot, header(stamp_l), |l, r| {
                    luma(buf_l, &formats[0], 0, w, h, l)
                        .and_then(|()| luma(buf_l, &formats[0], w, w, h, r))
                        .map_err(|e| device_error(paths[0], e))
                })
            })?;
            seq += 1;
            continue;
        };
        let (mut buf_r, meta_r) = right_stream.next().map_err(|e| device_error(paths[1], e))?;
        let mut stamp_r = stamp_ns(meta_r);
        let mut attempts = 1;
        loop {
            match pairing(stamp_l, stamp_r, tolerance_ns) {
                Pairing::Pair => break,
                _ if attempts >= MAX_PAIRING_ATTEMPTS => break,
                Pairing::NewerLeft => {
                    let (b, m) = left_stream.next().map_err(|e| device_error(paths[0], e))?;
                    (buf_l, stamp_l) = (b, stamp_ns(m));
                }
                Pairing::NewerRight => {
                    let (b, m) = right_stream.next().map_err(|e| device_error(paths[1], e))?;
                    (buf_r, stamp_r) = (b, stamp_ns(m));
                }
            }
            attempts += 1;
            unpaired += 1;
        }
        if pairing(stamp_l, stamp_r, tolerance_ns) != Pairing::Pair {
            // Once a second at most: cameras out of sync stay so for every frame.
            if last_warning.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                last_warning = Some(std::time::Instant::now());
                tracing::warn!(
                    left_ns = stamp_l,
                    right_ns = stamp_r,
                    unpaired,
                    "camera: left and right captures stay more than half a frame apart; are both cameras running at {} fps?",
                    config.fps
                );
            }
            continue;
        }
        sender.send_with(|slot| {
            StereoFrame::write_with(slot, header(stamp_l), |l, r| {
                luma(buf_l, &formats[0], 0, w, h, l).map_err(|e| device_error(paths[0], e))?;
                luma(buf_r, &formats[1], 0, w, h, r).map_err(|e| device_error(paths[1], e))
            })
        })?;
        seq += 1;
    }
    tracing::info!(frames = seq, unpaired, "camera: stopped");
    lifecycle.stopping();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::MaybeUninit;

    /// Runs `luma` for both halves (or the whole image twice) into a real frame slot and
    /// returns the two images as written.
    fn extract(
        buf: &[u8],
        format: &Format,
        regions: [(u32, u32); 2],
        h: u32,
    ) -> (Vec<u8>, Vec<u8>) {
        let mut slot = Box::<StereoFrame>::new_uninit();
        let w = regions[0].1;
        let header = FrameHeader {
            width: w,
            height: h,
            ..Default::default()
        };
        StereoFrame::write_with(&mut slot, header, |l, r| {
            luma(buf, format, regions[0].0, w, h, l).map_err(CameraError::Config)?;
            luma(buf, format, regions[1].0, w, h, r).map_err(CameraError::Config)
        })
        .unwrap();
        // SAFETY: write_with returned Ok: header and both images are written.
        let frame = unsafe { slot.assume_init() };
        (
            frame.left_image().unwrap().to_vec(),
            frame.right_image().unwrap().to_vec(),
        )
    }

    fn format(code: &[u8; 4], width: u32, height: u32, stride: u32) -> Format {
        let mut f = Format::new(width, height, FourCC::new(code));
        f.stride = stride;
        f
    }

    #[test]
    fn grey_side_by_side_halves_with_row_padding() {
        // 4x2 side-by-side (two 2x2 eyes), rows padded to a stride of 6 bytes.
        let buf = [1, 2, 3, 4, 99, 99, 5, 6, 7, 8, 99, 99];
        let (l, r) = extract(&buf, &format(b"GREY", 4, 2, 6), [(0, 2), (2, 2)], 2);
        assert_eq!(l, [1, 2, 5, 6]);
        assert_eq!(r, [3, 4, 7, 8]);
    }

    #[test]
    fn yuyv_luma_is_every_other_byte() {
        // 2x2 YUYV: Y0 U Y1 V per pixel pair; chroma bytes are 200+.
        let buf = [10, 200, 11, 201, 12, 202, 13, 203];
        let (l, r) = extract(&buf, &format(b"YUYV", 2, 2, 0), [(0, 2), (0, 2)], 2);
        assert_eq!(l, [10, 11, 12, 13]);
        assert_eq!(r, l);
        // Side by side in YUYV: the right eye starts at pixel 2, byte 4 of each row.
        let buf = [
            1, 200, 2, 200, 3, 200, 4, 200, 5, 200, 6, 200, 7, 200, 8, 200,
        ];
        let (l, r) = extract(&buf, &format(b"YUYV", 4, 2, 0), [(0, 2), (2, 2)], 2);
        assert_eq!((l, r), (vec![1, 2, 5, 6], vec![3, 4, 7, 8]));
    }

    #[test]
    fn short_buffers_and_regions_outside_the_image_are_errors() {
        let mut slot = Box::<StereoFrame>::new_uninit();
        let header = FrameHeader {
            width: 2,
            height: 2,
            ..Default::default()
        };
        let grey = format(b"GREY", 2, 2, 0);
        let err = StereoFrame::write_with(&mut slot, header, |l, r| {
            luma(&[1, 2, 3], &grey, 0, 2, 2, l).map_err(CameraError::Config)?;
            luma(&[1, 2, 3, 4], &grey, 0, 2, 2, r).map_err(CameraError::Config)
        })
        .unwrap_err();
        assert!(
            err.to_string()
                .contains("short frame from the driver: 3 bytes"),
            "{err}"
        );
        let err = StereoFrame::write_with(&mut slot, header, |l, _| {
            luma(&[0; 4], &grey, 1, 2, 2, l).map_err(CameraError::Config)
        })
        .unwrap_err();
        assert!(err.to_string().contains("outside the 2x2 image"), "{err}");
        // A fill that stops short never yields a frame (the header is not written).
        let err = StereoFrame::write_with(&mut slot, header, |l, r| {
            luma(&[0; 4], &grey, 0, 2, 1, l).map_err(CameraError::Config)?;
            luma(&[0; 4], &grey, 0, 2, 2, r).map_err(CameraError::Config)
        })
        .unwrap_err();
        assert!(err.to_string().contains("left image has 2 bytes"), "{err}");
        let _: &mut MaybeUninit<StereoFrame> = &mut slot;
    }

    #[test]
    fn captures_pair_within_half_a_period_and_the_older_one_is_replaced() {
        let tol = 16_666_666; // half a period at 30 fps
        assert_eq!(pairing(1_000_000_000, 1_010_000_000, tol), Pairing::Pair);
        assert_eq!(pairing(1_010_000_000, 1_000_000_000, tol), Pairing::Pair);
        assert_eq!(
            pairing(1_000_000_000, 1_000_000_000 + tol, tol),
            Pairing::Pair
        );
        assert_eq!(
            pairing(1_000_000_000, 1_033_000_000, tol),
            Pairing::NewerLeft,
            "left is a frame behind: read left again"
        );
        assert_eq!(
            pairing(1_033_000_000, 1_000_000_000, tol),
            Pairing::NewerRight
        );
    }
}
