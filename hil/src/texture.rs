//! Procedural textures of the synthetic town: ground, facades, roofs and sky.
//!
//! A texture maps a surface coordinate (u, v) in metres on its face to an intensity in
//! [0, 255]. It depends on nothing else — not the viewpoint, not the time — so a 3D
//! point has one intensity from every camera (the geometric tests rely on it). The
//! `footprint` argument (metres per pixel on the surface) only removes detail that one
//! pixel cannot resolve; with footprint 0 the texture is the unfiltered ground truth.
//!
//! Detail is chosen for feature detectors: window grids and paving give corners, and a
//! per-cell random value (window blinds, slab shades) makes every corner different, so
//! the only repetitions are the ones the world builds on purpose (identical facades).

use crate::noise::{fbm2, hash_unit, mix, noise1, Footprint, Lattice};

/// Index of a texture in its [`World`](crate::World).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct TextureId(pub u32);

/// The streets-and-lots ground of a town: a square lattice of lots of side `pitch`,
/// separated by streets of width `street` (centred on the lot boundaries) lined with
/// sidewalks of width `sidewalk`.
#[derive(Debug, Clone, PartialEq)]
pub struct GroundStyle {
    pub seed: u32,
    /// World x = y of a lot corner.
    pub origin: f64,
    pub pitch: f64,
    pub street: f64,
    pub sidewalk: f64,
}

/// A wall with a grid of windows, one window per column per floor.
#[derive(Debug, Clone, PartialEq)]
pub struct FacadeStyle {
    pub seed: u32,
    pub floor_height: f64,
    pub window_pitch: f64,
    pub window_width: f64,
    pub window_height: f64,
    /// Height of the window's lower edge above its floor.
    pub sill: f64,
    pub wall: f64,
    pub glass: f64,
}

/// A flat roof of membrane sheets with seams.
#[derive(Debug, Clone, PartialEq)]
pub struct RoofStyle {
    pub seed: u32,
    pub sheet: f64,
    pub base: f64,
}

/// One of the town's surface materials.
#[derive(Debug, Clone, PartialEq)]
pub enum Texture {
    Ground(GroundStyle),
    Facade(FacadeStyle),
    Roof(RoofStyle),
}

impl Texture {
    /// Intensity in [0, 255] at surface coordinate (u, v), box-filtered over `footprint`
    /// (metres per pixel on the surface; 0 = unfiltered).
    pub fn intensity(&self, u: f64, v: f64, footprint: f64) -> f64 {
        self.filtered(u, v, Footprint::new(footprint))
    }

    pub(crate) fn filtered(&self, u: f64, v: f64, fp: Footprint) -> f64 {
        let value = match self {
            Texture::Ground(g) => g.intensity(u, v, fp),
            Texture::Facade(f) => f.intensity(u, v, fp),
            Texture::Roof(r) => r.intensity(u, v, fp),
        };
        value.clamp(0.0, 255.0)
    }
}

/// Sky brightness for a unit viewing direction with world z up: bright haze at the
/// horizon, darker towards the zenith. A function of direction only (points at infinity).
pub fn sky_intensity(dir_z: f64) -> f64 {
    let up = dir_z.clamp(0.0, 1.0);
    215.0 - 75.0 * up.sqrt()
}

/// Length of a centre-line dash and of the gap after it (metres).
const DASH: f64 = 3.0;
/// Half the width of a painted line (metres).
const LINE_HALF_WIDTH: f64 = 0.075;

impl GroundStyle {
    fn intensity(&self, x: f64, y: f64, fp: Footprint) -> f64 {
        let lots = Lattice::new(self.pitch, fp);
        let (lx, ox) = lots.split(x - self.origin);
        let (ly, oy) = lots.split(y - self.origin);
        // Folded distances to the nearest street centre line: zones are intervals
        // symmetric about 0 in them.
        let (dx, dy) = (ox.min(self.pitch - ox), oy.min(self.pitch - oy));
        let half = 0.5 * self.street;
        let curb = half + self.sidewalk;
        // Coverage of each zone, box-filtered across its boundary.
        let street_x = lots.interval(dx, -half, half, fp);
        let street_y = lots.interval(dy, -half, half, fp);
        let street = 1.0 - (1.0 - street_x) * (1.0 - street_y);
        let paved_x = lots.interval(dx, -curb, curb, fp);
        let paved_y = lots.interval(dy, -curb, curb, fp);
        let paved = 1.0 - (1.0 - paved_x) * (1.0 - paved_y);
        let sidewalk = (paved - street).max(0.0);
        let lot = 1.0 - paved;

        let mut value = 0.0;
        if street > 0.0 {
            let dashes = Lattice::new(2.0 * DASH, fp);
            let along_x =
                dashes.interval(dashes.split(x - self.origin).1, 0.5 * DASH, 1.5 * DASH, fp);
            let along_y =
                dashes.interval(dashes.split(y - self.origin).1, 0.5 * DASH, 1.5 * DASH, fp);
            let line_x = lots.interval(dy, -LINE_HALF_WIDTH, LINE_HALF_WIDTH, fp) * along_x;
            let line_y = lots.interval(dx, -LINE_HALF_WIDTH, LINE_HALF_WIDTH, fp) * along_y;
            let patches = noise1(x, y, self.seed, 0.4, fp);
            let grain = fbm2(x, y, self.seed ^ 0xA5, 5.0, fp);
            let asphalt = 72.0 + 24.0 * patches + 14.0 * grain;
            value += street * mix(asphalt, 225.0, (line_x + line_y).min(1.0));
        }
        if sidewalk > 0.0 {
            let paving = Paving {
                size: 1.0,
                joint: 0.04,
                mean: 135.0,
                spread: 30.0,
                seed: self.seed ^ 0x51DE,
            };
            value += sidewalk * paving.intensity(x, y, fp);
        }
        if lot > 0.0 {
            // Each lot is either lawn (soft noise) or a plaza of large random-shade tiles.
            let open = if hash_unit(lx, ly, self.seed ^ 0x1A77) < 0.5 {
                let tufts = noise1(x, y, self.seed ^ 0x6A55, 0.25, fp);
                let blades = fbm2(x, y, self.seed ^ 0x6A56, 4.0, fp);
                100.0 + 45.0 * tufts + 25.0 * blades
            } else {
                let plaza = Paving {
                    size: 2.0,
                    joint: 0.06,
                    mean: 150.0,
                    spread: 60.0,
                    seed: self.seed ^ 0x91A2,
                };
                plaza.intensity(x, y, fp)
            };
            value += lot * open;
        }
        value
    }
}

/// Square paving of side `size` with dark joints of width `joint`; each slab has its own
/// shade (mean `mean`, spread `spread`) and a little grain.
struct Paving {
    size: f64,
    joint: f64,
    mean: f64,
    spread: f64,
    seed: u32,
}

impl Paving {
    fn intensity(&self, x: f64, y: f64, fp: Footprint) -> f64 {
        let cells = Lattice::new(self.size, fp);
        let (ix, fx) = cells.split(x);
        let (iy, fy) = cells.split(y);
        let shade = hash_unit(ix, iy, self.seed) - 0.5;
        let grain = fbm2(x, y, self.seed ^ 0x7777, 3.0, fp);
        let slab = self.mean + self.spread * cells.detail() * shade + 12.0 * grain;
        // Joints sit at the cell borders; the slab interior is the middle of the period,
        // so the box filter never has to wrap around.
        let (a, b) = (0.5 * self.joint, self.size - 0.5 * self.joint);
        let inside = cells.interval(fx, a, b, fp) * cells.interval(fy, a, b, fp);
        mix(0.55 * self.mean, slab, inside)
    }
}

impl FacadeStyle {
    fn intensity(&self, u: f64, v: f64, fp: Footprint) -> f64 {
        // Large stains plus a fine plaster grain (a few cm): texture for features and
        // stereo matching on the blank wall between windows.
        let stain = noise1(u, v, self.seed, 0.4, fp);
        let grain = fbm2(u, v, self.seed ^ 0x9A17, 4.0, fp);
        let mut wall = self.wall + 30.0 * stain + 14.0 * grain;
        let floors = Lattice::new(self.floor_height, fp);
        let columns = Lattice::new(self.window_pitch, fp);
        let (storey, vf) = floors.split(v);
        let (column, uf) = columns.split(u);
        // A darker floor slab band near the top of every storey.
        let fh = self.floor_height;
        wall = mix(
            wall,
            0.7 * wall,
            floors.interval(vf, fh - 0.35, fh - 0.1, fp),
        );

        let left = 0.5 * (self.window_pitch - self.window_width);
        let right = left + self.window_width;
        let top = self.sill + self.window_height;
        let mask = columns.interval(uf, left, right, fp) * floors.interval(vf, self.sill, top, fp);
        if mask <= 0.0 {
            return wall;
        }
        // Every window is different: glass shade, how far its blind is lowered.
        let detail = columns.detail();
        let r_glass = hash_unit(column, storey, self.seed ^ 0xC1A5) - 0.5;
        let r_blind = hash_unit(column, storey, self.seed ^ 0xB11D);
        let glass = self.glass + 70.0 * detail * r_glass;
        let blind_top = top - self.window_height * 0.9 * r_blind;
        let blind_cover = floors.interval(vf, blind_top, top, fp) * detail;
        let blind_shade = 175.0 + 50.0 * (hash_unit(column, storey, self.seed ^ 0x5EED) - 0.5);
        let pane = mix(glass, blind_shade, blind_cover);
        // A mullion splits each window into two panes.
        let centre = 0.5 * self.window_pitch;
        let mullion = columns.interval(uf, centre - 0.05, centre + 0.05, fp);
        let window = mix(pane, 0.45 * self.wall, mullion);
        mix(wall, window, mask)
    }
}

impl RoofStyle {
    fn intensity(&self, u: f64, v: f64, fp: Footprint) -> f64 {
        let gravel = noise1(u, v, self.seed, 0.7, fp);
        let sheets = Paving {
            size: self.sheet,
            joint: 0.08,
            mean: self.base,
            spread: 50.0,
            seed: self.seed ^ 0x2F,
        }
        .intensity(u, v, fp);
        sheets + 20.0 * gravel
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn facade() -> Texture {
        Texture::Facade(FacadeStyle {
            seed: 3,
            floor_height: 3.2,
            window_pitch: 2.8,
            window_width: 1.5,
            window_height: 1.6,
            sill: 0.9,
            wall: 150.0,
            glass: 60.0,
        })
    }

    #[test]
    fn intensity_is_in_range_and_varies() {
        let t = facade();
        let mut lo: f64 = 255.0;
        let mut hi: f64 = 0.0;
        for i in 0..2000 {
            let x = i as f64 * 0.0137;
            let y = i as f64 * 0.0071;
            let value = t.intensity(x, y, 0.0);
            assert!((0.0..=255.0).contains(&value));
            lo = lo.min(value);
            hi = hi.max(value);
        }
        assert!(hi - lo > 80.0, "contrast {lo}..{hi}");
    }

    #[test]
    fn huge_footprint_gives_a_flat_average() {
        let t = facade();
        let a = t.intensity(1.0, 1.0, 1e4);
        let b = t.intensity(50.0, 20.0, 1e4);
        assert!((a - b).abs() < 1e-9);
    }
}
