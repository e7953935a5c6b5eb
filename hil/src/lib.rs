//! # doorslam-hil
//!
//! Hardware-in-the-loop and simulation. Landed so far: the synthetic stereo world
//! renderer (below, issue "HIL/simulation"), [`posegraph_sim`], the multi-robot
//! pose-graph simulator, and [`experiments`] run on it (the PCM threshold sweep).
//!
//! ## Synthetic stereo world
//!
//! * [`World`]: a town of textured primitives — the ground plane z = 0 (streets, sidewalks,
//!   lawns, plazas) and axis-aligned box buildings whose facades carry window grids
//!   where every window differs (plenty of distinct ORB/GFTT corners). Some designs are
//!   built several times with identical size and textures, so different places look the
//!   same (perceptual aliasing, what place recognition and PCM must survive).
//!   [`World::town`] builds the default 200 m × 200 m scene from a seed, deterministically.
//! * [`StereoCamera`]: rectified pinhole pair, presets [`StereoCamera::euroc_like`] and
//!   [`StereoCamera::kitti_like`]; poses are camera-to-world `Isometry3<f64>` of the
//!   left camera, camera frame x right, y down, z forward; world frame z up.
//! * [`render_stereo`]: ray casting (parallel over rows) into left/right 8-bit images and
//!   the left camera's z-depth (`f32::INFINITY` on sky): the ideal camera.
//! * [`sensor`]: the realistic camera `doorslam sim world` uses by default: a global-shutter
//!   CMOS pair with auto-exposure following changing light (a smooth walk and shade
//!   steps), motion blur during the exposure, vignetting, shot and read noise;
//!   [`flights::TeamCamera`] images a planned team with either camera.
//!
//! A surface point's intensity is a pure function of the point (its face's texture at
//! its (u, v)), so it is the same from every viewpoint: [`World::texture_at`] gives it.
//! Rendering filters texture detail finer than a pixel instead of supersampling.
//!
//! Figures (`hil/docs/stereo_pair.png`, `hil/docs/aliasing.png`) come from
//! `cargo run --release -p doorslam-hil --example render_pair`; the throughput is printed
//! by `cargo bench -p doorslam-hil --bench render`.

mod camera;
mod cull;
pub mod delivery_bench;
pub mod demo;
pub mod dpgo;
mod error;
pub mod experiments;
pub mod flights;
mod geometry;
mod image;
pub mod netns;
mod noise;
pub mod posegraph_sim;
mod render;
mod rng;
pub mod sensor;
pub mod sim_keyframes;
mod texture;
mod town;
mod world;

pub use camera::{look_at, StereoCamera};
pub use error::HilError;
pub use geometry::{Aabb, Face, Ray, NEAR};
pub use image::{DepthMap, GrayImage};
pub use render::{render_radiance, render_stereo, render_view, StereoPair};
pub use texture::{sky_intensity, FacadeStyle, GroundStyle, RoofStyle, Texture, TextureId};
pub use town::{
    BUILDINGS, COPIES_PER_DESIGN, LOTS, REPEATED_DESIGNS, SIDEWALK_WIDTH, STREET_WIDTH, TOWN_SIZE,
};
pub use world::{light, Building, BuildingStyle, Hit, Primitive, SurfacePoint, World};
