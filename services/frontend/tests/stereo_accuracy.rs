//! The row stereo's disparities against the renderer's true depth, on frames of the
//! realistic camera (noise, auto-exposure, motion blur) at drone speed: the gradient
//! refinement (`stereo_gradient_refine`, the default) must be more accurate than the
//! parabola through three block costs, whose sub-pixel values lock towards whole pixels.
//! The errors printed are what `disparity_sigma_px` models.

use doorslam_hil::flights::{simulate_team, FlightConfig, TeamCamera};
use doorslam_hil::sensor::{CameraModel, SensorModel};
use doorslam_hil::{StereoCamera, World};
use doorslam_vision::{Extractor, FeatureConfig, Gray};

/// A town and flight nobody tuned on, every 10th frame of 200 at 5.5 m/s.
const SEED: u64 = 9;
const FRAMES: usize = 200;

/// Disparity errors (px) of every feature whose pixel sits on a smooth surface (its 5×5
/// neighbourhood's true depths within 1 % of each other: a depth edge has no single
/// disparity), for one feature configuration.
fn disparity_errors(config: &FeatureConfig) -> Vec<f64> {
    let world = World::town(SEED);
    let flight = FlightConfig {
        robots: 1,
        frames: FRAMES,
        seed: SEED,
        speed_mps: 5.5,
        ..FlightConfig::default()
    };
    let camera = StereoCamera::euroc_like();
    let team = simulate_team(&world, &camera, &flight).expect("plan a flight");
    let imaging = TeamCamera::new(
        &world,
        &team,
        CameraModel::Realistic(SensorModel::default()),
    )
    .expect("a valid camera model");
    let mut extractor = Extractor::new(config).expect("extractor");
    let mut errors = Vec::new();
    for k in (0..FRAMES).step_by(10) {
        let pair = imaging.render(0, k).expect("render").expect("frame exists");
        let (w, h) = (pair.left.width() as usize, pair.left.height() as usize);
        let left = Gray::new(w, h, pair.left.pixels()).unwrap();
        let right = Gray::new(w, h, pair.right.pixels()).unwrap();
        for f in extractor.extract(&left, &right).expect("features").features {
            let (col, row) = (f.pixel[0].round() as i64, f.pixel[1].round() as i64);
            let mut depths = Vec::with_capacity(25);
            for dy in -2..=2 {
                for dx in -2..=2 {
                    let (c, r) = (col + dx, row + dy);
                    if c >= 0 && r >= 0 {
                        if let Some(z) = pair.depth.get(c as u32, r as u32) {
                            depths.push(z as f64);
                        }
                    }
                }
            }
            let (lo, hi) = depths.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &z| {
                (lo.min(z), hi.max(z))
            });
            if depths.len() < 25 || !hi.is_finite() || hi > 1.01 * lo {
                continue;
            }
            let z = pair.depth.get(col as u32, row as u32).unwrap() as f64;
            errors.push(f.disparity as f64 - camera.disparity(z));
        }
    }
    errors
}

/// Median absolute error and the RMS of the errors under 2 px (the block matcher's wrong
/// matches are the validation's business, not the noise model's).
fn summary(errors: &[f64]) -> (f64, f64, usize) {
    let mut abs: Vec<f64> = errors.iter().map(|e| e.abs()).collect();
    abs.sort_by(f64::total_cmp);
    let inliers: Vec<f64> = abs.iter().copied().filter(|e| *e < 2.0).collect();
    let rms = (inliers.iter().map(|e| e * e).sum::<f64>() / inliers.len().max(1) as f64).sqrt();
    (abs[abs.len() / 2], rms, inliers.len())
}

#[test]
fn gradient_refined_disparities_are_closer_to_the_true_depth() {
    let parabola = FeatureConfig {
        stereo_gradient_refine: false,
        ..FeatureConfig::default()
    };
    let (p_median, p_rms, p_n) = summary(&disparity_errors(&parabola));
    let (g_median, g_rms, g_n) = summary(&disparity_errors(&FeatureConfig::default()));
    eprintln!(
        "disparity error, parabola: median |e| {p_median:.3} px, RMS {p_rms:.3} px over {p_n}; \
         gradient: median |e| {g_median:.3} px, RMS {g_rms:.3} px over {g_n}"
    );
    assert!(p_n > 500 && g_n > 500, "too few smooth-surface features");
    assert!(
        g_median < 0.8 * p_median && g_rms < p_rms,
        "the gradient refinement is not more accurate"
    );
}
