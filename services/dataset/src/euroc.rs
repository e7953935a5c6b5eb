//! EuRoC (ASL) cameras: `sensor.yaml` read into a type, and the stereo rectification that
//! turns a distorted, slightly converging EuRoC pair into the rectified pair stereo VO
//! needs (same intrinsics, rows aligned, the right camera on the left one's x axis).
//!
//! `sensor.yaml` is OpenCV's own YAML dialect (`%YAML:1.0`), so OpenCV's `FileStorage`
//! reads it. Fields: `T_BS` (the camera's pose in the body/IMU frame, 4×4 row-major under
//! `data`), `resolution: [w, h]`, `camera_model: pinhole`, `intrinsics: [fu, fv, cu, cv]`,
//! `distortion_model: radial-tangential`, `distortion_coefficients: [k1, k2, p1, p2]`.
//!
//! The rectification is computed once ([`Rectifier::new`]: `cv::stereoRectify` with
//! `alpha = 0`, so every output pixel comes from inside both images and no black border
//! makes false corners, then `cv::initUndistortRectifyMap` into fixed-point maps); each
//! pair then costs two `cv::remap` calls.

use std::path::Path;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use opencv::core::{FileNode, FileStorage, FileStorage_Mode, Mat, Rect, Size};
use opencv::prelude::*;

use crate::{DatasetError, Pair, StereoCalibration};

/// One EuRoC camera as its `sensor.yaml` describes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EurocCamera {
    /// Image width and height (px).
    pub resolution: [u32; 2],
    /// `fu, fv, cu, cv` (px).
    pub intrinsics: [f64; 4],
    /// Radial-tangential `k1, k2, p1, p2`.
    pub distortion: [f64; 4],
    /// `T_BS`: the camera's pose in the body (IMU) frame.
    pub body_from_camera: Isometry3<f64>,
}

fn field_err(path: &Path, field: &str, msg: impl Into<String>) -> DatasetError {
    DatasetError::Field {
        path: path.to_path_buf(),
        field: field.to_string(),
        msg: msg.into(),
    }
}

fn cv_err<'a>(path: &'a Path, op: &'static str) -> impl Fn(opencv::Error) -> DatasetError + 'a {
    move |e| DatasetError::Layout {
        path: path.to_path_buf(),
        msg: format!("OpenCV {op}: {}", e.message),
    }
}

/// The numbers of a YAML sequence field, exactly `n` of them, all finite.
fn numbers(path: &Path, node: &FileNode, field: &str, n: usize) -> Result<Vec<f64>, DatasetError> {
    let err = |msg: String| field_err(path, field, msg);
    if node.is_none().unwrap_or(true) {
        return Err(err("missing".into()));
    }
    if !node.is_seq().unwrap_or(false) {
        return Err(err(format!("expected a list of {n} numbers")));
    }
    let len = node.size().unwrap_or(0);
    if len != n {
        return Err(err(format!("{len} values, expected {n}")));
    }
    (0..n)
        .map(|i| {
            let item = node.at(i as i32).map_err(|e| err(e.message))?;
            let is_number = item.is_real().unwrap_or(false) || item.is_int().unwrap_or(false);
            let v = item.real().unwrap_or(f64::NAN);
            if is_number && v.is_finite() {
                Ok(v)
            } else {
                Err(err(format!("value {i} is not a finite number")))
            }
        })
        .collect()
}

fn text(path: &Path, fs: &FileStorage, field: &str) -> Result<Option<String>, DatasetError> {
    let node = fs
        .get(field)
        .map_err(|e| field_err(path, field, e.message))?;
    if node.is_none().unwrap_or(true) {
        return Ok(None);
    }
    if !node.is_string().unwrap_or(false) {
        return Err(field_err(path, field, "expected a name"));
    }
    node.string()
        .map(|s| Some(s.trim().to_string()))
        .map_err(|e| field_err(path, field, e.message))
}

impl EurocCamera {
    /// Reads a `sensor.yaml`.
    pub fn from_yaml(path: &Path) -> Result<Self, DatasetError> {
        if !path.is_file() {
            return Err(DatasetError::Io {
                path: path.to_path_buf(),
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
            });
        }
        let name = path.to_string_lossy();
        let fs = FileStorage::new(name.as_ref(), FileStorage_Mode::READ as i32, "").map_err(
            cv_err(path, "FileStorage (not a readable OpenCV YAML file)"),
        )?;
        Self::from_storage(&fs, path)
    }

    /// [`Self::from_yaml`] on text already read; `path` names it in errors.
    pub fn parse_yaml(yaml: &str, path: &Path) -> Result<Self, DatasetError> {
        let flags = FileStorage_Mode::READ as i32 | FileStorage_Mode::MEMORY as i32;
        let fs = FileStorage::new(yaml, flags, "").map_err(cv_err(
            path,
            "FileStorage (not a readable OpenCV YAML file)",
        ))?;
        Self::from_storage(&fs, path)
    }

    fn from_storage(fs: &FileStorage, path: &Path) -> Result<Self, DatasetError> {
        if !fs.is_opened().unwrap_or(false) {
            return Err(DatasetError::Layout {
                path: path.to_path_buf(),
                msg: "not a readable OpenCV YAML file".into(),
            });
        }
        let node = |field: &str| fs.get(field).map_err(|e| field_err(path, field, e.message));
        if let Some(model) = text(path, fs, "camera_model")? {
            if model != "pinhole" {
                return Err(field_err(
                    path,
                    "camera_model",
                    format!("{model:?}: only pinhole is supported"),
                ));
            }
        }
        match text(path, fs, "distortion_model")? {
            Some(m) if m == "radial-tangential" || m == "radtan" => {}
            Some(m) => {
                return Err(field_err(
                    path,
                    "distortion_model",
                    format!("{m:?}: only radial-tangential is supported"),
                ))
            }
            None => return Err(field_err(path, "distortion_model", "missing")),
        }
        let res = numbers(path, &node("resolution")?, "resolution", 2)?;
        if res
            .iter()
            .any(|&v| !(1.0..=65535.0).contains(&v) || v.fract() != 0.0)
        {
            return Err(field_err(
                path,
                "resolution",
                format!("{res:?}: expected two whole numbers of pixels"),
            ));
        }
        let k = numbers(path, &node("intrinsics")?, "intrinsics", 4)?;
        if k[0] <= 0.0 || k[1] <= 0.0 {
            return Err(field_err(
                path,
                "intrinsics",
                format!("focal lengths fu = {}, fv = {}: must be > 0", k[0], k[1]),
            ));
        }
        let d = numbers(
            path,
            &node("distortion_coefficients")?,
            "distortion_coefficients",
            4,
        )?;
        let t_bs = node("T_BS")?;
        if t_bs.is_none().unwrap_or(true) {
            return Err(field_err(path, "T_BS", "missing"));
        }
        let data = t_bs
            .get("data")
            .map_err(|e| field_err(path, "T_BS.data", e.message))?;
        let m = numbers(path, &data, "T_BS.data", 16)?;
        for (sub, want) in [("rows", 4.0), ("cols", 4.0)] {
            let v = t_bs.get(sub).and_then(|n| n.real()).unwrap_or(f64::NAN);
            if v != want {
                return Err(field_err(
                    path,
                    &format!("T_BS.{sub}"),
                    format!("{v}, expected 4"),
                ));
            }
        }
        let body_from_camera =
            rigid_from_rows(&m).map_err(|msg| field_err(path, "T_BS.data", msg))?;
        Ok(Self {
            resolution: [res[0] as u32, res[1] as u32],
            intrinsics: [k[0], k[1], k[2], k[3]],
            distortion: [d[0], d[1], d[2], d[3]],
            body_from_camera,
        })
    }

    fn camera_matrix(&self) -> Result<Mat, opencv::Error> {
        let [fu, fv, cu, cv] = self.intrinsics;
        Mat::from_slice_2d(&[[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    }

    fn distortion_mat(&self) -> Result<Mat, opencv::Error> {
        Mat::from_slice_2d(&[self.distortion])
    }
}

/// A rigid transform from 16 row-major values: the last row must be `0 0 0 1` and the
/// rotation orthonormal to 1e-3 (then projected onto SO(3): the files print 12 digits).
fn rigid_from_rows(m: &[f64]) -> Result<Isometry3<f64>, String> {
    if (m[12], m[13], m[14], m[15]) != (0.0, 0.0, 0.0, 1.0) {
        return Err("the last row must be 0 0 0 1".into());
    }
    let r = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    let off = (r.transpose() * r - Matrix3::identity()).amax();
    if off > 1e-3 || r.determinant() <= 0.0 {
        return Err(format!(
            "the rotation is not a rotation (|RᵀR − I| = {off:.1e}, det {:.3})",
            r.determinant()
        ));
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r));
    Ok(Isometry3::from_parts(
        Translation3::new(m[3], m[7], m[11]),
        rotation,
    ))
}

/// The rectification of a stereo pair, computed once: the rectified calibration and the
/// maps that resample each raw image into it.
#[derive(Debug)]
pub struct Rectifier {
    calibration: StereoCalibration,
    size: [u32; 2],
    left_maps: (Mat, Mat),
    right_maps: (Mat, Mat),
    /// Pose of the rectified left camera in the body frame (`T_BS` of cam0 turned by the
    /// rectifying rotation): converts body ground truth into what VO estimates.
    body_from_rectified: Isometry3<f64>,
}

fn mat_f64(m: &Mat, r: i32, c: i32) -> Result<f64, opencv::Error> {
    m.at_2d::<f64>(r, c).copied()
}

impl Rectifier {
    /// Rectifies the pair `left` (cam0) / `right` (cam1); `path` names the calibration in
    /// errors. Both cameras must have the same resolution and the right camera must sit
    /// to the right of the left one.
    pub fn new(left: &EurocCamera, right: &EurocCamera, path: &Path) -> Result<Self, DatasetError> {
        if left.resolution != right.resolution {
            return Err(field_err(
                path,
                "resolution",
                format!(
                    "cam0 is {:?}, cam1 {:?}: the two cameras must match",
                    left.resolution, right.resolution
                ),
            ));
        }
        let cv = |op| cv_err(path, op);
        let [w, h] = left.resolution;
        let size = Size::new(w as i32, h as i32);
        // OpenCV wants the second camera's pose relative to the first: x₂ = R x₁ + T.
        let right_from_left = right.body_from_camera.inverse() * left.body_from_camera;
        let rot = right_from_left.rotation.to_rotation_matrix();
        let r = Mat::from_slice_2d(&[
            [rot[(0, 0)], rot[(0, 1)], rot[(0, 2)]],
            [rot[(1, 0)], rot[(1, 1)], rot[(1, 2)]],
            [rot[(2, 0)], rot[(2, 1)], rot[(2, 2)]],
        ])
        .map_err(cv("R"))?;
        let tv = right_from_left.translation.vector;
        let t = Mat::from_slice_2d(&[[tv.x], [tv.y], [tv.z]]).map_err(cv("T"))?;
        let (k1, d1) = (
            left.camera_matrix().map_err(cv("K1"))?,
            left.distortion_mat().map_err(cv("D1"))?,
        );
        let (k2, d2) = (
            right.camera_matrix().map_err(cv("K2"))?,
            right.distortion_mat().map_err(cv("D2"))?,
        );
        let (mut r1, mut r2, mut p1, mut p2, mut q) = (
            Mat::default(),
            Mat::default(),
            Mat::default(),
            Mat::default(),
            Mat::default(),
        );
        let (mut roi1, mut roi2) = (Rect::default(), Rect::default());
        opencv::calib3d::stereo_rectify(
            &k1,
            &d1,
            &k2,
            &d2,
            size,
            &r,
            &t,
            &mut r1,
            &mut r2,
            &mut p1,
            &mut p2,
            &mut q,
            opencv::calib3d::CALIB_ZERO_DISPARITY,
            0.0,
            size,
            Some(&mut roi1),
            Some(&mut roi2),
        )
        .map_err(cv("stereoRectify"))?;
        let get = |m: &Mat, r, c| mat_f64(m, r, c).map_err(cv("stereoRectify result"));
        let (fx, fy, cx, cy) = (
            get(&p1, 0, 0)?,
            get(&p1, 1, 1)?,
            get(&p1, 0, 2)?,
            get(&p1, 1, 2)?,
        );
        // P2 = K [I | -b eₓ]: its fourth column holds -fx·b.
        let baseline_m = -get(&p2, 0, 3)? / fx;
        if !(fx > 0.0 && fy > 0.0 && baseline_m > 0.0 && baseline_m.is_finite()) {
            return Err(field_err(
                path,
                "T_BS",
                format!(
                    "the rectified pair has fx {fx}, baseline {baseline_m} m: cam1 must be to the right of cam0"
                ),
            ));
        }
        let maps = |k: &Mat, d: &Mat, rr: &Mat, p: &Mat| -> Result<(Mat, Mat), DatasetError> {
            let (mut m1, mut m2) = (Mat::default(), Mat::default());
            opencv::calib3d::init_undistort_rectify_map(
                k,
                d,
                rr,
                p,
                size,
                opencv::core::CV_16SC2,
                &mut m1,
                &mut m2,
            )
            .map_err(cv("initUndistortRectifyMap"))?;
            Ok((m1, m2))
        };
        let left_maps = maps(&k1, &d1, &r1, &p1)?;
        let right_maps = maps(&k2, &d2, &r2, &p2)?;
        // R1 rotates cam0 coordinates into the rectified frame: x_rect = R1 x_cam0.
        let mut r1m = Matrix3::zeros();
        for i in 0..3 {
            for j in 0..3 {
                r1m[(i, j)] = get(&r1, i as i32, j as i32)?;
            }
        }
        let cam0_from_rect = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r1m.transpose())),
        );
        Ok(Self {
            calibration: StereoCalibration {
                fx,
                fy,
                cx,
                cy,
                baseline_m,
            },
            size: [w, h],
            left_maps,
            right_maps,
            body_from_rectified: left.body_from_camera * cam0_from_rect,
        })
    }

    /// Reads `cam0/sensor.yaml` and `cam1/sensor.yaml` under `base` (an EuRoC `mav0/`).
    pub fn from_euroc_folder(base: &Path) -> Result<Self, DatasetError> {
        let left = EurocCamera::from_yaml(&base.join("cam0/sensor.yaml"))?;
        let right = EurocCamera::from_yaml(&base.join("cam1/sensor.yaml"))?;
        Self::new(&left, &right, &base.join("cam1/sensor.yaml"))
    }

    /// The calibration of the rectified pair.
    pub fn calibration(&self) -> StereoCalibration {
        self.calibration
    }

    /// Image size (width, height) in and out.
    pub fn size(&self) -> [u32; 2] {
        self.size
    }

    /// Pose of the rectified left camera in the body frame.
    pub fn body_from_rectified(&self) -> Isometry3<f64> {
        self.body_from_rectified
    }

    /// Resamples a raw pair into the rectified one, writing into `left_out` / `right_out`
    /// (each `width × height` bytes, e.g. a loaned shared-memory sample).
    pub fn rectify_into(
        &self,
        left: &[u8],
        right: &[u8],
        left_out: &mut [u8],
        right_out: &mut [u8],
    ) -> Result<(), DatasetError> {
        let [w, h] = self.size;
        let n = (w * h) as usize;
        for (what, len) in [
            ("left image", left.len()),
            ("right image", right.len()),
            ("left output", left_out.len()),
            ("right output", right_out.len()),
        ] {
            if len != n {
                return Err(DatasetError::Layout {
                    path: "rectification".into(),
                    msg: format!("{what} has {len} bytes, the calibration is {w}x{h}"),
                });
            }
        }
        let path = Path::new("rectification");
        for (src, dst, (m1, m2)) in [
            (left, left_out, &self.left_maps),
            (right, right_out, &self.right_maps),
        ] {
            let src = Mat::new_rows_cols_with_data(h as i32, w as i32, src)
                .map_err(cv_err(path, "Mat over image"))?;
            let mut dst = Mat::new_rows_cols_with_data_mut(h as i32, w as i32, dst)
                .map_err(cv_err(path, "Mat over output"))?;
            opencv::imgproc::remap(
                &src,
                &mut dst,
                m1,
                m2,
                opencv::imgproc::INTER_LINEAR,
                opencv::core::BORDER_CONSTANT,
                opencv::core::Scalar::all(0.0),
            )
            .map_err(cv_err(path, "remap"))?;
        }
        Ok(())
    }

    /// The rectified pair of a raw one.
    pub fn rectify(&self, pair: &Pair) -> Result<Pair, DatasetError> {
        if [pair.width, pair.height] != self.size {
            return Err(DatasetError::Layout {
                path: "rectification".into(),
                msg: format!(
                    "a {}x{} pair, the calibration is {}x{}",
                    pair.width, pair.height, self.size[0], self.size[1]
                ),
            });
        }
        let n = pair.left.len();
        let (mut left, mut right) = (vec![0u8; n], vec![0u8; n]);
        self.rectify_into(&pair.left, &pair.right, &mut left, &mut right)?;
        Ok(Pair {
            width: pair.width,
            height: pair.height,
            left,
            right,
        })
    }
}
