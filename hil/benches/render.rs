//! Renderer throughput: stereo pairs per second at the EuRoC-like (752×480) and KITTI-like
//! (1241×376) presets, over views of streets, facades, roofs and sky.
//!
//! `cargo bench -p doorslam-hil --bench render` (a plain measurement, no harness: the
//! number goes to BENCHMARKS.md, nothing here can fail a build). `--frames N` renders N
//! pairs per preset (default 60).

use std::time::Instant;

use doorslam_hil::{look_at, render_stereo, StereoCamera, World};
use nalgebra::Vector3;

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
    for camera in [StereoCamera::euroc_like(), StereoCamera::kitti_like()] {
        let start = Instant::now();
        let mut checksum = 0u64;
        for k in 0..frames {
            let pair = render_stereo(&world, &camera, &poses[k % poses.len()]);
            checksum += pair.left.pixels()[0] as u64 + pair.right.pixels()[0] as u64;
        }
        let secs = start.elapsed().as_secs_f64();
        println!(
            "{}x{}: {:.1} stereo pairs/s over {frames} pairs on {} threads (checksum {checksum})",
            camera.width(),
            camera.height(),
            frames as f64 / secs,
            rayon::current_num_threads()
        );
    }
}
