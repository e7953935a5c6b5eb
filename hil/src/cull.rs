//! Screen-space culling: the pixel rectangle a box can cover in one view.
//!
//! Testing all ~30 buildings for each of the 360k rays of a frame is the renderer's main
//! cost; a building that projects outside a pixel's row or column cannot be hit by that
//! pixel's ray, so each ray only tests the few boxes whose rectangle contains it.

use nalgebra::{Isometry3, Point3};

use crate::camera::StereoCamera;
use crate::geometry::{Aabb, NEAR};

/// Inclusive pixel rectangle (columns `col0..=col1`, rows `row0..=row1`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ScreenRect {
    pub col0: u32,
    pub col1: u32,
    pub row0: u32,
    pub row1: u32,
}

/// The 12 edges of a box, as index pairs into [`Aabb::corners`] (bit k of an index
/// selects max on axis k, so an edge joins indices differing in one bit).
const EDGES: [(usize, usize); 12] = [
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

/// Bounding pixel rectangle of the part of `aabb` in front of the near plane, seen by
/// the camera at `pose` (camera-to-world); `None` when it cannot appear in the image.
///
/// The visible part of a box is the convex polytope box ∩ {z ≥ NEAR}; its vertices are
/// the box corners in front of the plane and the edge crossings of the plane, and the
/// projection of a convex polytope is the hull of its projected vertices.
pub(crate) fn screen_rect(
    camera: &StereoCamera,
    pose: &Isometry3<f64>,
    aabb: &Aabb,
) -> Option<ScreenRect> {
    let corners = aabb.corners().map(|p| pose.inverse_transform_point(&p));
    let mut lo = (f64::INFINITY, f64::INFINITY);
    let mut hi = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    let mut extend = |p: &Point3<f64>| {
        if let Some((u, v)) = camera.project_camera(p) {
            lo = (lo.0.min(u), lo.1.min(v));
            hi = (hi.0.max(u), hi.1.max(v));
        }
    };
    for c in corners.iter().filter(|c| c.z >= NEAR) {
        extend(c);
    }
    for (a, b) in EDGES {
        let (pa, pb) = (corners[a], corners[b]);
        if (pa.z - NEAR) * (pb.z - NEAR) < 0.0 {
            let s = (NEAR - pa.z) / (pb.z - pa.z);
            extend(&(pa + (pb - pa) * s));
        }
    }
    // One pixel of margin absorbs rounding at the rectangle's edges.
    let (w, h) = (camera.width() as f64 - 1.0, camera.height() as f64 - 1.0);
    let (u0, u1) = ((lo.0 - 1.0).floor(), (hi.0 + 1.0).ceil());
    let (v0, v1) = ((lo.1 - 1.0).floor(), (hi.1 + 1.0).ceil());
    if !(u0 <= w && u1 >= 0.0 && v0 <= h && v1 >= 0.0) {
        return None; // also catches "no vertex in front" (infinite bounds compare false)
    }
    Some(ScreenRect {
        col0: u0.max(0.0) as u32,
        col1: u1.min(w) as u32,
        row0: v0.max(0.0) as u32,
        row1: v1.min(h) as u32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;
    use nalgebra::Vector3;

    #[test]
    fn box_ahead_is_inside_box_behind_is_culled() {
        let cam = StereoCamera::euroc_like();
        let pose = look_at(
            Point3::new(0.0, 0.0, 5.0),
            Point3::new(0.0, 10.0, 5.0),
            Vector3::z(),
        )
        .unwrap();
        let ahead = Aabb::new(Point3::new(-1.0, 9.0, 4.0), Point3::new(1.0, 11.0, 6.0));
        let r = screen_rect(&cam, &pose, &ahead).unwrap();
        assert!(r.col0 < 367 && r.col1 > 367 && r.row0 < 248 && r.row1 > 248);
        let behind = Aabb::new(Point3::new(-1.0, -11.0, 4.0), Point3::new(1.0, -9.0, 6.0));
        assert!(screen_rect(&cam, &pose, &behind).is_none());
    }

    #[test]
    fn box_around_the_camera_covers_the_image() {
        let cam = StereoCamera::euroc_like();
        let pose = look_at(
            Point3::new(0.0, 0.0, 5.0),
            Point3::new(0.0, 10.0, 5.0),
            Vector3::z(),
        )
        .unwrap();
        let around = Aabb::new(Point3::new(-3.0, -3.0, 0.0), Point3::new(3.0, 3.0, 10.0));
        let r = screen_rect(&cam, &pose, &around).unwrap();
        assert_eq!((r.col0, r.col1, r.row0, r.row1), (0, 751, 0, 479));
    }
}
