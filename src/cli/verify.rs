//! `doorslam verify KF_A KF_B`: geometric verification of two keyframe packets (files that
//! `doorslam vo --keyframes` writes: the wire message a robot sends), for debugging; and
//! `doorslam verify --bench DIR`: the verification benchmark on pairs with ground truth.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use doorslam_frontend::packet::{from_packet, read_packet_file};
use doorslam_frontend::verify_bench::{bench_folder, pose_error, summarize};
use doorslam_frontend::{verify, VerifyConfig, VoConfig};
use doorslam_geometry::LieGroup;

#[derive(Debug, Args)]
pub struct VerifyArgs {
    /// Packet of keyframe A (the reference: the pose printed is B's in A's frame).
    #[arg(required_unless_present = "bench")]
    pub kf_a: Option<PathBuf>,
    /// Packet of keyframe B.
    #[arg(required_unless_present = "bench")]
    pub kf_b: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Verification settings (TOML with any fields of the front-end's VerifyConfig).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Benchmark instead: every pair of a `doorslam sim world` output (closures.csv) or of
    /// EuRoC's loop-closure pairs folder, on full features and on the wire packet.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["kf_a", "kf_b"])]
    pub bench: Option<PathBuf>,
    /// With --bench: at most this many pairs of each kind (overlap, aliased).
    #[arg(long, requires = "bench")]
    pub limit: Option<usize>,
}

pub fn run(a: VerifyArgs) -> Result<()> {
    let config: VerifyConfig = match &a.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
        }
        None => VerifyConfig::default(),
    };
    if let Some(dir) = &a.bench {
        return bench(dir, &config, a.limit, a.json);
    }
    let (Some(path_a), Some(path_b)) = (&a.kf_a, &a.kf_b) else {
        anyhow::bail!("give two keyframe packets, or --bench DIR");
    };
    let packet_a = read_packet_file(path_a)?;
    let packet_b = read_packet_file(path_b)?;
    let (calib_a, features_a) = from_packet(&packet_a, config.disparity_sigma_px);
    let (calib_b, features_b) = from_packet(&packet_b, config.disparity_sigma_px);
    // A is the remote side (its points), B the local one (its pixels): X_A⁻¹ X_B.
    let outcome = verify(&calib_b, &features_b, &calib_a, &features_a, &config);
    match outcome {
        Ok(v) => {
            let t = v.relative.translation.vector;
            let q = v.relative.rotation;
            let rotation_deg = v.relative.rotation.angle().to_degrees();
            let covariance_diagonal: Vec<f64> = v
                .information
                .try_inverse()
                .map(|c| (0..6).map(|k| c[(k, k)].sqrt()).collect())
                .unwrap_or_default();
            if a.json {
                let information: Vec<Vec<f64>> = (0..6)
                    .map(|r| (0..6).map(|c| v.information[(r, c)]).collect())
                    .collect();
                println!(
                    "{}",
                    serde_json::json!({
                        "accepted": true,
                        "inliers": v.inliers,
                        "matches": v.matches,
                        "translation_m": [t.x, t.y, t.z],
                        "quaternion_xyzw": [q.i, q.j, q.k, q.w],
                        "rotation_deg": rotation_deg,
                        "distance_m": t.norm(),
                        "information": information,
                        "sigma_rotation_translation": covariance_diagonal,
                        "features_a": features_a.len(),
                        "features_b": features_b.len(),
                    })
                );
            } else {
                let log = v.relative.log();
                println!(
                    "accepted: {} inliers of {} matches ({} and {} features)\n\
                     B in A's frame: t = ({:.3}, {:.3}, {:.3}) m ({:.3} m), rotation {rotation_deg:.2}° (rotation vector {:.4} {:.4} {:.4})\n\
                     σ (rotation rad ×3, translation m ×3): {:.4?}",
                    v.inliers,
                    v.matches,
                    features_a.len(),
                    features_b.len(),
                    t.x,
                    t.y,
                    t.z,
                    t.norm(),
                    log[0],
                    log[1],
                    log[2],
                    covariance_diagonal
                );
            }
        }
        Err(rejection) => {
            if a.json {
                println!(
                    "{}",
                    serde_json::json!({
                        "accepted": false,
                        "rejection": rejection.name(),
                        "reason": rejection.to_string(),
                        "features_a": features_a.len(),
                        "features_b": features_b.len(),
                    })
                );
            } else {
                println!("rejected ({}): {rejection}", rejection.name());
            }
        }
    }
    Ok(())
}

fn bench(
    dir: &std::path::Path,
    config: &VerifyConfig,
    limit: Option<usize>,
    json: bool,
) -> Result<()> {
    let progress = |done: usize, total: usize| {
        if done.is_multiple_of(25) || done == total {
            eprintln!("verify: {done}/{total} pairs");
        }
    };
    let outcomes = bench_folder(dir, &VoConfig::default(), config, limit, &progress)
        .with_context(|| format!("verification benchmark on {}", dir.display()))?;
    let summary = summarize(&outcomes);
    if json {
        println!("{}", serde_json::to_string(&summary)?);
        return Ok(());
    }
    for o in &outcomes {
        let show = |r: &Result<doorslam_frontend::Verified, doorslam_frontend::Rejection>| match r {
            Ok(v) => {
                let (rot, t) = pose_error(&o.truth, &v.relative);
                format!(
                    "{:>4} inliers, error {rot:6.3}° {:7.1} mm",
                    v.inliers,
                    t * 1e3
                )
            }
            Err(e) => format!("rejected: {}", e.name()),
        };
        println!(
            "{:<14} {:<8} full: {:<38} packet ({} B): {}",
            o.label,
            o.kind.as_str(),
            show(&o.full),
            o.packet_bytes,
            show(&o.packet)
        );
    }
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
