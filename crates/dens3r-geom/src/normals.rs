//! Surface normals from a camera-frame pointmap.
//!
//! Invalid normals are the zero vector (the spec's `||n||_1 > 0` validity rule).

use crate::pointmap::point_valid;
use crate::raster::Raster;
use glam::Vec3;
use rayon::prelude::*;

/// The Dens3R `pcd2normal` rule (spec section 5, `ABSNormalFromDepthLoss`), bit-for-bit in
/// structure: on interior pixels `a = P[i, j+1] - P[i, j-1]`, `b = P[i-1, j] - P[i+1, j]`,
/// `n = a x b`, negate `n_y`, divide by `max(|n|, 1e-12)`; a one-pixel zero border.
/// The result is in the **Dens3R raw** convention (`(x, -y, z)` of OpenCV). Non-finite
/// neighbours propagate NaN, as in the reference.
pub fn normals_dens3r(points: &Raster<Vec3>) -> Raster<Vec3> {
    let (w, h) = (points.width(), points.height());
    Raster::from_fn(w, h, |x, y| {
        if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
            return Vec3::ZERO;
        }
        let a = *points.get(x + 1, y) - *points.get(x - 1, y);
        let b = *points.get(x, y - 1) - *points.get(x, y + 1);
        let n = a.cross(b);
        let n = Vec3::new(n.x, -n.y, n.z);
        n / n.length().max(1e-12)
    })
}

/// Normals by central differences (the Dens3R rule without its y flip), in the OpenCV
/// convention and oriented toward the camera. Pixels whose four neighbours are not all valid,
/// and the border, get the zero vector.
pub fn normals_from_pointmap(points: &Raster<Vec3>) -> Raster<Vec3> {
    let (w, h) = (points.width(), points.height());
    par_map_pixels(w, h, |x, y| {
        if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
            return Vec3::ZERO;
        }
        let (l, r) = (*points.get(x - 1, y), *points.get(x + 1, y));
        let (t, b) = (*points.get(x, y - 1), *points.get(x, y + 1));
        if ![l, r, t, b].iter().all(|p| point_valid(*p)) || !point_valid(*points.get(x, y)) {
            return Vec3::ZERO;
        }
        orient_to_camera((r - l).cross(t - b), *points.get(x, y))
    })
}

/// Normals that ignore depth discontinuities: along each image axis the one-sided difference
/// with the smaller depth jump is used, and a pixel whose smaller jump still exceeds
/// `max_rel_jump * z` (a silhouette or occlusion edge) gets the zero vector. OpenCV
/// convention, facing the camera, defined on the border too. `0.05` suits most renders.
pub fn normals_from_pointmap_robust(points: &Raster<Vec3>, max_rel_jump: f32) -> Raster<Vec3> {
    let (w, h) = (points.width(), points.height());
    let at = |x: isize, y: isize| -> Option<Vec3> {
        if x < 0 || y < 0 || x as usize >= w || y as usize >= h {
            return None;
        }
        let p = *points.get(x as usize, y as usize);
        point_valid(p).then_some(p)
    };
    par_map_pixels(w, h, |x, y| {
        let (xi, yi) = (x as isize, y as isize);
        let Some(c) = at(xi, yi) else { return Vec3::ZERO };
        let limit = max_rel_jump * c.z;
        // Best one-sided difference along an axis, oriented toward increasing index.
        let best = |prev: Option<Vec3>, next: Option<Vec3>| -> Option<Vec3> {
            let fwd = next.map(|n| n - c).filter(|d| d.z.abs() <= limit);
            let bwd = prev.map(|p| c - p).filter(|d| d.z.abs() <= limit);
            match (fwd, bwd) {
                (Some(f), Some(b)) => Some(if f.z.abs() <= b.z.abs() { f } else { b }),
                (f, b) => f.or(b),
            }
        };
        let (Some(dx), Some(dy)) = (best(at(xi - 1, yi), at(xi + 1, yi)), best(at(xi, yi - 1), at(xi, yi + 1))) else {
            return Vec3::ZERO;
        };
        // dy points down the image; the Dens3R rule uses top - bottom, i.e. -dy.
        orient_to_camera(dx.cross(-dy), c)
    })
}

/// Normalises `n` and flips it to face a camera at the origin looking at `p`; zero when
/// degenerate.
#[inline]
pub fn orient_to_camera(n: Vec3, p: Vec3) -> Vec3 {
    let n = n.normalize_or_zero();
    if n.dot(p) > 0.0 {
        -n
    } else {
        n
    }
}

fn par_map_pixels(w: usize, h: usize, f: impl Fn(usize, usize) -> Vec3 + Sync) -> Raster<Vec3> {
    let data: Vec<Vec3> = (0..w * h).into_par_iter().map(|i| f(i % w, i / w)).collect();
    Raster::from_vec(w, h, data).expect("length is w * h")
}
