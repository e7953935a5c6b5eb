//! The calibration of a rectified stereo pair, as a type: what stereo VO needs to turn a
//! disparity into depth and a pixel into a ray.
//!
//! Read from KITTI's `calib.txt` (the rectified projection matrices `P0` of the left and
//! `P1` of the right camera, 12 row-major values each), which is also what
//! `doorslam sim world` writes for the simulator's cameras. Errors name the file, line and
//! field. EuRoC's `sensor.yaml` (unrectified: intrinsics, distortion, extrinsics) gives one
//! through rectification ([`crate::euroc::Rectifier`]).

use std::path::Path;

use crate::DatasetError;

/// A rectified stereo pair: both cameras share the intrinsics; the right one sits
/// `baseline_m` along the left camera's x axis (camera frame x right, y down, z forward).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoCalibration {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Distance between the optical centres, in metres (> 0).
    pub baseline_m: f64,
}

impl StereoCalibration {
    /// Reads `P0` and `P1` from a KITTI `calib.txt`.
    pub fn from_kitti(path: &Path) -> Result<Self, DatasetError> {
        let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse_kitti(&text, path)
    }

    /// [`Self::from_kitti`] on text already read; `path` names it in errors.
    pub fn parse_kitti(text: &str, path: &Path) -> Result<Self, DatasetError> {
        let line_err = |line: usize, msg: String| DatasetError::Line {
            path: path.to_path_buf(),
            line,
            msg,
        };
        let matrix = |name: &str| -> Result<(usize, [f64; 12]), DatasetError> {
            let (n, rest) = text
                .lines()
                .enumerate()
                .find_map(|(n, l)| l.strip_prefix(name)?.strip_prefix(':').map(|r| (n + 1, r)))
                .ok_or_else(|| DatasetError::Layout {
                    path: path.to_path_buf(),
                    msg: format!("no {name}: line (the rectified projection matrix)"),
                })?;
            let mut p = [0.0; 12];
            let mut count = 0;
            for (k, field) in rest.split_whitespace().enumerate() {
                let v: f64 = field
                    .parse()
                    .ok()
                    .filter(|v: &f64| v.is_finite())
                    .ok_or_else(|| {
                        line_err(n, format!("{name}[{k}] = {field:?} is not a finite number"))
                    })?;
                if k < 12 {
                    p[k] = v;
                }
                count += 1;
            }
            if count != 12 {
                return Err(line_err(
                    n,
                    format!("{name} has {count} values, expected 12 (3×4 row-major)"),
                ));
            }
            Ok((n, p))
        };
        let (n0, p0) = matrix("P0")?;
        let (n1, p1) = matrix("P1")?;
        let (fx, fy, cx, cy) = (p0[0], p0[5], p0[2], p0[6]);
        if fx <= 0.0 || fy <= 0.0 {
            return Err(line_err(
                n0,
                format!("P0 focal lengths fx = {fx}, fy = {fy}: must be > 0"),
            ));
        }
        if p0[3] != 0.0 || p0[7] != 0.0 {
            return Err(line_err(
                n0,
                "P0 must be the reference camera (no translation)".into(),
            ));
        }
        if [p1[0], p1[5], p1[2], p1[6]] != [fx, fy, cx, cy] || p1[7] != 0.0 {
            return Err(line_err(
                n1,
                "P1's intrinsics differ from P0's: the pair is not rectified".into(),
            ));
        }
        // P1 = K [I | -b e_x]: its fourth column is -fx·b.
        let baseline_m = -p1[3] / fx;
        if baseline_m <= 0.0 {
            return Err(line_err(
                n1,
                format!(
                    "P1[3] = {}: the right camera must be to the right of the left one",
                    p1[3]
                ),
            ));
        }
        Ok(Self {
            fx,
            fy,
            cx,
            cy,
            baseline_m,
        })
    }

    /// Depth (m) of a point seen with disparity `d` (px, > 0): `z = fx · b / d`.
    pub fn depth(&self, disparity_px: f64) -> f64 {
        self.fx * self.baseline_m / disparity_px
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const KITTI: &str =
        "P0: 700 0 600 0 0 710 180 0 0 0 1 0\nP1: 700 0 600 -350 0 710 180 0 0 0 1 0\nP2: 1 2 3\n";

    #[test]
    fn reads_p0_p1() {
        let c = StereoCalibration::parse_kitti(KITTI, Path::new("calib.txt")).unwrap();
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (700.0, 710.0, 600.0, 180.0));
        assert!((c.baseline_m - 0.5).abs() < 1e-15);
        assert!((c.depth(35.0) - 10.0).abs() < 1e-12);
    }

    #[test]
    fn errors_name_file_line_and_field() {
        let bad = |text: &str| {
            StereoCalibration::parse_kitti(text, Path::new("seq/calib.txt"))
                .unwrap_err()
                .to_string()
        };
        let e = bad("P0: 700 0 600 0 0 710 180 0 0 0 1 0\n");
        assert!(e.contains("seq/calib.txt") && e.contains("no P1"), "{e}");
        let e = bad(&KITTI.replace("P1: 700 0 600 -350", "P1: 700 0 600 nan"));
        assert!(e.contains("seq/calib.txt:2") && e.contains("P1[3]"), "{e}");
        let e = bad(&KITTI.replace(" 0 0 0 1 0\nP1", " 0 0 1\nP1"));
        assert!(e.contains(":1") && e.contains("P0 has 10 values"), "{e}");
        let e = bad(&KITTI.replace("-350", "350"));
        assert!(e.contains("right of the left"), "{e}");
        let e = bad(&KITTI.replace("P1: 700 0 600", "P1: 701 0 600"));
        assert!(e.contains("not rectified"), "{e}");
    }
}
