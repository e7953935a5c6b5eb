//! Local bundle adjustment: the last few keyframes' poses and the landmarks they share,
//! refined together on the stereo reprojection errors of every keyframe observation.
//!
//! With keyframe poses `Tⱼ` (camera to world, right perturbation `Tⱼ · Exp(δⱼ)`, rotation
//! first) and world points `Xᵢ`, each observation `zᵢⱼ = (u, v, d)` has the residual
//! `rᵢⱼ = h(Tⱼ⁻¹ Xᵢ) − zᵢⱼ` (two rows when there was no disparity) with covariance
//! `S = diag(σu², σv², σd²)`. Levenberg-Marquardt minimises `Σ ρ(rᵀ S⁻¹ r)` (Huber) with
//! the oldest keyframe fixed (the gauge). The normal equations are solved by eliminating
//! the points first (each a 3×3 block): the Schur complement on the poses is a dense
//! `6(N−1)` square, small for a handful of keyframes. Its inverse at the optimum is the
//! poses' covariance, from which each odometry edge gets its information.

use nalgebra::{DMatrix, DVector, Matrix3, Matrix3x6, Matrix6, Matrix6x3, Vector3, Vector6};

use doorslam_dataset::StereoCalibration;
use doorslam_geometry::{inverse_action_jacobian, LieGroup, TangentMatrix, SE3};

use crate::refine::{project_stereo, Noise, StereoProjection};

/// One keyframe's measurement of one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct BundleObservation {
    pub point: usize,
    pub pose: usize,
    /// `(u, v, d)`; `d` unused when `stereo` is false.
    pub uvd: [f64; 3],
    pub stereo: bool,
}

/// The window: poses (`poses[0]` fixed), points, and what each pose saw.
#[derive(Debug, Clone, Default)]
pub(crate) struct Bundle {
    pub poses: Vec<SE3>,
    pub points: Vec<Vector3<f64>>,
    pub observations: Vec<BundleObservation>,
}

/// What the adjustment found.
#[derive(Debug, Clone)]
pub(crate) struct Adjusted {
    /// Covariance of poses `1..N` (their right perturbations, 6 each, in order).
    pub pose_covariance: DMatrix<f64>,
    /// χ² of the inlier observations and the residual dimensions they sum.
    pub chi2: f64,
    pub dimensions: usize,
    /// Observations whose χ² exceeds the outlier threshold at the optimum.
    pub outliers: Vec<bool>,
    /// The points' 3×3 covariances given the poses.
    pub point_covariances: Vec<Matrix3<f64>>,
}

struct Linear {
    r: Vector3<f64>,
    /// `S⁻¹`, with the third row and column zero for a two-row observation.
    w: Matrix3<f64>,
    jp: Matrix3x6<f64>,
    jx: Matrix3<f64>,
    chi2: f64,
}

fn linearize(
    calib: &StereoCalibration,
    noise: &Noise,
    pose: &SE3,
    x: &Vector3<f64>,
    o: &BundleObservation,
) -> Option<Linear> {
    let StereoProjection { rt, p, h, dh } = project_stereo(calib, pose, x)?;
    let (sp, sd) = (
        noise.pixel_sigma_px.powi(-2),
        noise.disparity_sigma_px.powi(-2),
    );
    let mut r = h - Vector3::new(o.uvd[0], o.uvd[1], o.uvd[2]);
    let w = if o.stereo {
        Matrix3::from_diagonal(&Vector3::new(sp, sp, sd))
    } else {
        r.z = 0.0;
        Matrix3::from_diagonal(&Vector3::new(sp, sp, 0.0))
    };
    let chi2 = (r.transpose() * w * r)[0];
    Some(Linear {
        r,
        w,
        jp: dh * inverse_action_jacobian(&p),
        jx: dh * rt,
        chi2,
    })
}

/// The normal equations after eliminating the points, and what back-substitution needs.
struct Reduced {
    s: DMatrix<f64>,
    g: DVector<f64>,
    /// Per point: `Hxx⁻¹` (damped) and its gradient.
    hxx_inv: Vec<Matrix3<f64>>,
    gx: Vec<Vector3<f64>>,
    /// Per observation: `Hpx` (6×3).
    hpx: Vec<Matrix6x3<f64>>,
    cost: f64,
}

fn reduce(
    bundle: &Bundle,
    calib: &StereoCalibration,
    noise: &Noise,
    huber: f64,
    lambda: f64,
) -> Option<Reduced> {
    let free = bundle.poses.len() - 1;
    let n = 6 * free;
    let mut hpp = vec![Matrix6::<f64>::zeros(); free];
    let mut gp = vec![Vector6::<f64>::zeros(); free];
    let mut hxx = vec![Matrix3::<f64>::zeros(); bundle.points.len()];
    let mut gx = vec![Vector3::<f64>::zeros(); bundle.points.len()];
    let mut hpx = vec![Matrix6x3::<f64>::zeros(); bundle.observations.len()];
    let mut cost = 0.0;
    for (k, o) in bundle.observations.iter().enumerate() {
        let Some(l) = linearize(
            calib,
            noise,
            &bundle.poses[o.pose],
            &bundle.points[o.point],
            o,
        ) else {
            continue;
        };
        let e = l.chi2.sqrt();
        let (weight, rho) = if e > huber {
            (huber / e, 2.0 * huber * e - huber * huber)
        } else {
            (1.0, l.chi2)
        };
        cost += rho;
        let w = l.w * weight;
        let jxw = l.jx.transpose() * w;
        hxx[o.point] += jxw * l.jx;
        gx[o.point] += jxw * l.r;
        if o.pose > 0 {
            let j = o.pose - 1;
            let jpw = l.jp.transpose() * w;
            hpp[j] += jpw * l.jp;
            gp[j] += jpw * l.r;
            hpx[k] = jpw * l.jx;
        }
    }
    let mut s = DMatrix::<f64>::zeros(n, n);
    let mut g = DVector::<f64>::zeros(n);
    for j in 0..free {
        let mut block = hpp[j];
        for d in 0..6 {
            block[(d, d)] += lambda * block[(d, d)].max(1e-9);
        }
        s.fixed_view_mut::<6, 6>(6 * j, 6 * j).copy_from(&block);
        g.fixed_rows_mut::<6>(6 * j).copy_from(&gp[j]);
    }
    let mut hxx_inv = Vec::with_capacity(hxx.len());
    for h in &hxx {
        let mut h = *h;
        for d in 0..3 {
            h[(d, d)] += lambda * h[(d, d)].max(1e-9) + 1e-12;
        }
        hxx_inv.push(h.try_inverse().unwrap_or_else(Matrix3::zeros));
    }
    // Observations of each point, to form the point's contributions pairwise.
    let mut by_point: Vec<Vec<usize>> = vec![Vec::new(); bundle.points.len()];
    for (k, o) in bundle.observations.iter().enumerate() {
        if o.pose > 0 {
            by_point[o.point].push(k);
        }
    }
    for (i, obs) in by_point.iter().enumerate() {
        let inv = hxx_inv[i];
        for &a in obs {
            let ja = bundle.observations[a].pose - 1;
            let left = hpx[a] * inv;
            let ga = left * gx[i];
            let mut rows = g.fixed_rows_mut::<6>(6 * ja);
            rows -= ga;
            for &b in obs {
                let jb = bundle.observations[b].pose - 1;
                let block = left * hpx[b].transpose();
                let mut view = s.fixed_view_mut::<6, 6>(6 * ja, 6 * jb);
                view -= block;
            }
        }
    }
    s.iter().all(|x| x.is_finite()).then_some(Reduced {
        s,
        g,
        hxx_inv,
        gx,
        hpx,
        cost,
    })
}

fn total_cost(bundle: &Bundle, calib: &StereoCalibration, noise: &Noise, huber: f64) -> f64 {
    bundle
        .observations
        .iter()
        .map(|o| {
            linearize(
                calib,
                noise,
                &bundle.poses[o.pose],
                &bundle.points[o.point],
                o,
            )
            .map_or(0.0, |l| {
                let e = l.chi2.sqrt();
                if e > huber {
                    2.0 * huber * e - huber * huber
                } else {
                    l.chi2
                }
            })
        })
        .sum()
}

/// Levenberg-Marquardt on the window (at most `iterations` steps); `None` when the poses'
/// normal equations are singular (too few shared points: the window cannot be adjusted).
pub(crate) fn adjust(
    bundle: &mut Bundle,
    calib: &StereoCalibration,
    noise: &Noise,
    outlier_chi2: f64,
    iterations: usize,
) -> Option<Adjusted> {
    if bundle.poses.len() < 2 {
        return None;
    }
    let huber = outlier_chi2.sqrt();
    let free = bundle.poses.len() - 1;
    let mut lambda = 1e-4;
    for _ in 0..iterations {
        let reduced = reduce(bundle, calib, noise, huber, lambda)?;
        let Some(chol) = reduced.s.clone().cholesky() else {
            lambda *= 10.0;
            continue;
        };
        let dp = -chol.solve(&reduced.g);
        let mut trial = bundle.clone();
        for j in 0..free {
            let d: Vector6<f64> = dp.fixed_rows::<6>(6 * j).into_owned();
            trial.poses[j + 1] = trial.poses[j + 1].oplus(&d);
        }
        // Back-substitution: δxᵢ = −Hxxᵢ⁻¹ (gxᵢ + Σⱼ Hpxᵢⱼᵀ δpⱼ).
        let mut rhs = reduced.gx.clone();
        for (k, o) in bundle.observations.iter().enumerate() {
            if o.pose > 0 {
                let d: Vector6<f64> = dp.fixed_rows::<6>(6 * (o.pose - 1)).into_owned();
                rhs[o.point] += reduced.hpx[k].transpose() * d;
            }
        }
        for (i, x) in trial.points.iter_mut().enumerate() {
            *x -= reduced.hxx_inv[i] * rhs[i];
        }
        let new_cost = total_cost(&trial, calib, noise, huber);
        if new_cost.is_finite() && new_cost <= reduced.cost {
            let small = dp.amax() < 1e-7;
            *bundle = trial;
            lambda = (lambda * 0.3).max(1e-7);
            if small {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e4 {
                break;
            }
        }
    }
    // Covariances at the optimum: undamped, inliers at full weight (the Huber weights of
    // outliers would otherwise shrink the information they never gave).
    let reduced = reduce(bundle, calib, noise, huber, 0.0)?;
    let pose_covariance = reduced.s.clone().cholesky()?.inverse();
    let (mut chi2, mut dimensions) = (0.0, 0);
    let mut outliers = Vec::with_capacity(bundle.observations.len());
    for o in &bundle.observations {
        let l = linearize(
            calib,
            noise,
            &bundle.poses[o.pose],
            &bundle.points[o.point],
            o,
        );
        let outlier = l.as_ref().is_none_or(|l| l.chi2 > outlier_chi2);
        if let (false, Some(l)) = (outlier, &l) {
            chi2 += l.chi2;
            dimensions += if o.stereo { 3 } else { 2 };
        }
        outliers.push(outlier);
    }
    Some(Adjusted {
        pose_covariance,
        chi2,
        dimensions,
        outliers,
        point_covariances: reduced.hxx_inv,
    })
}

/// Covariance of the relative pose `Tₐ⁻¹ T_b` (right perturbation) from the poses' joint
/// covariance: `δ = δ_b − Ad(Tₐ⁻¹T_b)⁻¹ δₐ`. `a` and `b` index `bundle.poses`; pose 0 is
/// fixed (no uncertainty).
pub(crate) fn relative_covariance(
    bundle: &Bundle,
    adjusted: &Adjusted,
    a: usize,
    b: usize,
) -> TangentMatrix {
    let rel = bundle.poses[a].inverse() * bundle.poses[b];
    let block = |i: usize, j: usize| -> TangentMatrix {
        adjusted
            .pose_covariance
            .fixed_view::<6, 6>(6 * (i - 1), 6 * (j - 1))
            .into_owned()
    };
    let bb = block(b, b);
    if a == 0 {
        return bb;
    }
    let m = rel.inverse().adjoint();
    let (aa, ab) = (block(a, a), block(a, b));
    // Σ = Σbb − M Σab − Σba Mᵀ + M Σaa Mᵀ
    let c = bb - m * ab - ab.transpose() * m.transpose() + m * aa * m.transpose();
    0.5 * (c + c.transpose())
}
