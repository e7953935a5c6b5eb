//! Rays and the two primitives of the town: the ground plane z = 0 and axis-aligned boxes.
//!
//! World frame: x east, y north, z up (ENU), metres. Buildings stand on the ground.

use nalgebra::{Point3, Vector3};

/// Hits closer than this (metres along a camera ray whose direction has unit z in the
/// camera frame, i.e. camera depth) are ignored: the camera's near plane.
pub const NEAR: f64 = 1e-3;

/// A half-line `origin + t * dir`, t > 0. `dir` need not be unit length; ray parameters
/// are then in units of `|dir|`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: Point3<f64>,
    pub dir: Vector3<f64>,
}

impl Ray {
    pub fn at(&self, t: f64) -> Point3<f64> {
        self.origin + self.dir * t
    }
}

/// A face of an axis-aligned box, named by its outward normal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Face {
    /// Normal −x.
    West,
    /// Normal +x.
    East,
    /// Normal −y.
    South,
    /// Normal +y.
    North,
    /// Normal +z (the roof).
    Top,
    /// Normal −z (on the ground, never visible from above).
    Bottom,
}

impl Face {
    /// The four vertical faces, in the order buildings store their wall textures.
    pub const WALLS: [Face; 4] = [Face::West, Face::East, Face::South, Face::North];

    pub fn normal(self) -> Vector3<f64> {
        match self {
            Face::West => -Vector3::x(),
            Face::East => Vector3::x(),
            Face::South => -Vector3::y(),
            Face::North => Vector3::y(),
            Face::Top => Vector3::z(),
            Face::Bottom => -Vector3::z(),
        }
    }

    /// The face of `axis` (0, 1, 2) on the min side (`max_side == false`) or max side.
    fn of_axis(axis: usize, max_side: bool) -> Face {
        match (axis, max_side) {
            (0, false) => Face::West,
            (0, true) => Face::East,
            (1, false) => Face::South,
            (1, true) => Face::North,
            (_, false) => Face::Bottom,
            (_, true) => Face::Top,
        }
    }
}

/// An axis-aligned box `min ≤ p ≤ max`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Point3<f64>,
    pub max: Point3<f64>,
}

impl Aabb {
    pub fn new(min: Point3<f64>, max: Point3<f64>) -> Self {
        Self { min, max }
    }

    pub fn size(&self) -> Vector3<f64> {
        self.max - self.min
    }

    pub fn corners(&self) -> [Point3<f64>; 8] {
        let (a, b) = (self.min, self.max);
        [
            Point3::new(a.x, a.y, a.z),
            Point3::new(b.x, a.y, a.z),
            Point3::new(a.x, b.y, a.z),
            Point3::new(b.x, b.y, a.z),
            Point3::new(a.x, a.y, b.z),
            Point3::new(b.x, a.y, b.z),
            Point3::new(a.x, b.y, b.z),
            Point3::new(b.x, b.y, b.z),
        ]
    }

    /// Slab test (Kay–Kajiya): the nearest t in (t_min, t_max) where the ray meets the
    /// box surface, and the face it meets. `inv_dir` is the componentwise 1/dir (±inf for
    /// axis-parallel rays, which the min/max below handle). From inside the box the ray
    /// meets the face it leaves through.
    pub fn intersect(
        &self,
        ray: &Ray,
        inv_dir: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> Option<(f64, Face)> {
        let mut t_enter = f64::NEG_INFINITY;
        let mut t_exit = f64::INFINITY;
        let mut enter_axis = 0;
        let mut exit_axis = 0;
        for axis in 0..3 {
            let t0 = (self.min[axis] - ray.origin[axis]) * inv_dir[axis];
            let t1 = (self.max[axis] - ray.origin[axis]) * inv_dir[axis];
            // NaN (0 * inf: origin on a slab plane, ray parallel to it) counts as "inside".
            let (near, far) = if t0 <= t1 { (t0, t1) } else { (t1, t0) };
            if near > t_enter {
                t_enter = near;
                enter_axis = axis;
            }
            if far < t_exit {
                t_exit = far;
                exit_axis = axis;
            }
        }
        if t_enter > t_exit {
            return None;
        }
        if t_enter > t_min && t_enter < t_max {
            let max_side = ray.dir[enter_axis] < 0.0;
            return Some((t_enter, Face::of_axis(enter_axis, max_side)));
        }
        if t_enter <= t_min && t_exit > t_min && t_exit < t_max {
            let max_side = ray.dir[exit_axis] > 0.0;
            return Some((t_exit, Face::of_axis(exit_axis, max_side)));
        }
        None
    }
}

/// Where a ray meets the ground plane z = 0 from above, if within (t_min, t_max).
pub(crate) fn intersect_ground(ray: &Ray, t_min: f64, t_max: f64) -> Option<f64> {
    if ray.origin.z <= 0.0 || ray.dir.z >= 0.0 {
        return None;
    }
    let t = -ray.origin.z / ray.dir.z;
    (t > t_min && t < t_max).then_some(t)
}

/// Componentwise reciprocal of a direction, for the slab test.
pub(crate) fn inverse_dir(dir: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(1.0 / dir.x, 1.0 / dir.y, 1.0 / dir.z)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> Aabb {
        Aabb::new(Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 1.0, 1.0))
    }

    #[test]
    fn slab_hits_the_facing_side() {
        let ray = Ray {
            origin: Point3::new(0.5, -2.0, 0.5),
            dir: Vector3::new(0.0, 1.0, 0.0),
        };
        let hit = unit_box().intersect(&ray, &inverse_dir(&ray.dir), NEAR, f64::INFINITY);
        assert_eq!(hit, Some((2.0, Face::South)));
        let ray = Ray {
            origin: Point3::new(0.5, 0.5, 5.0),
            dir: Vector3::new(0.0, 0.0, -2.0),
        };
        let hit = unit_box().intersect(&ray, &inverse_dir(&ray.dir), NEAR, f64::INFINITY);
        assert_eq!(hit, Some((2.0, Face::Top)));
    }

    #[test]
    fn slab_misses_and_respects_t_max() {
        let ray = Ray {
            origin: Point3::new(2.0, -2.0, 0.5),
            dir: Vector3::new(0.0, 1.0, 0.0),
        };
        assert!(unit_box()
            .intersect(&ray, &inverse_dir(&ray.dir), NEAR, f64::INFINITY)
            .is_none());
        let ray = Ray {
            origin: Point3::new(0.5, -2.0, 0.5),
            dir: Vector3::new(0.0, 1.0, 0.0),
        };
        assert!(unit_box()
            .intersect(&ray, &inverse_dir(&ray.dir), NEAR, 1.5)
            .is_none());
    }

    #[test]
    fn from_inside_the_exit_face_is_hit() {
        let ray = Ray {
            origin: Point3::new(0.5, 0.5, 0.5),
            dir: Vector3::new(-1.0, 0.0, 0.0),
        };
        let hit = unit_box().intersect(&ray, &inverse_dir(&ray.dir), NEAR, f64::INFINITY);
        assert_eq!(hit, Some((0.5, Face::West)));
    }

    #[test]
    fn ground_is_hit_from_above_only() {
        let down = Ray {
            origin: Point3::new(0.0, 0.0, 2.0),
            dir: Vector3::new(1.0, 0.0, -1.0),
        };
        assert_eq!(intersect_ground(&down, NEAR, f64::INFINITY), Some(2.0));
        let up = Ray {
            origin: Point3::new(0.0, 0.0, 2.0),
            dir: Vector3::new(1.0, 0.0, 1.0),
        };
        assert_eq!(intersect_ground(&up, NEAR, f64::INFINITY), None);
    }
}
