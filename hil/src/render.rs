//! Ray casting of a [`World`] into a rectified stereo pair with ground-truth depth.
//!
//! One ray per pixel centre; instead of supersampling, textures are box-filtered over
//! the pixel's footprint on the surface (see [`crate::noise`]), which costs one texture
//! evaluation per pixel and still keeps distant detail from aliasing. Rows are rendered
//! in parallel (rayon); the output does not depend on the thread count.

use nalgebra::{Isometry3, Matrix3, Point3};
use rayon::prelude::*;

use crate::camera::StereoCamera;
use crate::cull::screen_rect;
use crate::geometry::Ray;
use crate::image::{DepthMap, GrayImage};
use crate::noise::Footprint;
use crate::texture::sky_intensity;
use crate::world::{SurfacePoint, World};

/// Floor on the cosine between a pixel's ray and the surface normal when sizing its
/// footprint (see [`Footprint::of_pixel`]).
const MIN_COS: f32 = 0.02;

/// A rendered stereo frame: both images and the left camera's z-depth.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoPair {
    pub left: GrayImage,
    pub right: GrayImage,
    /// Depth along the left camera's z axis; `f32::INFINITY` on sky pixels.
    pub depth: DepthMap,
}

/// Renders the pair whose LEFT camera is at `pose` (camera-to-world).
pub fn render_stereo(world: &World, camera: &StereoCamera, pose: &Isometry3<f64>) -> StereoPair {
    let (left, depth) = render_view(world, camera, pose);
    let (right, _) = render_view(world, camera, &camera.right_pose(pose));
    StereoPair { left, right, depth }
}

/// Renders one camera (the pair's intrinsics) at `pose`: intensity and z-depth.
pub fn render_view(
    world: &World,
    camera: &StereoCamera,
    pose: &Isometry3<f64>,
) -> (GrayImage, DepthMap) {
    let (pixels, depth) = render_rows(world, camera, pose, quantize);
    (
        GrayImage::from_parts_unchecked(camera.width(), camera.height(), pixels),
        depth,
    )
}

/// [`render_view`] before quantization: the scene radiance in intensity units (what an
/// ideal camera exposed for the town reads, 0–255, unclamped and unrounded), row-major.
/// The realistic camera ([`crate::sensor`]) exposes, blurs and digitizes this.
pub fn render_radiance(
    world: &World,
    camera: &StereoCamera,
    pose: &Isometry3<f64>,
) -> (Vec<f32>, DepthMap) {
    render_rows(world, camera, pose, |value| value as f32)
}

/// The ideal camera's 8-bit pixel of an intensity.
fn quantize(value: f64) -> u8 {
    (value.clamp(0.0, 255.0) + 0.5) as u8
}

/// Ray casts every row in parallel; `store` turns a pixel's intensity into the output type.
fn render_rows<T: Copy + Default + Send>(
    world: &World,
    camera: &StereoCamera,
    pose: &Isometry3<f64>,
    store: impl Fn(f64) -> T + Sync,
) -> (Vec<T>, DepthMap) {
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    let view = View::new(world, camera, pose);
    let mut pixels = vec![T::default(); w * h];
    let mut depth = vec![0f32; w * h];
    pixels
        .par_chunks_mut(w)
        .zip(depth.par_chunks_mut(w))
        .enumerate()
        .for_each(|(row, (out, z))| {
            view.render_row(row as u32, out, z, &store);
        });
    (
        pixels,
        DepthMap::from_parts_unchecked(camera.width(), camera.height(), depth),
    )
}

/// Everything per-frame that rows share.
struct View<'a> {
    world: &'a World,
    camera: &'a StereoCamera,
    origin: Point3<f64>,
    rotation: Matrix3<f64>,
    /// Angle subtended by one pixel (radians).
    pixel_angle: f32,
    /// (building index, its screen rectangle), for buildings that can appear.
    rects: Vec<(usize, crate::cull::ScreenRect)>,
}

impl<'a> View<'a> {
    fn new(world: &'a World, camera: &'a StereoCamera, pose: &Isometry3<f64>) -> Self {
        let rects = world
            .buildings()
            .iter()
            .enumerate()
            .filter_map(|(i, b)| screen_rect(camera, pose, b.bounds()).map(|r| (i, r)))
            .collect();
        View {
            world,
            camera,
            origin: Point3::from(pose.translation.vector),
            rotation: pose.rotation.to_rotation_matrix().into_inner(),
            pixel_angle: (1.0 / (camera.fx() * camera.fy()).sqrt()) as f32,
            rects,
        }
    }

    fn render_row<T>(&self, row: u32, out: &mut [T], depth: &mut [f32], store: &impl Fn(f64) -> T) {
        // Buildings whose rectangle spans this row, with their column range.
        let spans: Vec<(usize, u32, u32)> = self
            .rects
            .iter()
            .filter(|(_, r)| r.row0 <= row && row <= r.row1)
            .map(|&(i, r)| (i, r.col0, r.col1))
            .collect();
        // World ray of column c: start + c * step (the camera ray has unit z, so its
        // parameter at a hit is the hit's depth).
        let start = self.rotation * self.camera.ray_camera(0.0, row as f64);
        let step = self.rotation.column(0) / self.camera.fx();
        // Two passes: all of the row's rays first, then all shading. Each pass is a
        // chain of long-latency operations (divisions, square roots) per pixel with no
        // dependency between pixels, which the CPU overlaps far better when the
        // pixels' chains are not interleaved with the other pass.
        let hits: Vec<Option<(SurfacePoint, Footprint)>> = (0..out.len())
            .zip(depth.iter_mut())
            .map(|(col, z)| {
                let dir = start + step * col as f64;
                let col = col as u32;
                let candidates = spans
                    .iter()
                    .filter(|s| s.1 <= col && col <= s.2)
                    .map(|s| s.0);
                let ray = Ray {
                    origin: self.origin,
                    dir,
                };
                match self.world.cast_among(&ray, candidates) {
                    Some(hit) => {
                        *z = hit.t as f32;
                        let normal_dot = hit.surface.normal.dot(&dir) as f32;
                        Some((
                            hit.surface,
                            Footprint::of_pixel(
                                hit.t as f32,
                                self.pixel_angle,
                                normal_dot,
                                MIN_COS,
                            ),
                        ))
                    }
                    None => {
                        *z = f32::INFINITY;
                        None
                    }
                }
            })
            .collect();
        for (col, (pixel, hit)) in out.iter_mut().zip(hits).enumerate() {
            let value = match hit {
                Some((surface, fp)) => self.world.shade_filtered(&surface, fp),
                None => {
                    let dir = start + step * col as f64;
                    sky_intensity(dir.z / dir.norm())
                }
            };
            *pixel = store(value);
        }
    }
}
