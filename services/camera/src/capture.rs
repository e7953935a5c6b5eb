//! v4l2 stereo capture into the robot's frame service: two devices (left, right) or one
//! side-by-side device. Frames are requested as 8-bit grey (`GREY`), else YUYV, whose luma
//! is used. Each published frame costs one copy: from the driver's mmap buffer into the
//! loaned shared-memory sample (plus a de-interleave for YUYV or side-by-side layouts).
//!
//! Not exercised by the test suite (no camera on CI machines): the no-camera path is.

use std::time::Duration;

use doorslam_ipc::{create_node, FrameHeader, Lifecycle, Sender, StereoFrame, Topic};
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

/// Luma of one image region: `x0..x0+w` of each row, from a GREY or YUYV buffer.
fn luma(
    buf: &[u8],
    format: &Format,
    x0: u32,
    w: u32,
    h: u32,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    out.clear();
    let bpp = if format.fourcc == FourCC::new(b"YUYV") {
        2
    } else {
        1
    };
    let stride = if format.stride > 0 {
        format.stride as usize
    } else {
        (format.width * bpp) as usize
    };
    for y in 0..h as usize {
        let row = buf
            .get(y * stride..y * stride + (format.width * bpp) as usize)
            .ok_or("short frame from the driver")?;
        out.extend(
            row.iter()
                .skip((x0 * bpp) as usize)
                .step_by(bpp as usize)
                .take(w as usize),
        );
    }
    Ok(())
}

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
    let (mut left, mut right) = (Vec::new(), Vec::new());
    let mut seq = 0u64;
    let period = Duration::from_secs_f64(1.0 / config.fps as f64);
    while lifecycle.keep_going(&node) {
        let (buf, meta) = streams[0].next().map_err(|e| device_error(paths[0], e))?;
        let stamp_ns =
            meta.timestamp.sec as u64 * 1_000_000_000 + meta.timestamp.usec as u64 * 1000;
        if side_by_side {
            luma(buf, &formats[0], 0, w, h, &mut left).map_err(|e| device_error(paths[0], e))?;
            luma(buf, &formats[0], w, w, h, &mut right).map_err(|e| device_error(paths[0], e))?;
        } else {
            luma(buf, &formats[0], 0, w, h, &mut left).map_err(|e| device_error(paths[0], e))?;
            let (buf_r, meta_r) = streams[1].next().map_err(|e| device_error(paths[1], e))?;
            let stamp_r =
                meta_r.timestamp.sec as u64 * 1_000_000_000 + meta_r.timestamp.usec as u64 * 1000;
            // Unsynchronized cameras: a pair more than half a period apart is not a stereo pair.
            if stamp_r.abs_diff(stamp_ns) > period.as_nanos() as u64 / 2 {
                tracing::warn!(
                    left_ns = stamp_ns,
                    right_ns = stamp_r,
                    "camera: left/right too far apart, frame skipped"
                );
                continue;
            }
            luma(buf_r, &formats[1], 0, w, h, &mut right).map_err(|e| device_error(paths[1], e))?;
        }
        let header = FrameHeader {
            seq,
            stamp_ns,
            robot: robot_index,
            camera: 0,
            width: w,
            height: h,
            ..Default::default()
        };
        sender.send_with(|slot| StereoFrame::write(slot, header, &left, &right))?;
        seq += 1;
    }
    lifecycle.stopping();
    Ok(())
}
