//! The realistic camera (`doorslam_hil::sensor`): noise statistics against the model,
//! smooth and bounded exposure changes, blur length and shape against the motion,
//! determinism, and the ideal camera left as it was.

use doorslam_hil::flights::{camera_for_resolution, simulate_team, FlightConfig, TeamCamera};
use doorslam_hil::sensor::{
    digitize, exposure_track, frame_noise_seed, motion_blur, render_realistic, CameraModel,
    ExposureMotion, FrameExposure, SensorModel, SHADE_MEAN_S, WALK_PERIODS_S,
};
use doorslam_hil::{look_at, render_radiance, render_stereo, GrayImage, StereoCamera, World};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn exposure(gain: f64) -> FrameExposure {
    FrameExposure {
        exposure_s: 0.005,
        gain,
        light: 1.0,
        brightness: 1.0,
        shade: false,
    }
}

fn mean_var(values: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = values.clone().count() as f64;
    let mean = values.clone().sum::<f64>() / n;
    let var = values.map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var)
}

fn pixels(image: &GrayImage) -> impl Iterator<Item = f64> + Clone + '_ {
    image.pixels().iter().map(|&p| p as f64)
}

#[test]
fn flat_patch_noise_follows_the_photon_transfer_curve() {
    let camera = StereoCamera::euroc_like();
    let n = (camera.width() * camera.height()) as usize;
    let model = SensorModel {
        vignetting: 0.0,
        ..SensorModel::default()
    };
    let k = 255.0 / model.full_well_e;
    for gain in [1.0, 3.0] {
        for level in [30.0f32, 100.0, 200.0] {
            let image = digitize(&vec![level; n], &camera, &model, &exposure(gain), 7).unwrap();
            let (mean, var) = mean_var(pixels(&image));
            // σ² = g K μ + g² σ_r², plus the rounding to integers (1/12).
            let mu = level as f64;
            let expected = gain * k * mu + (gain * model.read_noise_dn).powi(2) + 1.0 / 12.0;
            assert!(
                (mean - mu).abs() < 0.02,
                "gain {gain} level {level}: mean {mean}"
            );
            // 360,960 pixels: the variance is known to ±0.5 % (1σ).
            assert!(
                (var / expected - 1.0).abs() < 0.03,
                "gain {gain} level {level}: variance {var}, model {expected}"
            );
        }
    }
    // Negative control: without noise a flat patch stays flat.
    let quiet = SensorModel {
        full_well_e: 0.0,
        read_noise_dn: 0.0,
        ..model
    };
    let image = digitize(&vec![100.0; n], &camera, &quiet, &exposure(1.0), 7).unwrap();
    assert!(image.pixels().iter().all(|&p| p == 100));
}

#[test]
fn brightness_scales_the_signal_and_vignetting_darkens_the_corners() {
    let camera = StereoCamera::euroc_like();
    let n = (camera.width() * camera.height()) as usize;
    let model = SensorModel::default();
    let dim = FrameExposure {
        brightness: 0.5,
        ..exposure(1.0)
    };
    let image = digitize(&vec![160.0; n], &camera, &model, &dim, 1).unwrap();
    // Mean of 11×11 patches: the centre (principal point) and the four corners.
    let patch = |c0: u32, r0: u32| {
        mean_var(
            (r0..r0 + 11)
                .flat_map(|r| (c0..c0 + 11).map(move |c| (c, r)))
                .map(|(c, r)| image.get(c, r).unwrap() as f64),
        )
        .0
    };
    let centre = patch(camera.cx() as u32 - 5, camera.cy() as u32 - 5);
    assert!((centre - 80.0).abs() < 1.0, "centre {centre}");
    let (w, h) = (camera.width(), camera.height());
    let corner = patch(w - 11, h - 11)
        .min(patch(0, 0))
        .min(patch(w - 11, 0))
        .min(patch(0, h - 11));
    // The farthest corner loses `vignetting` of its light (the patch is 5 px inside it).
    let expected = 80.0 * (1.0 - model.vignetting);
    assert!(
        (corner - expected).abs() < 2.5,
        "corner {corner}, expected ≈ {expected}"
    );
}

#[test]
fn exposure_changes_are_smooth_bounded_and_recover_after_shade() {
    let model = SensorModel::default();
    let rate_hz = 10.0;
    let dt = 1.0 / rate_hz;
    let times: Vec<f64> = (0..6000).map(|k| k as f64 * dt).collect();
    // The walk's slope bound: σ √(2/M) · M · 2π / P_min with M = 4 terms.
    let walk_slope = model.exposure_walk * 8f64.sqrt() * std::f64::consts::TAU / WALK_PERIODS_S.0;
    // The auto-exposure loop's gain per frame; a first-order loop trails a ramp of slope s
    // per frame by s / α.
    let alpha = 1.0 - (-dt / model.ae_time_constant_s).exp();
    let lag = walk_slope * dt / alpha;
    let drop = model.shade_stops * std::f64::consts::LN_2;
    let mut shade_frames = 0;
    let mut entries = 0;
    for robot in 0..5 {
        let track = exposure_track(&model, 3, robot, &times);
        assert_eq!(
            track,
            exposure_track(&model, 3, robot, &times),
            "deterministic"
        );
        let mut since_switch = usize::MAX / 2;
        for (k, e) in track.iter().enumerate() {
            assert!(
                e.exposure_s >= model.min_exposure_ms * 1e-3 - 1e-15
                    && e.exposure_s <= model.max_exposure_ms * 1e-3 + 1e-15,
                "robot {robot} frame {k}: {e:?}"
            );
            assert!((1.0..=model.max_gain).contains(&e.gain), "{e:?}");
            let lb = e.brightness.ln();
            // Never further off than one shade step on top of the loop's lag.
            let reach = drop + walk_slope * dt + lag + 0.01;
            assert!(
                lb.abs() < reach,
                "robot {robot} frame {k}: brightness {}",
                e.brightness
            );
            shade_frames += usize::from(e.shade);
            let Some(prev) = k.checked_sub(1).map(|p| &track[p]) else {
                continue;
            };
            if e.shade != prev.shade {
                since_switch = 0;
                entries += usize::from(e.shade);
                // A sudden step: the light changes by the shade's stops (± the walk).
                let step = (e.light / prev.light).ln().abs();
                assert!((step - drop).abs() <= walk_slope * dt + 1e-9, "step {step}");
                // ... and the image with it, the exposure having reacted only to the
                // previous frame's small error.
                let image_step = (e.brightness / prev.brightness).ln().abs();
                assert!((image_step - step).abs() <= alpha * prev.brightness.ln().abs() + 1e-9);
                continue;
            }
            since_switch += 1;
            // Between steps the light changes smoothly ...
            let dl = (e.light / prev.light).ln().abs();
            assert!(
                dl <= walk_slope * dt + 1e-9,
                "robot {robot} frame {k}: Δ ln light {dl}"
            );
            // ... and one second (5 time constants) after a step the exposure has caught
            // up with it, up to its lag behind the walk.
            if since_switch >= 10 {
                assert!(
                    lb.abs() < lag + 0.02,
                    "robot {robot} frame {k}: brightness {}",
                    e.brightness
                );
            }
        }
    }
    // 5 × 600 s: in shade a fraction r·T/(1 + r·T) of the time (r = 2/min, T = 3 s: 9 %),
    // entered about r · (time in sun) times.
    let fraction = shade_frames as f64 / (5.0 * times.len() as f64);
    let expected = model.shade_per_min / 60.0 * SHADE_MEAN_S;
    let expected = expected / (1.0 + expected);
    assert!(
        (fraction - expected).abs() < 0.03,
        "shade fraction {fraction}, expected {expected}"
    );
    let expected_entries = 5.0 * 600.0 * (1.0 - expected) * model.shade_per_min / 60.0;
    assert!(
        (entries as f64 / expected_entries - 1.0).abs() < 0.25,
        "{entries} shade entries, expected ≈ {expected_entries}"
    );
    // Other robots and other seeds see other light.
    let a = exposure_track(&model, 3, 0, &times);
    assert_ne!(a, exposure_track(&model, 3, 1, &times));
    assert_ne!(a, exposure_track(&model, 4, 0, &times));
}

#[test]
fn long_shade_raises_exposure_then_gain() {
    // Deep shade (3 stops = 8× darker) needs 40 ms at unity gain: the exposure stops at
    // its 20 ms maximum and the gain makes up the factor 2.
    let model = SensorModel {
        exposure_walk: 0.0,
        shade_per_min: 600.0,
        shade_stops: 3.0,
        ..SensorModel::default()
    };
    let times: Vec<f64> = (0..300).map(|k| k as f64 * 0.1).collect();
    let track = exposure_track(&model, 1, 0, &times);
    let settled: Vec<_> = track
        .windows(15)
        .filter(|w| w.iter().all(|e| e.shade))
        .map(|w| w[14])
        .collect();
    assert!(
        !settled.is_empty(),
        "no long shade in 30 s at 600 entries/min"
    );
    for e in settled {
        assert!((e.exposure_s - 0.020).abs() < 1e-12, "{e:?}");
        assert!(
            (e.gain - 2.0).abs() < 0.05 && (e.brightness - 1.0).abs() < 0.03,
            "{e:?}"
        );
    }
}

/// A camera-to-camera motion `T(t)`: forward speed `v` (m/s) and yaw rate `w` (rad/s).
fn constant_motion(v: Vector3<f64>, w: Vector3<f64>, t: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(v * t),
        UnitQuaternion::from_scaled_axis(w * t),
    )
}

/// Light, centre and length of a row's smear of a one-pixel line: a box of length L has
/// variance L²/12, and bilinear sampling of the line adds a triangle's 1/6.
fn smear(profile: &[f32]) -> (f64, f64, f64) {
    let mass: f64 = profile.iter().map(|&p| p as f64).sum();
    let centre = profile
        .iter()
        .enumerate()
        .map(|(c, &p)| c as f64 * p as f64)
        .sum::<f64>()
        / mass;
    let var = profile
        .iter()
        .enumerate()
        .map(|(c, &p)| (c as f64 - centre).powi(2) * p as f64)
        .sum::<f64>()
        / mass;
    (mass, centre, (12.0 * (var - 1.0 / 6.0)).sqrt())
}

#[test]
fn pure_translation_smears_a_line_by_fx_v_t_over_z() {
    let camera = StereoCamera::euroc_like();
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    // A bright vertical line on black, every pixel 10 m away.
    let line = 300;
    let radiance: Vec<f32> = (0..w * h)
        .map(|i| if i % w == line { 255.0 } else { 0.0 })
        .collect();
    let depth = vec![10.0f32; w * h];
    // 8 m/s sideways through a 25 ms exposure: 0.2 m → fx · 0.2 / 10 = 9.17 px.
    let (speed, exposure_s, z) = (8.0, 0.025, 10.0);
    let motion = ExposureMotion {
        start: constant_motion(Vector3::x() * speed, Vector3::zeros(), -0.5 * exposure_s),
        end: constant_motion(Vector3::x() * speed, Vector3::zeros(), 0.5 * exposure_s),
    };
    let expected = camera.fx() * speed * exposure_s / z;
    let blurred = motion_blur(&radiance, &depth, &camera, &motion).unwrap();
    for row in [0, h / 2, h - 1] {
        let profile = &blurred[row * w..(row + 1) * w];
        let (mass, centre, length) = smear(profile);
        assert!(
            (mass / 255.0 - 1.0).abs() < 0.01,
            "row {row}: light not conserved: {mass}"
        );
        assert!(
            (centre - line as f64).abs() < 0.05,
            "row {row}: centre {centre}"
        );
        assert!(
            (length / expected - 1.0).abs() < 0.03,
            "row {row}: smear {length:.2} px, expected {expected:.2} px"
        );
    }
    // Twice as far away, half the smear; no motion, no smear at all.
    let far = vec![20.0f32; w * h];
    let (_, _, length) = smear(&motion_blur(&radiance, &far, &camera, &motion).unwrap()[..w]);
    assert!(
        (length / (expected / 2.0) - 1.0).abs() < 0.03,
        "smear {length:.2} px at 20 m"
    );
    let still = motion_blur(&radiance, &depth, &camera, &ExposureMotion::still()).unwrap();
    assert_eq!(still, radiance);
}

#[test]
fn blur_matches_the_average_of_sub_pose_renders() {
    // Low down a street, flying forward at 8 m/s and yawing at 1.5 rad/s through a 20 ms
    // exposure (a fast corner in shade): up to ~14 px of smear at the image edge.
    let world = World::town(7);
    let camera = StereoCamera::euroc_like();
    let mid = look_at(
        [-33.3, -80.0, 4.0].into(),
        [-33.3, 0.0, 3.0].into(),
        Vector3::z(),
    )
    .unwrap();
    let (v, w, exposure_s) = (Vector3::z() * 8.0, Vector3::y() * 1.5, 0.020);
    let at = |t: f64| mid * constant_motion(v, w, t);
    let motion = ExposureMotion::from_poses(&mid, &at(-0.5 * exposure_s), &at(0.5 * exposure_s));
    // Reference: the mean of 24 renders at the midpoints of 24 equal slices of the exposure.
    let slices = 24;
    let n = (camera.width() * camera.height()) as usize;
    let mut reference = vec![0f64; n];
    for s in 0..slices {
        let t = ((s as f64 + 0.5) / slices as f64 - 0.5) * exposure_s;
        let (r, _) = render_radiance(&world, &camera, &at(t));
        for (acc, v) in reference.iter_mut().zip(r) {
            *acc += v as f64 / slices as f64;
        }
    }
    let (sharp, depth) = render_radiance(&world, &camera, &mid);
    let blurred = motion_blur(&sharp, depth.values(), &camera, &motion).unwrap();
    let mad = |img: &[f32]| {
        img.iter()
            .zip(&reference)
            .map(|(&a, &b)| (a as f64 - b).abs())
            .sum::<f64>()
            / n as f64
    };
    let (err_blur, err_sharp) = (mad(&blurred), mad(&sharp));
    eprintln!("mean |error| against 24 sub-pose renders: blurred {err_blur:.3}, sharp {err_sharp:.3} (intensity levels)");
    assert!(err_sharp > 2.0, "the motion must blur visibly: {err_sharp}");
    assert!(
        err_blur < 0.15 * err_sharp,
        "blur {err_blur} vs sharp {err_sharp}"
    );
}

fn small_team() -> (World, doorslam_hil::flights::TeamFlight) {
    let world = World::town(2);
    let camera = camera_for_resolution("188x120").unwrap();
    let config = FlightConfig {
        robots: 2,
        frames: 6,
        seed: 2,
        ..FlightConfig::default()
    };
    let team = simulate_team(&world, &camera, &config).unwrap();
    (world, team)
}

#[test]
fn same_seed_same_bytes_on_any_thread_count() {
    let (world, team) = small_team();
    let camera = TeamCamera::new(&world, &team, CameraModel::default()).unwrap();
    let a = camera.render(1, 5).unwrap().unwrap();
    let b = camera.render(1, 5).unwrap().unwrap();
    assert_eq!(a, b);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let c = pool.install(|| camera.render(1, 5).unwrap().unwrap());
    assert_eq!(a, c, "one thread renders the same bytes");
    // The ideal camera renders exactly what the renderer does; the realistic one differs.
    let ideal = TeamCamera::new(&world, &team, CameraModel::Ideal).unwrap();
    let sharp = ideal.render(1, 5).unwrap().unwrap();
    assert_eq!(
        sharp,
        render_stereo(&world, &team.camera, &team.flights[1].poses[5])
    );
    assert_ne!(a.left, sharp.left);
    assert!(ideal.exposure(1, 5).is_none() && camera.exposure(1, 5).is_some());
    assert!(camera.render(2, 0).unwrap().is_none() && camera.render(1, 6).unwrap().is_none());
}

#[test]
fn realistic_with_every_effect_off_is_the_ideal_camera() {
    let (world, team) = small_team();
    let off = SensorModel {
        full_well_e: 0.0,
        read_noise_dn: 0.0,
        exposure_walk: 0.0,
        shade_per_min: 0.0,
        blur: false,
        vignetting: 0.0,
        ..SensorModel::default()
    };
    let realistic = TeamCamera::new(&world, &team, CameraModel::Realistic(off)).unwrap();
    let ideal = TeamCamera::new(&world, &team, CameraModel::Ideal).unwrap();
    for k in 0..6 {
        let (a, b) = (
            realistic.render(0, k).unwrap().unwrap(),
            ideal.render(0, k).unwrap().unwrap(),
        );
        for (x, y) in [(&a.left, &b.left), (&a.right, &b.right)] {
            // Same radiance; the realistic path rounds from f32 instead of f64.
            let differ = x
                .pixels()
                .iter()
                .zip(y.pixels())
                .filter(|(p, q)| p != q)
                .count();
            assert!(x.mean_abs_diff(y).unwrap() < 0.01 && differ * 1000 < x.pixels().len());
            assert!(x
                .pixels()
                .iter()
                .zip(y.pixels())
                .all(|(p, q)| p.abs_diff(*q) <= 1));
        }
    }
}

#[test]
fn both_eyes_share_the_exposure_but_not_the_noise() {
    let world = World::town(7);
    let camera = StereoCamera::euroc_like();
    let pose = look_at(
        [-66.7, -66.7, 14.0].into(),
        [0.0, 0.0, 0.0].into(),
        Vector3::z(),
    )
    .unwrap();
    let model = SensorModel {
        blur: false,
        ..SensorModel::default()
    };
    let still = ExposureMotion::still();
    let render = |e: &FrameExposure, seed| {
        render_realistic(&world, &camera, &model, &pose, e, &still, seed).unwrap()
    };
    let bright = render(&exposure(1.0), 1);
    // Same frame, other noise: the differences are pure noise, independent per eye.
    let other = render(&exposure(1.0), 2);
    let noise = |a: &GrayImage, b: &GrayImage| -> Vec<f64> {
        a.pixels()
            .iter()
            .zip(b.pixels())
            .map(|(&p, &q)| p as f64 - q as f64)
            .collect()
    };
    let (nl, nr) = (
        noise(&bright.left, &other.left),
        noise(&bright.right, &other.right),
    );
    let (_, vl) = mean_var(nl.iter().copied());
    let (_, vr) = mean_var(nr.iter().copied());
    let cov = nl.iter().zip(&nr).map(|(a, b)| a * b).sum::<f64>() / nl.len() as f64;
    let correlation = cov / (vl * vr).sqrt();
    assert!(vl > 1.0 && vr > 1.0, "noise variance {vl}, {vr}");
    assert!(
        correlation.abs() < 0.01,
        "left and right noise correlate: {correlation}"
    );
    // A darker exposure darkens both eyes alike.
    let dark = render(
        &FrameExposure {
            brightness: 0.5,
            ..exposure(1.0)
        },
        1,
    );
    let ratio = |a: &GrayImage, b: &GrayImage| a.mean_std().0 / b.mean_std().0;
    let (rl, rr) = (
        ratio(&dark.left, &bright.left),
        ratio(&dark.right, &bright.right),
    );
    assert!(
        (rl - 0.5).abs() < 0.03 && (rr - 0.5).abs() < 0.03,
        "{rl} {rr}"
    );
    // Noise seeds of frames and robots differ.
    assert_ne!(frame_noise_seed(1, 0, 0), frame_noise_seed(1, 0, 1));
    assert_ne!(frame_noise_seed(1, 0, 0), frame_noise_seed(1, 1, 0));
}

#[test]
fn invalid_settings_are_named() {
    let bad = |model: SensorModel, field: &str| {
        let err = model.validate(10.0).unwrap_err().to_string();
        assert!(err.contains(field), "{err}");
    };
    bad(
        SensorModel {
            max_exposure_ms: 150.0,
            ..SensorModel::default()
        },
        "max_exposure_ms",
    );
    bad(
        SensorModel {
            exposure_ms: 30.0,
            ..SensorModel::default()
        },
        "exposure_ms",
    );
    bad(
        SensorModel {
            read_noise_dn: f64::NAN,
            ..SensorModel::default()
        },
        "read_noise_dn",
    );
    bad(
        SensorModel {
            full_well_e: 10.0,
            ..SensorModel::default()
        },
        "full_well_e",
    );
    bad(
        SensorModel {
            max_gain: 0.5,
            ..SensorModel::default()
        },
        "max_gain",
    );
    bad(
        SensorModel {
            vignetting: 1.0,
            ..SensorModel::default()
        },
        "vignetting",
    );
    assert!(SensorModel::default().validate(10.0).is_ok());
    // A team camera refuses exposures longer than its frames.
    let (world, team) = small_team();
    let slow = SensorModel {
        max_exposure_ms: 101.0,
        ..SensorModel::default()
    };
    assert!(TeamCamera::new(&world, &team, CameraModel::Realistic(slow)).is_err());
}
