//! # doorslam-dataset
//!
//! Stereo datasets on disk, read frame by frame: the camera service's replay source reads
//! them on the robot (hardware-in-the-loop runs), the offline tools and the simulator's
//! output use the same layouts. A robot-side crate, so the camera never depends on the
//! simulator.
//!
//! Layouts:
//! - **KITTI odometry**: `image_0/NNNNNN.png` (left), `image_1/NNNNNN.png` (right),
//!   `times.txt` (seconds, one line per frame), optional ground truth `poses.txt` (KITTI
//!   pose format, one line per frame; KITTI ships it separately as `poses/XX.txt`: point
//!   [`Dataset::with_truth`] at it).
//! - **EuRoC ASL**: `mav0/cam0/data/<ns>.png` and `mav0/cam1/data/<ns>.png` (the `mav0/`
//!   level is optional), timestamps from the file names, calibration in
//!   `cam0/sensor.yaml` and `cam1/sensor.yaml`. The images are distorted and not
//!   rectified: [`Dataset::stereo`] gives the [`Rectifier`] that makes them so. No ground
//!   truth is attached (it is the body frame, not the camera's).
//!
//! [`Dataset::split`] keeps one of N consecutive parts, as in the paper's KITTI 00
//! experiment where one sequence plays the role of several robots.

pub mod calibration;
pub mod euroc;

pub use calibration::StereoCalibration;
pub use euroc::{EurocCamera, Rectifier};

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

/// Failures of reading (or writing) a dataset; each names the file or folder.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {msg}")]
    Layout { path: PathBuf, msg: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode PNG: {msg}")]
    Png { path: PathBuf, msg: String },
    #[error("{path}: field {field}: {msg}")]
    Field {
        path: PathBuf,
        field: String,
        msg: String,
    },
    #[error("{path}:{line}: {msg}")]
    Line {
        path: PathBuf,
        line: usize,
        msg: String,
    },
}

/// Which on-disk layout a dataset uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    Kitti,
    Euroc,
}

/// One stereo frame on disk.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFiles {
    pub left: PathBuf,
    pub right: PathBuf,
    pub stamp_ns: u64,
    /// Index in the full sequence (kept through [`Dataset::split`]).
    pub index: usize,
}

/// A decoded stereo pair.
#[derive(Debug, Clone, PartialEq)]
pub struct Pair {
    pub width: u32,
    pub height: u32,
    pub left: Vec<u8>,
    pub right: Vec<u8>,
}

/// A dataset folder.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub root: PathBuf,
    pub layout: Layout,
    pub frames: Vec<FrameFiles>,
    /// Ground-truth left-camera pose per frame of `frames`, when known.
    pub truth: Option<Vec<Isometry3<f64>>>,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn pngs(dir: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")))
        .collect();
    files.sort();
    Ok(files)
}

/// The right image with the same file name as `left`, in `right_dir`.
fn right_of(left: &Path, right_dir: &Path) -> Result<PathBuf, DatasetError> {
    let r = right_dir.join(left.file_name().unwrap_or_default());
    if r.is_file() {
        Ok(r)
    } else {
        Err(DatasetError::Layout {
            path: r,
            msg: "right image missing for this left image".into(),
        })
    }
}

impl Dataset {
    /// Opens a KITTI or EuRoC folder (detected from its contents).
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        if root.join("image_0").is_dir() {
            return Self::open_kitti(root);
        }
        for base in [root.join("mav0"), root.to_path_buf()] {
            if base.join("cam0/data").is_dir() {
                return Self::open_euroc(root, &base);
            }
        }
        Err(DatasetError::Layout {
            path: root.to_path_buf(),
            msg: "not a dataset: expected image_0/ + image_1/ (KITTI) or [mav0/]cam0/data + cam1/data (EuRoC)".into(),
        })
    }

    fn open_kitti(root: &Path) -> Result<Self, DatasetError> {
        let left = pngs(&root.join("image_0"))?;
        let times_path = root.join("times.txt");
        let times: Vec<f64> = if times_path.is_file() {
            let text = std::fs::read_to_string(&times_path).map_err(io(&times_path))?;
            text.lines()
                .enumerate()
                .filter(|(_, l)| !l.trim().is_empty())
                .map(|(n, l)| {
                    l.trim()
                        .parse::<f64>()
                        .ok()
                        .filter(|t| t.is_finite() && *t >= 0.0)
                        .ok_or_else(|| DatasetError::Line {
                            path: times_path.clone(),
                            line: n + 1,
                            msg: format!("{l:?} is not a time in seconds"),
                        })
                })
                .collect::<Result<_, _>>()?
        } else {
            // Without times.txt, KITTI's 10 Hz.
            (0..left.len()).map(|i| i as f64 * 0.1).collect()
        };
        if times.len() != left.len() {
            return Err(DatasetError::Layout {
                path: times_path,
                msg: format!(
                    "{} times for {} images in image_0/",
                    times.len(),
                    left.len()
                ),
            });
        }
        let mut frames = Vec::with_capacity(left.len());
        for (index, (l, t)) in left.into_iter().zip(times).enumerate() {
            let r = right_of(&l, &root.join("image_1"))?;
            frames.push(FrameFiles {
                left: l,
                right: r,
                stamp_ns: (t * 1e9).round() as u64,
                index,
            });
        }
        let dataset = Self {
            root: root.to_path_buf(),
            layout: Layout::Kitti,
            frames,
            truth: None,
        };
        let poses = root.join("poses.txt");
        if poses.is_file() {
            return dataset.with_truth(&poses);
        }
        Ok(dataset)
    }

    fn open_euroc(root: &Path, base: &Path) -> Result<Self, DatasetError> {
        let mut frames = Vec::new();
        for (index, l) in pngs(&base.join("cam0/data"))?.into_iter().enumerate() {
            let name = l
                .file_stem()
                .and_then(|s| s.to_str())
                .unwrap_or_default()
                .to_string();
            let stamp_ns: u64 = name.parse().map_err(|_| DatasetError::Layout {
                path: l.clone(),
                msg: "EuRoC image names must be nanosecond timestamps".into(),
            })?;
            let r = right_of(&l, &base.join("cam1/data"))?;
            frames.push(FrameFiles {
                left: l,
                right: r,
                stamp_ns,
                index,
            });
        }
        Ok(Self {
            root: root.to_path_buf(),
            layout: Layout::Euroc,
            frames,
            truth: None,
        })
    }

    /// Attaches ground truth from a KITTI pose file (one line per frame of the full sequence).
    pub fn with_truth(mut self, path: &Path) -> Result<Self, DatasetError> {
        let text = std::fs::read_to_string(path).map_err(io(path))?;
        let mut poses = Vec::new();
        for (n, line) in text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
        {
            let v: Vec<f64> = line
                .split_whitespace()
                .filter_map(|x| x.parse().ok())
                .collect();
            if v.len() != 12 || v.iter().any(|x| !x.is_finite()) {
                return Err(DatasetError::Line {
                    path: path.into(),
                    line: n + 1,
                    msg: "expected 12 finite numbers (KITTI pose)".into(),
                });
            }
            let r = nalgebra::Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
            let rot = nalgebra::Rotation3::from_matrix(&r);
            poses.push(Isometry3::from_parts(
                nalgebra::Translation3::new(v[3], v[7], v[11]),
                rot.into(),
            ));
        }
        let needed = self.frames.iter().map(|f| f.index + 1).max().unwrap_or(0);
        if poses.len() < needed {
            return Err(DatasetError::Layout {
                path: path.into(),
                msg: format!("{} poses for {needed} frames", poses.len()),
            });
        }
        self.truth = Some(self.frames.iter().map(|f| poses[f.index]).collect());
        Ok(self)
    }

    /// Keeps part `part` (0-based) of `parts` consecutive, equal parts of the sequence.
    pub fn split(mut self, part: usize, parts: usize) -> Result<Self, DatasetError> {
        if parts == 0 || part >= parts {
            return Err(DatasetError::Layout {
                path: self.root.clone(),
                msg: format!("split part {part} of {parts}: need part < parts"),
            });
        }
        let n = self.frames.len();
        let (a, b) = (part * n / parts, (part + 1) * n / parts);
        self.frames = self.frames[a..b].to_vec();
        if let Some(t) = self.truth.take() {
            self.truth = Some(t[a..b].to_vec());
        }
        Ok(self)
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// The rectified stereo calibration: a KITTI-layout folder's `calib.txt` (as KITTI and
    /// `doorslam sim world` write it), or an EuRoC folder's `sensor.yaml` pair after
    /// rectification (which computes the maps: call [`Self::stereo`] to keep them).
    pub fn calibration(&self) -> Result<StereoCalibration, DatasetError> {
        Ok(self.stereo()?.calibration)
    }

    /// The camera of this dataset as stereo VO sees it: the rectified calibration and, for
    /// EuRoC folders, the rectifier every raw pair must go through first
    /// ([`Stereo::prepare`]). The one place both the offline VO and the camera's replay
    /// learn whether frames need rectifying.
    pub fn stereo(&self) -> Result<Stereo, DatasetError> {
        Ok(match self.rectifier()? {
            Some(rectifier) => Stereo {
                calibration: rectifier.calibration(),
                rectifier: Some(rectifier),
            },
            None => Stereo {
                calibration: StereoCalibration::from_kitti(&self.root.join("calib.txt"))?,
                rectifier: None,
            },
        })
    }

    /// The rectifier raw pairs need, `None` when the folder is rectified on disk (KITTI
    /// layout); reads no KITTI `calib.txt`, so a replay that only forwards frames does not
    /// need one.
    pub fn rectifier(&self) -> Result<Option<Rectifier>, DatasetError> {
        match self.layout {
            Layout::Kitti => Ok(None),
            Layout::Euroc => {
                let base = [self.root.join("mav0"), self.root.clone()]
                    .into_iter()
                    .find(|b| b.join("cam0/data").is_dir())
                    .unwrap_or_else(|| self.root.clone());
                Rectifier::from_euroc_folder(&base).map(Some)
            }
        }
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Decodes frame `k` (8-bit grayscale; colour is converted, 16-bit keeps the high byte).
    pub fn load(&self, k: usize) -> Result<Pair, DatasetError> {
        let f = self.frames.get(k).ok_or_else(|| DatasetError::Layout {
            path: self.root.clone(),
            msg: format!("no frame {k}"),
        })?;
        let (w, h, left) = read_gray_png(&f.left)?;
        let (w2, h2, right) = read_gray_png(&f.right)?;
        if (w, h) != (w2, h2) {
            return Err(DatasetError::Layout {
                path: f.right.clone(),
                msg: format!("{w2}x{h2}, left image is {w}x{h}"),
            });
        }
        Ok(Pair {
            width: w,
            height: h,
            left,
            right,
        })
    }
}

impl Dataset {
    /// Writes the pairs as stereo VO sees them (rectified when the folder is not) into
    /// `out` as a KITTI-layout folder: `image_0/`, `image_1/` (renumbered 000000.png, ...),
    /// `calib.txt` (the rectified `P0`, `P1`), `times.txt`, and `poses.txt` when the
    /// dataset has ground truth: another odometry can then run on exactly these frames.
    /// Returns the number of pairs written.
    pub fn write_kitti_layout(&self, out: &Path) -> Result<usize, DatasetError> {
        let stereo = self.stereo()?;
        for d in ["image_0", "image_1"] {
            let dir = out.join(d);
            std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        }
        let c = stereo.calibration;
        let calib = format!(
            "P0: {fx:e} 0 {cx:e} 0 0 {fy:e} {cy:e} 0 0 0 1 0\nP1: {fx:e} 0 {cx:e} {tx:e} 0 {fy:e} {cy:e} 0 0 0 1 0\n",
            fx = c.fx,
            fy = c.fy,
            cx = c.cx,
            cy = c.cy,
            tx = -c.fx * c.baseline_m,
        );
        let path = out.join("calib.txt");
        std::fs::write(&path, calib).map_err(io(&path))?;
        let mut times = String::new();
        let t0 = self.frames.first().map_or(0, |f| f.stamp_ns);
        for (k, f) in self.frames.iter().enumerate() {
            let pair = stereo.prepare(self.load(k)?)?;
            let name = format!("{k:06}.png");
            write_gray_png(
                &out.join("image_0").join(&name),
                pair.width,
                pair.height,
                &pair.left,
            )?;
            write_gray_png(
                &out.join("image_1").join(&name),
                pair.width,
                pair.height,
                &pair.right,
            )?;
            times.push_str(&format!(
                "{:.9}\n",
                f.stamp_ns.saturating_sub(t0) as f64 * 1e-9
            ));
        }
        let path = out.join("times.txt");
        std::fs::write(&path, times).map_err(io(&path))?;
        if let Some(truth) = &self.truth {
            let mut text = String::new();
            for p in truth {
                let m = p.to_homogeneous();
                let row: Vec<String> = (0..3)
                    .flat_map(|r| (0..4).map(move |c| (r, c)))
                    .map(|(r, c)| format!("{:e}", m[(r, c)]))
                    .collect();
                text.push_str(&row.join(" "));
                text.push('\n');
            }
            let path = out.join("poses.txt");
            std::fs::write(&path, text).map_err(io(&path))?;
        }
        Ok(self.frames.len())
    }
}

/// A dataset's stereo camera: the calibration of the pairs VO gets, and the rectifier raw
/// pairs go through when the dataset is not rectified on disk (EuRoC).
#[derive(Debug)]
pub struct Stereo {
    pub calibration: StereoCalibration,
    pub rectifier: Option<Rectifier>,
}

impl Stereo {
    /// The pair as VO must see it: rectified when the dataset is not.
    pub fn prepare(&self, pair: Pair) -> Result<Pair, DatasetError> {
        match &self.rectifier {
            Some(r) => r.rectify(&pair),
            None => Ok(pair),
        }
    }
}

/// Reads a PNG as 8-bit grayscale.
pub fn read_gray_png(path: &Path) -> Result<(u32, u32, Vec<u8>), DatasetError> {
    let png_err = |msg: String| DatasetError::Png {
        path: path.to_path_buf(),
        msg,
    };
    let file = std::fs::File::open(path).map_err(io(path))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(|e| png_err(e.to_string()))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| png_err(e.to_string()))?;
    let (w, h) = (info.width, info.height);
    let px = (w * h) as usize;
    let channels = info.color_type.samples();
    let bytes = &buf[..info.buffer_size()];
    let gray = match channels {
        1 => bytes[..px].to_vec(),
        2 => bytes.chunks_exact(2).map(|c| c[0]).collect(),
        3 | 4 => bytes
            .chunks_exact(channels)
            .map(|c| ((299 * c[0] as u32 + 587 * c[1] as u32 + 114 * c[2] as u32) / 1000) as u8)
            .collect(),
        n => return Err(png_err(format!("{n} channels"))),
    };
    Ok((w, h, gray))
}

/// Writes an 8-bit grayscale PNG (test fixtures, debugging dumps).
pub fn write_gray_png(
    path: &Path,
    width: u32,
    height: u32,
    pixels: &[u8],
) -> Result<(), DatasetError> {
    let file = std::fs::File::create(path).map_err(io(path))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    let png_err = |e: png::EncodingError| DatasetError::Png {
        path: path.to_path_buf(),
        msg: e.to_string(),
    };
    enc.write_header()
        .and_then(|mut w| w.write_image_data(pixels))
        .map_err(png_err)
}
