//! Renders the figures in `hil/docs/`: one stereo pair of the default town
//! (`stereo_pair.png`, left | right, half resolution) and the left images of two
//! copies of the same building design standing at different places (`aliasing.png`).
//! Run from the workspace root:
//!
//!     cargo run --release -p doorslam-hil --example render_pair

use std::path::Path;

use doorslam_hil::{
    look_at, render_stereo, Building, Face, GrayImage, HilError, StereoCamera, World,
};
use nalgebra::{Isometry3, Point3, Vector3};

/// A camera across the street from `b`'s south wall, 3 m up, looking slightly up.
fn across_the_street(b: &Building) -> Result<Isometry3<f64>, HilError> {
    let (lo, hi) = (b.bounds().min, b.bounds().max);
    let target = Point3::new(0.5 * (lo.x + hi.x), lo.y, 0.3 * hi.z);
    let eye = Point3::new(target.x, lo.y, 3.0) + Face::South.normal() * 13.0;
    look_at(eye, target, Vector3::z())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs");
    std::fs::create_dir_all(&out)?;
    let world = World::town(7);
    let camera = StereoCamera::euroc_like();

    // A drone 14 m up over a street corner, looking diagonally across the town.
    let eye = Point3::new(-66.7, -66.7, 14.0);
    let pose = look_at(eye, Point3::new(0.0, 0.0, 0.0), Vector3::z())?;
    let pair = render_stereo(&world, &camera, &pose);
    let both = GrayImage::side_by_side(&pair.left, &pair.right, 4)?;
    both.downscale2().write_png(&out.join("stereo_pair.png"))?;

    // Two buildings of one design: same walls, different streets around them.
    let buildings = world.buildings();
    let (a, b) = (0..buildings.len())
        .flat_map(|i| (i + 1..buildings.len()).map(move |j| (i, j)))
        .find(|&(i, j)| buildings[i].style() == buildings[j].style())
        .ok_or("the town has no repeated design")?;
    let view_a = render_stereo(&world, &camera, &across_the_street(&buildings[a])?);
    let view_b = render_stereo(&world, &camera, &across_the_street(&buildings[b])?);
    let alias = GrayImage::side_by_side(&view_a.left, &view_b.left, 4)?;
    alias.downscale2().write_png(&out.join("aliasing.png"))?;
    eprintln!(
        "wrote stereo_pair.png and aliasing.png (buildings {a} and {b}) in {}",
        out.display()
    );
    Ok(())
}
