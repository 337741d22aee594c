//! Depth <-> pointmap conversions.

use crate::camera::Intrinsics;
use crate::raster::Raster;
use glam::{DMat4, Vec3};

/// True for a usable depth value (finite and > 0).
#[inline]
pub fn depth_valid(d: f32) -> bool {
    d.is_finite() && d > 0.0
}

/// True for a usable point (all coordinates finite and z > 0).
#[inline]
pub fn point_valid(p: Vec3) -> bool {
    p.is_finite() && p.z > 0.0
}

/// Camera-frame pointmap from z-depth; invalid depth gives a NaN point.
pub fn depth_to_pointmap(depth: &Raster<f32>, k: &Intrinsics) -> Raster<Vec3> {
    Raster::from_fn(depth.width(), depth.height(), |x, y| {
        let d = *depth.get(x, y);
        if depth_valid(d) {
            (k.unproject(x as f64, y as f64) * d as f64).as_vec3()
        } else {
            Vec3::NAN
        }
    })
}

/// z-depth of a camera-frame pointmap (invalid points give 0).
pub fn pointmap_to_depth(points: &Raster<Vec3>) -> Raster<f32> {
    points.map(|p| if point_valid(*p) { p.z } else { 0.0 })
}

/// Applies a 4x4 transform (e.g. camera-to-world) to every valid point.
pub fn transform_pointmap(points: &Raster<Vec3>, m: &DMat4) -> Raster<Vec3> {
    points.map(|p| if p.is_finite() { m.transform_point3(p.as_dvec3()).as_vec3() } else { Vec3::NAN })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_round_trip() {
        let k = Intrinsics { fx: 100.0, fy: 110.0, cx: 8.0, cy: 6.0 };
        let depth = Raster::from_fn(16, 12, |x, y| if x == 3 { 0.0 } else { 1.0 + (x + y) as f32 * 0.1 });
        let pts = depth_to_pointmap(&depth, &k);
        assert!(!pts.get(3, 4).is_finite());
        let p = *pts.get(10, 2);
        assert!((p.x - (10.0 - 8.0) / 100.0 * 2.2).abs() < 1e-6);
        assert_eq!(pointmap_to_depth(&pts), depth);
    }
}
