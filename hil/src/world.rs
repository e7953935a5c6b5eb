//! The scene: a textured ground plane and textured axis-aligned buildings, and the
//! queries the renderer and the tests need (nearest hit, surface lookup, intensity).

use nalgebra::{Point3, Vector3};

use crate::error::HilError;
use crate::geometry::{intersect_ground, inverse_dir, Aabb, Face, Ray, NEAR};
use crate::noise::Footprint;
use crate::texture::{FacadeStyle, GroundStyle, RoofStyle, Texture, TextureId};

/// A box-shaped building. Buildings with the same `style` and size look identical
/// (same textures on the same faces): they are the town's perceptual aliases.
#[derive(Debug, Clone, PartialEq)]
pub struct Building {
    bounds: Aabb,
    style: u32,
    walls: [TextureId; 4],
    roof: TextureId,
}

impl Building {
    pub fn bounds(&self) -> &Aabb {
        &self.bounds
    }

    /// Buildings with equal style (and equal size) are indistinguishable.
    pub fn style(&self) -> u32 {
        self.style
    }

    fn texture_of(&self, face: Face) -> TextureId {
        match face {
            Face::West => self.walls[0],
            Face::East => self.walls[1],
            Face::South => self.walls[2],
            Face::North => self.walls[3],
            Face::Top | Face::Bottom => self.roof,
        }
    }

    /// Texture coordinates (metres) of a point on `face`: u runs left to right as seen
    /// from outside, v upwards (walls) — relative to the box, so copies share them.
    fn uv(&self, face: Face, p: &Point3<f64>) -> (f64, f64) {
        let (a, b) = (self.bounds.min, self.bounds.max);
        match face {
            Face::South => (p.x - a.x, p.z - a.z),
            Face::East => (p.y - a.y, p.z - a.z),
            Face::North => (b.x - p.x, p.z - a.z),
            Face::West => (b.y - p.y, p.z - a.z),
            Face::Top | Face::Bottom => (p.x - a.x, p.y - a.y),
        }
    }
}

/// Which primitive a surface point belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Primitive {
    Ground,
    Building { index: usize, face: Face },
}

/// A point on a primitive with what shading needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    pub primitive: Primitive,
    pub texture: TextureId,
    pub u: f64,
    pub v: f64,
    pub normal: Vector3<f64>,
}

/// The nearest intersection of a ray with the world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter (in units of the ray direction's length).
    pub t: f64,
    pub point: Point3<f64>,
    pub surface: SurfacePoint,
}

/// Brightness factor of a primitive under a fixed sun high in the south-east: roofs and
/// ground brightest, north walls in shade. Without it all faces of a box have the same
/// mean intensity and building edges only show through texture changes. It depends on
/// the face only, never on the viewpoint, so shading stays a function of the point.
pub fn light(primitive: Primitive) -> f64 {
    match primitive {
        Primitive::Ground => 1.0,
        Primitive::Building { face, .. } => match face {
            Face::Top | Face::Bottom => 1.0,
            Face::South => 0.92,
            Face::East => 0.8,
            Face::West => 0.66,
            Face::North => 0.56,
        },
    }
}

/// Ground plus buildings, with their textures. Built deterministically from a seed.
#[derive(Debug, Clone, PartialEq)]
pub struct World {
    seed: u64,
    ground: TextureId,
    buildings: Vec<Building>,
    styles: Vec<StyleTextures>,
    textures: Vec<Texture>,
}

/// The textures of one registered [`BuildingStyle`].
#[derive(Debug, Clone, PartialEq)]
struct StyleTextures {
    walls: [TextureId; 4],
    roof: TextureId,
}

/// The four wall textures and the roof of a building design.
#[derive(Debug, Clone, PartialEq)]
pub struct BuildingStyle {
    pub walls: [FacadeStyle; 4],
    pub roof: RoofStyle,
}

impl World {
    /// A world with only the ground.
    pub fn new(seed: u64, ground: GroundStyle) -> Self {
        Self {
            seed,
            ground: TextureId(0),
            buildings: Vec::new(),
            styles: Vec::new(),
            textures: vec![Texture::Ground(ground)],
        }
    }

    /// Registers a building design; returns its style id (0, 1, 2, … in registration
    /// order) for [`World::add_building`].
    pub fn add_style(&mut self, style: BuildingStyle) -> u32 {
        let first = self.textures.len() as u32;
        self.textures
            .extend(style.walls.into_iter().map(Texture::Facade));
        self.textures.push(Texture::Roof(style.roof));
        self.styles.push(StyleTextures {
            walls: [0, 1, 2, 3].map(|k| TextureId(first + k)),
            roof: TextureId(first + 4),
        });
        (self.styles.len() - 1) as u32
    }

    /// Places a building of a registered style; returns its index in
    /// [`World::buildings`]. The box must be finite with `min < max` on every axis.
    pub fn add_building(&mut self, bounds: Aabb, style: u32) -> Result<usize, HilError> {
        let Some(textures) = self.styles.get(style as usize).cloned() else {
            return Err(HilError::UnknownStyle(style));
        };
        let proper = (0..3).all(|k| {
            bounds.min[k].is_finite() && bounds.max[k].is_finite() && bounds.min[k] < bounds.max[k]
        });
        if !proper {
            return Err(HilError::InvalidBounds {
                min: bounds.min.into(),
                max: bounds.max.into(),
            });
        }
        self.buildings.push(Building {
            bounds,
            style,
            walls: textures.walls,
            roof: textures.roof,
        });
        Ok(self.buildings.len() - 1)
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    pub fn buildings(&self) -> &[Building] {
        &self.buildings
    }

    pub fn texture(&self, id: TextureId) -> Option<&Texture> {
        self.textures.get(id.0 as usize)
    }

    /// Nearest hit of `ray` with anything (t > [`NEAR`]), testing every building.
    pub fn cast(&self, ray: &Ray) -> Option<Hit> {
        self.cast_among(ray, 0..self.buildings.len())
    }

    /// Nearest hit among the ground and the given buildings (the renderer passes only
    /// the buildings whose screen bounds contain the pixel).
    pub(crate) fn cast_among(
        &self,
        ray: &Ray,
        candidates: impl IntoIterator<Item = usize>,
    ) -> Option<Hit> {
        let mut best_t = intersect_ground(ray, NEAR, f64::INFINITY).unwrap_or(f64::INFINITY);
        let mut best: Option<Primitive> = best_t.is_finite().then_some(Primitive::Ground);
        // The reciprocal direction costs three divisions: only for rays that meet a box's
        // screen rectangle.
        let mut inv = None;
        for index in candidates {
            let Some(building) = self.buildings.get(index) else {
                continue;
            };
            let inv = inv.get_or_insert_with(|| inverse_dir(&ray.dir));
            if let Some((t, face)) = building.bounds.intersect(ray, inv, NEAR, best_t) {
                best_t = t;
                best = Some(Primitive::Building { index, face });
            }
        }
        let primitive = best?;
        let point = ray.at(best_t);
        Some(Hit {
            t: best_t,
            point,
            surface: self.surface(primitive, &point)?,
        })
    }

    fn surface(&self, primitive: Primitive, p: &Point3<f64>) -> Option<SurfacePoint> {
        match primitive {
            Primitive::Ground => Some(SurfacePoint {
                primitive,
                texture: self.ground,
                u: p.x,
                v: p.y,
                normal: Vector3::z(),
            }),
            Primitive::Building { index, face } => {
                let b = self.buildings.get(index)?;
                let (u, v) = b.uv(face, p);
                Some(SurfacePoint {
                    primitive,
                    texture: b.texture_of(face),
                    u,
                    v,
                    normal: face.normal(),
                })
            }
        }
    }

    /// The surface a world point lies on (within `tol` metres), if any: the ground, or
    /// the building face nearest to the point. Used to check depth maps.
    pub fn surface_at(&self, p: &Point3<f64>, tol: f64) -> Option<SurfacePoint> {
        let mut best: Option<(f64, Primitive)> =
            (p.z.abs() <= tol).then_some((p.z.abs(), Primitive::Ground));
        for (index, b) in self.buildings.iter().enumerate() {
            let (lo, hi) = (b.bounds.min, b.bounds.max);
            let inside = (0..3).all(|k| p[k] >= lo[k] - tol && p[k] <= hi[k] + tol);
            if !inside {
                continue;
            }
            let distances = [
                (Face::West, (p.x - lo.x).abs()),
                (Face::East, (p.x - hi.x).abs()),
                (Face::South, (p.y - lo.y).abs()),
                (Face::North, (p.y - hi.y).abs()),
                (Face::Top, (p.z - hi.z).abs()),
            ];
            for (face, d) in distances {
                if d <= tol && best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, Primitive::Building { index, face }));
                }
            }
        }
        let (_, primitive) = best?;
        self.surface(primitive, p)
    }

    /// Intensity of a surface point, box-filtered over `footprint` metres.
    /// Includes fixed sunlight (see [`light`]): still a function of the point only.
    pub fn shade(&self, surface: &SurfacePoint, footprint: f64) -> f64 {
        self.shade_filtered(surface, Footprint::new(footprint))
    }

    pub(crate) fn shade_filtered(&self, surface: &SurfacePoint, fp: Footprint) -> f64 {
        let albedo = self
            .texture(surface.texture)
            .map_or(0.0, |t| t.filtered(surface.u, surface.v, fp));
        albedo * light(surface.primitive)
    }

    /// Unfiltered intensity of the world point `p` if it lies on a surface (within 1 mm):
    /// what a camera sees there when close enough to resolve all detail.
    pub fn texture_at(&self, p: &Point3<f64>) -> Option<f64> {
        let s = self.surface_at(p, 1e-3)?;
        Some(self.shade(&s, 0.0))
    }
}
