//! Renderer throughput: stereo pairs per second at the EuRoC-like (752×480) and KITTI-like
//! (1241×376) presets, over views of streets, facades, roofs and sky, through the ideal
//! camera and through the realistic one (`doorslam_hil::sensor`: blur, exposure, noise),
//! with the realistic camera's extra stages timed on their own.
//!
//! `cargo bench -p doorslam-hil --bench render` (a plain measurement, no harness: the
//! number goes to BENCHMARKS.md, nothing here can fail a build). `--frames N` renders N
//! pairs per preset and camera (default 60).

use std::time::Instant;

use doorslam_hil::sensor::{
    digitize, motion_blur, render_realistic, ExposureMotion, FrameExposure, SensorModel,
};
use doorslam_hil::{look_at, render_radiance, render_stereo, StereoCamera, World};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn main() {
    let frames = std::env::args()
        .skip_while(|a| a != "--frames")
        .nth(1)
        .and_then(|n| n.parse::<usize>().ok())
        .unwrap_or(60)
        .max(1);
    let world = World::town(7);
    // High over a street corner; low down a street; steeply down over the centre.
    let poses: Vec<_> = [
        ([-66.7, -66.7, 14.0], [0.0, 0.0, 0.0]),
        ([-33.3, -95.0, 3.0], [-33.3, 0.0, 4.0]),
        ([5.0, -25.0, 45.0], [0.0, 5.0, 0.0]),
    ]
    .iter()
    .filter_map(|(eye, target)| look_at((*eye).into(), (*target).into(), Vector3::z()).ok())
    .collect();
    let model = SensorModel::default();
    // Two cases: the default flight in a corner (3.5 m/s, 0.44 rad/s on the 8 m arc,
    // 5 ms at unity gain), and a fast flight turning in shade (7 m/s, 0.9 rad/s, 12 ms at
    // 2× gain), where the smears are ~5 px and the blur costs the most.
    let motion = |speed: f64, yaw_rate: f64, exposure_s: f64| {
        let at = |t: f64| {
            Isometry3::from_parts(
                Translation3::new(0.0, 0.0, speed * t),
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, yaw_rate * t, 0.0)),
            )
        };
        ExposureMotion {
            start: at(-0.5 * exposure_s),
            end: at(0.5 * exposure_s),
        }
    };
    let cases = [
        (
            "default flight",
            FrameExposure {
                exposure_s: 0.005,
                gain: 1.0,
                light: 1.0,
                brightness: 1.0,
                shade: false,
            },
            motion(3.5, 0.44, 0.005),
        ),
        (
            "fast, in shade",
            FrameExposure {
                exposure_s: 0.012,
                gain: 2.0,
                light: 0.4,
                brightness: 1.0,
                shade: true,
            },
            motion(7.0, 0.9, 0.012),
        ),
    ];
    let threads = rayon::current_num_threads();
    for camera in [StereoCamera::euroc_like(), StereoCamera::kitti_like()] {
        let size = format!("{}x{}", camera.width(), camera.height());
        let start = Instant::now();
        let mut checksum = 0u64;
        for k in 0..frames {
            let pair = render_stereo(&world, &camera, &poses[k % poses.len()]);
            checksum += pair.left.pixels()[0] as u64 + pair.right.pixels()[0] as u64;
        }
        let ideal = start.elapsed().as_secs_f64();
        println!(
            "{size} ideal:     {:.1} stereo pairs/s, {:.1} ms/pair over {frames} pairs on {threads} threads (checksum {checksum})",
            frames as f64 / ideal,
            1e3 * ideal / frames as f64
        );

        for (case, exposure, motion) in &cases {
            let start = Instant::now();
            for k in 0..frames {
                let pair = render_realistic(
                    &world,
                    &camera,
                    &model,
                    &poses[k % poses.len()],
                    exposure,
                    motion,
                    k as u64,
                )
                .expect("buffers have the camera's size");
                checksum += pair.left.pixels()[0] as u64 + pair.right.pixels()[0] as u64;
            }
            let realistic = start.elapsed().as_secs_f64();
            // The realistic camera's own stages on one view, per stereo pair (× 2 views).
            let (radiance, depth) = render_radiance(&world, &camera, &poses[0]);
            let start = Instant::now();
            for _ in 0..frames {
                let blurred = motion_blur(&radiance, depth.values(), &camera, motion)
                    .expect("buffers have the camera's size");
                checksum += blurred[0] as u64;
            }
            let blur = 2.0 * start.elapsed().as_secs_f64() / frames as f64;
            let start = Instant::now();
            for k in 0..frames {
                let image = digitize(&radiance, &camera, &model, exposure, k as u64)
                    .expect("buffers have the camera's size");
                checksum += image.pixels()[0] as u64;
            }
            let noise = 2.0 * start.elapsed().as_secs_f64() / frames as f64;
            println!(
                "{size} realistic, {case}: {:.1} stereo pairs/s, {:.1} ms/pair (+{:.0} %): motion blur {:.1} ms, exposure + vignetting + noise + 8 bits {:.1} ms per pair (checksum {checksum})",
                frames as f64 / realistic,
                1e3 * realistic / frames as f64,
                100.0 * (realistic / ideal - 1.0),
                1e3 * blur,
                1e3 * noise
            );
        }
    }
}
