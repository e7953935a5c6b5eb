//! Scene light over a flight and the auto-exposure loop that follows it.
//!
//! Log light `ℓ(t) = w(t) − s(t) · shade_stops · ln 2`:
//! * `w(t) = σ √(2/M) Σᵢ sin(2π t / Pᵢ + φᵢ)`, M = 4 sinusoids with random periods in
//!   [`WALK_PERIODS_S`] and random phases: stationary σ, smooth (its slope is at most
//!   `σ √(2M) π / P_min` per second), bounded by `σ √(2M)`.
//! * `s(t)` ∈ {0, 1}, shade: entered at `shade_per_min` per minute, left after
//!   [`SHADE_MEAN_S`] on average (exponential dwell times), switched between frames.
//!
//! The auto-exposure meters frame k−1 and sets frame k's log exposure value (exposure
//! time × gain relative to the reference) `E_k = E_{k−1} − α (ℓ_{k−1} + E_{k−1})`,
//! `α = 1 − exp(−Δt / τ)`: a first-order loop one frame late. The exposure time takes
//! `E` first (within its limits), the gain the rest. Image brightness `B_k = exp(ℓ_k + E_k)`.

use crate::rng::SplitMix64;

use super::{mix, SensorModel};

/// Shortest and longest period of the light's random walk (seconds): clouds and the
/// drone's heading relative to the sun change over seconds, not within a frame.
pub const WALK_PERIODS_S: (f64, f64) = (4.0, 20.0);
/// Sinusoids summed in the walk.
const WALK_TERMS: usize = 4;
/// Mean time spent in shade (seconds).
pub const SHADE_MEAN_S: f64 = 3.0;

/// One frame's exposure, shared by both cameras of the synced pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameExposure {
    /// Exposure time (seconds), centred on the frame's timestamp.
    pub exposure_s: f64,
    /// Analog gain, in [1, max_gain].
    pub gain: f64,
    /// Scene light relative to the reference the renders are exposed for.
    pub light: f64,
    /// Image brightness relative to the ideal render: light × (exposure / reference
    /// exposure) × gain. 1 when the auto-exposure has caught up with the light.
    pub brightness: f64,
    /// Whether the drone is in shade at this frame.
    pub shade: bool,
}

/// The random walk of one flight: (period, phase) per sinusoid.
fn walk_terms(rng: &mut SplitMix64) -> [(f64, f64); WALK_TERMS] {
    let mut terms = [(0.0, 0.0); WALK_TERMS];
    for term in &mut terms {
        *term = (
            rng.range(WALK_PERIODS_S.0, WALK_PERIODS_S.1),
            rng.range(0.0, std::f64::consts::TAU),
        );
    }
    terms
}

fn walk_at(terms: &[(f64, f64)], sigma: f64, t: f64) -> f64 {
    let scale = sigma * (2.0 / terms.len() as f64).sqrt();
    scale
        * terms
            .iter()
            .map(|(period, phase)| (std::f64::consts::TAU * t / period + phase).sin())
            .sum::<f64>()
}

/// Every frame's exposure for one robot of a flight seeded with `seed`, at frame times
/// `times` (seconds, increasing). Deterministic; robots get independent light and shade.
/// `model` must be valid ([`SensorModel::validate`]).
pub fn exposure_track(
    model: &SensorModel,
    seed: u64,
    robot: usize,
    times: &[f64],
) -> Vec<FrameExposure> {
    let mut rng = SplitMix64::new(mix(seed ^ 0xE4B0_5E00_11C4_7000, robot as u64));
    let terms = walk_terms(&mut rng);
    let reference_s = model.exposure_ms * 1e-3;
    let (min_s, max_s) = (model.min_exposure_ms * 1e-3, model.max_exposure_ms * 1e-3);
    // Log exposure value range: shortest exposure at unity gain .. longest at most gain.
    let (e_min, e_max) = (
        (min_s / reference_s).ln(),
        (max_s * model.max_gain / reference_s).ln(),
    );
    let shade_drop = model.shade_stops * std::f64::consts::LN_2;
    let mut shade = false;
    let mut out: Vec<FrameExposure> = Vec::with_capacity(times.len());
    let mut previous: Option<(f64, f64, f64)> = None; // (time, log light, log exposure)
    for &t in times {
        let dt = previous.map_or(0.0, |(t0, _, _)| (t - t0).max(0.0));
        // Shade switches between frames: a Poisson entry rate, exponential dwell.
        if previous.is_some() {
            let p = if shade {
                1.0 - (-dt / SHADE_MEAN_S).exp()
            } else {
                1.0 - (-dt * model.shade_per_min / 60.0).exp()
            };
            if rng.unit() < p {
                shade = !shade;
            }
        }
        let log_light =
            walk_at(&terms, model.exposure_walk, t) - if shade { shade_drop } else { 0.0 };
        let log_exposure = match previous {
            // Converged on the first frame's light.
            None => -log_light,
            Some((_, l, e)) => {
                let alpha = if model.ae_time_constant_s > 0.0 {
                    1.0 - (-dt / model.ae_time_constant_s).exp()
                } else {
                    1.0
                };
                e - alpha * (l + e)
            }
        }
        .clamp(e_min, e_max);
        let exposure_s = (reference_s * log_exposure.exp()).clamp(min_s, max_s);
        let gain = (log_exposure.exp() * reference_s / exposure_s).clamp(1.0, model.max_gain);
        out.push(FrameExposure {
            exposure_s,
            gain,
            light: log_light.exp(),
            brightness: log_light.exp() * exposure_s / reference_s * gain,
            shade,
        });
        previous = Some((t, log_light, log_exposure));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn walk_has_the_requested_spread() {
        let mut rng = SplitMix64::new(5);
        let terms = walk_terms(&mut rng);
        let values: Vec<f64> = (0..20_000)
            .map(|k| walk_at(&terms, 0.3, k as f64 * 0.1))
            .collect();
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64;
        // 2000 s covers ≥ 100 periods of every term: the sample σ is within a few %.
        assert!((var.sqrt() - 0.3).abs() < 0.03, "σ {}", var.sqrt());
        assert!(values
            .iter()
            .all(|v| v.abs() <= 0.3 * (2.0 * WALK_TERMS as f64).sqrt()));
    }

    #[test]
    fn without_light_changes_the_exposure_stays_at_the_reference() {
        let model = SensorModel {
            exposure_walk: 0.0,
            shade_per_min: 0.0,
            ..SensorModel::default()
        };
        let times: Vec<f64> = (0..50).map(|k| k as f64 * 0.1).collect();
        for e in exposure_track(&model, 1, 0, &times) {
            assert!((e.brightness - 1.0).abs() < 1e-12, "{e:?}");
            assert!((e.exposure_s - model.exposure_ms * 1e-3).abs() < 1e-15);
            assert_eq!((e.gain, e.shade), (1.0, false));
        }
    }
}
