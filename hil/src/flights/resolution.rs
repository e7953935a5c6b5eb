//! Cameras for a requested image size.

use crate::camera::StereoCamera;

use super::FlightError;

/// Accepted image sides (pixels): below 16 nothing is recognizable, above 8192 one frame
/// no longer fits a shared-memory sample of the pipeline.
const SIDE: std::ops::RangeInclusive<u32> = 16..=8192;

/// The camera for `spec`: `euroc` (= `752x480`) and `kitti` are the presets
/// [`StereoCamera::euroc_like`] and [`StereoCamera::kitti_like`]; any other `WxH` scales
/// the EuRoC-like camera to width `W`, keeping its horizontal field of view and pixel
/// aspect (so the vertical field of view follows `H`), its principal point at the same
/// relative place, and its 11 cm baseline.
pub fn camera_for_resolution(spec: &str) -> Result<StereoCamera, FlightError> {
    let bad = |reason: String| FlightError::Resolution {
        spec: spec.to_string(),
        reason,
    };
    let trimmed = spec.trim().to_ascii_lowercase();
    match trimmed.as_str() {
        "euroc" => return Ok(StereoCamera::euroc_like()),
        "kitti" => return Ok(StereoCamera::kitti_like()),
        _ => {}
    }
    let (w, h) = trimmed
        .split_once('x')
        .ok_or_else(|| bad("no 'x' between width and height".into()))?;
    let side = |name: &str, text: &str| -> Result<u32, FlightError> {
        let value: u32 = text
            .trim()
            .parse()
            .map_err(|_| bad(format!("{name} {text:?} is not a whole number")))?;
        if SIDE.contains(&value) {
            Ok(value)
        } else {
            Err(bad(format!(
                "{name} {value} is outside {}..={}",
                SIDE.start(),
                SIDE.end()
            )))
        }
    };
    let (width, height) = (side("width", w)?, side("height", h)?);
    let euroc = StereoCamera::euroc_like();
    if (width, height) == (euroc.width(), euroc.height()) {
        return Ok(euroc);
    }
    // Pixel edges run from -0.5 to W - 0.5: scale positions measured from the edge.
    let sx = width as f64 / euroc.width() as f64;
    let sy = height as f64 / euroc.height() as f64;
    Ok(StereoCamera::new(
        width,
        height,
        euroc.fx() * sx,
        euroc.fy() * sx,
        (euroc.cx() + 0.5) * sx - 0.5,
        (euroc.cy() + 0.5) * sy - 0.5,
        euroc.baseline(),
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_scaling_and_errors() {
        assert_eq!(
            camera_for_resolution("752x480").unwrap(),
            StereoCamera::euroc_like()
        );
        assert_eq!(
            camera_for_resolution("KITTI").unwrap(),
            StereoCamera::kitti_like()
        );
        let small = camera_for_resolution("188x120").unwrap();
        let e = StereoCamera::euroc_like();
        let hfov = |c: &StereoCamera| (c.width() as f64 / (2.0 * c.fx())).atan();
        assert!((hfov(&small) - hfov(&e)).abs() < 1e-12);
        for bad in ["752", "752x", "axb", "8x8", "100000x10", "-5x7"] {
            let err = camera_for_resolution(bad).unwrap_err().to_string();
            assert!(err.contains(bad), "{err}");
        }
    }
}
