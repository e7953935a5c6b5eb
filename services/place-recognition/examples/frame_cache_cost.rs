//! What the place-recognition service pays per camera frame to keep images for its
//! keyframes, against the alternative of downsampling every frame to the model's input on
//! arrival (BENCHMARKS.md):
//!
//!   cargo run --release -p doorslam-place-recognition --example frame_cache_cost
//!
//! - the cache as built: the left image copied into the cache (`PlaceState::on_frame`);
//! - downsampled on arrival: area resampling to NetVLAD's 320 x 208 input
//!   (`image::resize_area`, what preprocessing does once per keyframe instead).

use std::time::Instant;

use doorslam_ipc::FrameHeader;
use doorslam_place_recognition::image::resize_area;
use doorslam_place_recognition::service::{BowFeatures, PlaceState};
use doorslam_place_recognition::{GrayImage, Method};

fn main() {
    let (w, h) = (752usize, 480usize);
    let pixels: Vec<u8> = (0..w * h).map(|i| (i * 31 % 251) as u8).collect();
    let frames = 400u64;
    let mut state = PlaceState::new(0, Method::NetVlad, BowFeatures::Image, 16);
    let start = Instant::now();
    for seq in 0..frames {
        let header = FrameHeader {
            seq,
            width: w as u32,
            height: h as u32,
            ..Default::default()
        };
        state.on_frame(&header, &pixels);
    }
    let copy_us = start.elapsed().as_secs_f64() * 1e6 / frames as f64;
    let img = GrayImage::new(w, h, pixels).unwrap();
    let start = Instant::now();
    let mut sink = 0f32;
    for _ in 0..frames {
        sink += resize_area(&img, 320, 208)[1000];
    }
    let resize_us = start.elapsed().as_secs_f64() * 1e6 / frames as f64;
    println!(
        "{w}x{h} left image per frame: copy into the cache {copy_us:.0} us, \
         area-resample to 320x208 {resize_us:.0} us (cache of 16: {:.1} MB as copies, \
         {:.1} MB as f32 planes) [{sink:.0}]",
        16.0 * (w * h) as f64 / 1e6,
        16.0 * (320 * 208 * 4) as f64 / 1e6
    );
}
