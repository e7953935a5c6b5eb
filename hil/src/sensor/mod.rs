//! The realistic camera: what a global-shutter CMOS stereo rig (EuRoC's MT9V034 pair) does
//! to the scene the renderer sees, so simulated flights do not flatter the odometry.
//!
//! The renderer gives the scene radiance in the ideal camera's intensity units (0–255 is
//! what an exposure made for the town's reference light reads). Per frame, both cameras
//! of the synced pair share one exposure and each adds its own noise:
//!
//! 1. **Exposure** ([`exposure_track`]): the scene light wanders smoothly (a random-phase
//!    sum of slow sinusoids) and steps down and back up when the drone enters and leaves
//!    shade; an auto-exposure loop follows it one frame late with a time constant, first
//!    with the exposure time (up to a maximum), then with analog gain. The image's
//!    brightness is light × exposure × gain relative to the reference: 1 once the loop
//!    has caught up, dark or blown out right after a step.
//! 2. **Motion blur** ([`motion_blur`]): the camera moves during the exposure, which is
//!    centred on the frame's timestamp (the ground-truth pose is the mid-exposure pose).
//!    Not several renders along the trajectory but one: every pixel's scene point (from
//!    the rendered depth) is projected into the camera at the exposure's start and end,
//!    and the pixel averages the sharp image along that smear. Exact for a static scene
//!    whose image motion is locally uniform; at depth discontinuities the smear of a
//!    foreground edge does not spill over the background (the test compares it with the
//!    average of 24 sub-pose renders).
//! 3. **Vignetting**: light falls off with the squared distance from the principal
//!    point, by `vignetting` at the farthest corner.
//! 4. **Noise and digitization** ([`digitize`]): photon shot noise (variance in
//!    electrons = signal in electrons; `full_well_e` electrons fill the 8-bit range at
//!    unity gain) and read noise (`read_noise_dn` at unity gain), both amplified by the
//!    gain; rounded and clipped to 8 bits. A Gaussian approximation of the Poisson
//!    (exact mean and variance; signals here are thousands of electrons).
//!
//! Everything is deterministic: the exposure track from the flight seed and the robot,
//! each image's noise from the seed, robot, frame and eye.

mod blur;
mod digitize;
mod exposure;

use nalgebra::Isometry3;

use crate::camera::StereoCamera;
use crate::error::HilError;
use crate::render::{render_radiance, StereoPair};
use crate::rng::SplitMix64;
use crate::world::World;

pub use blur::{motion_blur, ExposureMotion};
pub use digitize::{digitize, standard_normal_approx, vignetting_factor};
pub use exposure::{exposure_track, FrameExposure, SHADE_MEAN_S, WALK_PERIODS_S};

/// What `doorslam sim world` images with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CameraModel {
    /// The renderer's pixels as they are: noise-free, perfectly exposed, no blur.
    Ideal,
    /// A global-shutter CMOS sensor with auto-exposure ([`SensorModel`]).
    Realistic(SensorModel),
}

impl CameraModel {
    /// `ideal` or `realistic`, as `--camera` and `world.txt` spell it.
    pub fn name(&self) -> &'static str {
        match self {
            CameraModel::Ideal => "ideal",
            CameraModel::Realistic(_) => "realistic",
        }
    }
}

impl Default for CameraModel {
    /// Realistic: the flights VO is benchmarked on should not flatter it.
    fn default() -> Self {
        CameraModel::Realistic(SensorModel::default())
    }
}

/// Settings of the realistic camera. `Default` is an MT9V034-like sensor (EuRoC's
/// cameras: 6 µm pixels, > 55 dB linear dynamic range, 1–4× analog gain) flying in
/// daylight with some cloud and building shade.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorModel {
    /// Electrons that fill the 8-bit range at unity gain: shot noise has variance
    /// `gain · 255 / full_well_e · DN` (DN²). 0 turns shot noise off.
    pub full_well_e: f64,
    /// Read noise σ in 8-bit DN at unity gain (multiplied by the gain). 0 turns it off.
    pub read_noise_dn: f64,
    /// Exposure time under the reference light (what the renders are exposed for).
    pub exposure_ms: f64,
    /// Shortest exposure the sensor makes (bright light).
    pub min_exposure_ms: f64,
    /// Longest exposure the auto-exposure allows before it raises the gain (motion blur
    /// grows with it); at most the frame period.
    pub max_exposure_ms: f64,
    /// Highest analog gain (noise grows with it); at least 1.
    pub max_gain: f64,
    /// σ of the smooth random walk of the scene light (natural log: 0.2 ≈ ±20 %). 0: none.
    pub exposure_walk: f64,
    /// Mean number of times per minute the drone enters shade (a sudden step). 0: never.
    pub shade_per_min: f64,
    /// How much darker shade is, in stops (factors of 2).
    pub shade_stops: f64,
    /// Time constant of the auto-exposure loop (seconds); 0 catches up in one frame.
    pub ae_time_constant_s: f64,
    /// Motion blur during the exposure.
    pub blur: bool,
    /// Fraction of light lost at the image corner farthest from the principal point. 0: none.
    pub vignetting: f64,
}

impl Default for SensorModel {
    fn default() -> Self {
        Self {
            // SNR at full scale √20000 ≈ 43 dB; σ ≈ 1.3 DN at mid-grey, unity gain.
            full_well_e: 20_000.0,
            // 55 dB dynamic range of the 10-bit ADC at 4× gain: ≈ 7 LSB₁₀ → 0.45 DN₈ at 1×.
            read_noise_dn: 0.45,
            exposure_ms: 5.0,
            min_exposure_ms: 0.05,
            max_exposure_ms: 20.0,
            max_gain: 4.0,
            exposure_walk: 0.2,
            shade_per_min: 2.0,
            shade_stops: 1.5,
            ae_time_constant_s: 0.2,
            blur: true,
            vignetting: 0.3,
        }
    }
}

fn invalid(field: &'static str, value: f64, reason: impl Into<String>) -> HilError {
    HilError::InvalidSensor {
        field,
        value,
        reason: reason.into(),
    }
}

impl SensorModel {
    /// Checks every field for frames at `rate_hz`; the error names the first bad one.
    pub fn validate(&self, rate_hz: f64) -> Result<(), HilError> {
        let in_range = |field, value: f64, lo: f64, hi: f64| {
            if value.is_finite() && value >= lo && value <= hi {
                Ok(())
            } else {
                Err(invalid(field, value, format!("must be in [{lo}, {hi}]")))
            }
        };
        in_range("full_well_e", self.full_well_e, 0.0, 1e9)?;
        if self.full_well_e > 0.0 && self.full_well_e < 255.0 {
            return Err(invalid(
                "full_well_e",
                self.full_well_e,
                "must be 0 (no shot noise) or at least 255 (one electron per DN)",
            ));
        }
        in_range("read_noise_dn", self.read_noise_dn, 0.0, 64.0)?;
        let period_ms = 1000.0 / rate_hz;
        in_range("max_exposure_ms", self.max_exposure_ms, 0.0, period_ms)?;
        in_range(
            "min_exposure_ms",
            self.min_exposure_ms,
            1e-6,
            self.max_exposure_ms,
        )?;
        in_range(
            "exposure_ms",
            self.exposure_ms,
            self.min_exposure_ms,
            self.max_exposure_ms,
        )?;
        in_range("max_gain", self.max_gain, 1.0, 64.0)?;
        in_range("exposure_walk", self.exposure_walk, 0.0, 2.0)?;
        in_range("shade_per_min", self.shade_per_min, 0.0, 600.0)?;
        in_range("shade_stops", self.shade_stops, 0.0, 10.0)?;
        in_range("ae_time_constant_s", self.ae_time_constant_s, 0.0, 60.0)?;
        in_range("vignetting", self.vignetting, 0.0, 0.95)?;
        Ok(())
    }

    /// The `key = value` lines `world.txt` records (TOML values).
    pub fn describe(&self) -> Vec<String> {
        vec![
            format!("full_well_e = {:e}", self.full_well_e),
            format!("read_noise_dn = {:e}", self.read_noise_dn),
            format!("exposure_ms = {:e}", self.exposure_ms),
            format!("min_exposure_ms = {:e}", self.min_exposure_ms),
            format!("max_exposure_ms = {:e}", self.max_exposure_ms),
            format!("max_gain = {:e}", self.max_gain),
            format!("exposure_walk = {:e}", self.exposure_walk),
            format!("shade_per_min = {:e}", self.shade_per_min),
            format!("shade_stops = {:e}", self.shade_stops),
            format!("ae_time_constant_s = {:e}", self.ae_time_constant_s),
            format!("blur = {}", self.blur),
            format!("vignetting = {:e}", self.vignetting),
        ]
    }
}

/// A 64-bit key mixed from two (SplitMix64's finaliser over their combination): streams
/// of noise per (seed, robot, frame, eye, row) that do not overlap.
pub(crate) fn mix(a: u64, b: u64) -> u64 {
    SplitMix64::new(a ^ b.wrapping_mul(0xD1B5_4A32_D192_ED03)).next_u64()
}

/// The noise seed of one stereo frame of one robot of a flight seeded with `seed`.
pub fn frame_noise_seed(seed: u64, robot: usize, frame: usize) -> u64 {
    mix(
        mix(seed ^ 0x5E45_0A0C_A3E7_A000, robot as u64),
        frame as u64,
    )
}

/// Renders the realistic pair whose LEFT camera is at `pose` (mid-exposure): both views'
/// radiance, blurred by `motion` (the left camera's, see [`ExposureMotion`]) when the
/// model blurs, then exposed, vignetted, made noisy (independently per eye, from
/// `noise_seed`) and digitized. `depth` is the left camera's sharp z-depth.
pub fn render_realistic(
    world: &World,
    camera: &StereoCamera,
    model: &SensorModel,
    pose: &Isometry3<f64>,
    exposure: &FrameExposure,
    motion: &ExposureMotion,
    noise_seed: u64,
) -> Result<StereoPair, HilError> {
    let (mut left, depth) = render_radiance(world, camera, pose);
    let (mut right, right_depth) = render_radiance(world, camera, &camera.right_pose(pose));
    if model.blur {
        left = motion_blur(&left, depth.values(), camera, motion)?;
        let right_motion = motion.of_right_camera(camera.baseline());
        right = motion_blur(&right, right_depth.values(), camera, &right_motion)?;
    }
    Ok(StereoPair {
        left: digitize(&left, camera, model, exposure, mix(noise_seed, 0))?,
        right: digitize(&right, camera, model, exposure, mix(noise_seed, 1))?,
        depth,
    })
}
