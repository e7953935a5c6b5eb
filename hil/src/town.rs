//! `World::town(seed)`: a 200 m × 200 m town on a 6 × 6 lattice of lots separated by
//! streets, with 30 buildings of which three designs are built three times each
//! (identical size and textures: places that look alike from the street).

use nalgebra::Point3;

use crate::geometry::Aabb;
use crate::rng::SplitMix64;
use crate::texture::{FacadeStyle, GroundStyle, RoofStyle};
use crate::world::{BuildingStyle, World};

/// Side of the town square (metres), centred on the origin.
pub const TOWN_SIZE: f64 = 200.0;
/// Lots per side.
pub const LOTS: usize = 6;
pub const STREET_WIDTH: f64 = 10.0;
pub const SIDEWALK_WIDTH: f64 = 2.0;
/// Designs that are built more than once, and how many times each.
pub const REPEATED_DESIGNS: usize = 3;
pub const COPIES_PER_DESIGN: usize = 3;
/// Buildings in total; the remaining lots are lawns or plazas.
pub const BUILDINGS: usize = 30;

impl World {
    /// The default scene: deterministic from `seed`, different seeds give different towns.
    pub fn town(seed: u64) -> World {
        let mut rng = SplitMix64::new(seed);
        let pitch = TOWN_SIZE / LOTS as f64;
        let origin = -0.5 * TOWN_SIZE;
        let ground = GroundStyle {
            seed: rng.next_u32(),
            origin,
            pitch,
            street: STREET_WIDTH,
            sidewalk: SIDEWALK_WIDTH,
        };
        let mut world = World::new(seed, ground);

        // Lots in a seeded random order (Fisher–Yates): repeated designs first, then
        // one-off buildings, the rest stay open.
        let mut lots: Vec<(usize, usize)> =
            (0..LOTS * LOTS).map(|k| (k % LOTS, k / LOTS)).collect();
        for i in (1..lots.len()).rev() {
            let j = rng.below(i + 1);
            lots.swap(i, j);
        }
        // Buildable square inside a lot: clear of the street and its sidewalks.
        let setback = 0.5 * STREET_WIDTH + SIDEWALK_WIDTH;
        let buildable = pitch - 2.0 * setback;

        let designs: Vec<(u32, [f64; 3])> = (0..REPEATED_DESIGNS)
            .map(|_| {
                let style = world.add_style(random_style(&mut rng));
                // Wide and tall enough to fill a street-level view from across the street.
                let size = [
                    rng.range(14.0, buildable),
                    rng.range(12.0, buildable),
                    rng.range(14.0, 30.0),
                ];
                (style, size)
            })
            .collect();

        for (k, &(lx, ly)) in lots.iter().take(BUILDINGS).enumerate() {
            let (style, size) = if k < REPEATED_DESIGNS * COPIES_PER_DESIGN {
                designs[k % REPEATED_DESIGNS]
            } else {
                let style = world.add_style(random_style(&mut rng));
                let height = if rng.unit() < 0.2 {
                    rng.range(30.0, 45.0)
                } else {
                    rng.range(6.0, 24.0)
                };
                (
                    style,
                    [rng.range(8.0, buildable), rng.range(8.0, buildable), height],
                )
            };
            let lot_x = origin + pitch * lx as f64 + setback;
            let lot_y = origin + pitch * ly as f64 + setback;
            let x0 = lot_x + rng.range(0.0, buildable - size[0]);
            let y0 = lot_y + rng.range(0.0, buildable - size[1]);
            let bounds = Aabb::new(
                Point3::new(x0, y0, 0.0),
                Point3::new(x0 + size[0], y0 + size[1], size[2]),
            );
            // Cannot fail (the style was registered above, every size is positive);
            // skipping instead of panicking keeps `town` infallible all the same.
            if world.add_building(bounds, style).is_err() {
                continue;
            }
        }
        world
    }
}

fn random_facade(rng: &mut SplitMix64) -> FacadeStyle {
    let floor_height = rng.range(2.9, 3.9);
    let window_pitch = rng.range(2.0, 3.6);
    let window_height = floor_height * rng.range(0.4, 0.62);
    FacadeStyle {
        seed: rng.next_u32(),
        floor_height,
        window_pitch,
        window_width: window_pitch * rng.range(0.4, 0.7),
        window_height,
        sill: rng.range(0.6, floor_height - 0.45 - window_height).max(0.3),
        wall: rng.range(95.0, 200.0),
        glass: rng.range(35.0, 85.0),
    }
}

fn random_style(rng: &mut SplitMix64) -> BuildingStyle {
    // One design shares window layout on all four walls (like real buildings) but each
    // wall gets its own noise seed and shade, so the walls are distinguishable.
    let base = random_facade(rng);
    let walls = [0, 1, 2, 3].map(|_| FacadeStyle {
        seed: rng.next_u32(),
        wall: (base.wall + rng.range(-15.0, 15.0)).clamp(60.0, 220.0),
        ..base.clone()
    });
    let roof = RoofStyle {
        seed: rng.next_u32(),
        sheet: rng.range(2.0, 4.0),
        base: rng.range(90.0, 150.0),
    };
    BuildingStyle { walls, roof }
}
