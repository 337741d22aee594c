//! Reference predictions that use no image content, fitted to the ground truth itself: what a
//! depth or normal predictor must beat to show it sees anything.
//!
//! - **constant**: every pixel at the ground truth's median depth, every normal facing the
//!   camera (0, 0, -1) in the OpenCV frame;
//! - **plane**: the best-fit 3-D plane of the ground truth, its depth and its normal.
//!
//! A plane `n . X = d` seen through intrinsics `K` has inverse depth affine in the pixel,
//! `1/z = a x + b y + c`, so the plane is fitted as least squares on inverse depth over the
//! valid pixels (of `mask`), and its normal is `n ~ K^T (a, b, c)` (the camera-facing sign).

use crate::camera::Intrinsics;
use crate::pointmap::depth_valid;
use crate::raster::Raster;
use glam::{DMat3, DVec3, Vec3};

/// A baseline's depth and normals (OpenCV frame, facing the camera).
pub struct Baseline {
    /// z-depth per pixel (0 where undefined).
    pub depth: Raster<f32>,
    /// Unit normals per pixel.
    pub normals: Raster<Vec3>,
}

fn valid_pixels<'a>(
    gt: &'a Raster<f32>,
    mask: Option<&'a Raster<bool>>,
) -> impl Iterator<Item = (usize, usize, f64)> + 'a {
    let w = gt.width();
    gt.data().iter().enumerate().filter_map(move |(i, &d)| {
        (depth_valid(d) && mask.is_none_or(|m| m.data()[i])).then_some((i % w, i / w, d as f64))
    })
}

/// The median ground-truth depth everywhere, normals (0, 0, -1). `None` without a valid pixel.
pub fn constant_baseline(gt: &Raster<f32>, mask: Option<&Raster<bool>>) -> Option<Baseline> {
    let mut d: Vec<f64> = valid_pixels(gt, mask).map(|p| p.2).collect();
    let median = crate::focal::median(&mut d)? as f32;
    Some(Baseline {
        depth: Raster::filled(gt.width(), gt.height(), median),
        normals: Raster::filled(gt.width(), gt.height(), Vec3::new(0.0, 0.0, -1.0)),
    })
}

/// Least-squares `v ~ a x + b y + c` over pixels `(x, y, v)` of a `w x h` grid, as `(a, b, c)`
/// (solved on coordinates centred and scaled for conditioning); `None` with fewer than 3
/// pixels or a degenerate fit (all on one line).
pub(crate) fn fit_affine(
    (w, h): (usize, usize),
    pixels: impl Iterator<Item = (usize, usize, f64)>,
) -> Option<(f64, f64, f64)> {
    let (sx, sy) = (w as f64 / 2.0, h as f64 / 2.0);
    let (mut ata, mut atb, mut n) = (DMat3::ZERO, DVec3::ZERO, 0usize);
    for (x, y, v) in pixels {
        let r = DVec3::new((x as f64 - sx) / sx, (y as f64 - sy) / sy, 1.0);
        ata += DMat3::from_cols(r * r.x, r * r.y, r * r.z);
        atb += r * v;
        n += 1;
    }
    if n < 3 || ata.determinant().abs() < 1e-12 * (n as f64).powi(3) {
        return None;
    }
    let q = ata.inverse() * atb;
    // Back to raw pixels.
    Some((q.x / sx, q.y / sy, q.z - q.x - q.y))
}

/// The least-squares plane of the ground truth (fitted on inverse depth; see the module
/// docs). Pixels whose ray misses the plane (behind the camera, or beyond 100x the median
/// depth) get the median depth. `None` with fewer than 3 valid pixels or a degenerate fit.
pub fn plane_baseline(gt: &Raster<f32>, k: &Intrinsics, mask: Option<&Raster<bool>>) -> Option<Baseline> {
    let px: Vec<(usize, usize, f64)> = valid_pixels(gt, mask).collect();
    let (a, b, c) = fit_affine((gt.width(), gt.height()), px.iter().map(|&(x, y, z)| (x, y, 1.0 / z)))?;
    let mut depths: Vec<f64> = px.iter().map(|p| p.2).collect();
    let median = crate::focal::median(&mut depths)?;
    // n^T K^-1 p = d (a, b, c) . p for every pixel p, so K^-T n ~ (a, b, c): n ~ K^T (a, b, c).
    let kt = DMat3::from_cols(DVec3::new(k.fx, 0.0, k.cx), DVec3::new(0.0, k.fy, k.cy), DVec3::new(0.0, 0.0, 1.0));
    let n = (kt * DVec3::new(a, b, c)).normalize_or_zero();
    // Visible points X = z K^-1 p have n . X = z (a x + b y + c) > 0: the camera-facing normal is -n.
    let normal = (-n).as_vec3();
    let depth = Raster::from_fn(gt.width(), gt.height(), |x, y| {
        let inv = a * x as f64 + b * y as f64 + c;
        let z = 1.0 / inv;
        if inv > 0.0 && z < 100.0 * median {
            z as f32
        } else {
            median as f32
        }
    });
    Some(Baseline { depth, normals: Raster::filled(gt.width(), gt.height(), normal) })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pointmap::depth_to_pointmap;

    fn k() -> Intrinsics {
        Intrinsics { fx: 80.0, fy: 90.0, cx: 31.0, cy: 23.0 }
    }

    /// Depth of the plane n . X = d seen through k (ray-plane intersection).
    fn plane_depth(n: DVec3, d: f64) -> Raster<f32> {
        let k = k();
        Raster::from_fn(64, 48, |x, y| {
            let ray = k.unproject(x as f64, y as f64);
            (d / n.dot(ray) * ray.z) as f32
        })
    }

    #[test]
    fn the_plane_of_a_planar_scene_is_that_plane() {
        // A floor tilted towards the camera, normal facing it.
        let n = DVec3::new(0.2, -0.7, -0.6).normalize();
        let gt = plane_depth(n, -2.0);
        assert!(gt.data().iter().all(|&z| z > 0.0));
        let b = plane_baseline(&gt, &k(), None).unwrap();
        for (p, g) in b.depth.data().iter().zip(gt.data()) {
            assert!((p - g).abs() < 1e-4 * g, "{p} vs {g}");
        }
        let got = b.normals.data()[0].as_dvec3();
        assert!(got.dot(n) > 1.0 - 1e-6, "{got} vs {n}");
        // The normal is that of the ground-truth points, and faces the camera.
        let pts = depth_to_pointmap(&gt, &k());
        let (p0, px, py) = (*pts.get(10, 10), *pts.get(11, 10), *pts.get(10, 11));
        let nn = (px - p0).cross(py - p0).normalize().as_dvec3();
        assert!(nn.dot(got).abs() > 1.0 - 1e-4, "{nn} vs {got}");
        assert!(got.dot(p0.as_dvec3()) < 0.0);
    }

    #[test]
    fn the_constant_is_the_median_and_masks_restrict_the_fit() {
        let mut gt = Raster::from_fn(4, 1, |x, _| [1.0, 2.0, 3.0, 0.0][x]);
        let b = constant_baseline(&gt, None).unwrap();
        assert!(b.depth.data().iter().all(|&z| z == 2.0));
        assert_eq!(b.normals.data()[0], Vec3::new(0.0, 0.0, -1.0));
        let mask = Raster::from_fn(4, 1, |x, _| x == 2);
        assert_eq!(constant_baseline(&gt, Some(&mask)).unwrap().depth.data()[0], 3.0);
        *gt.get_mut(2, 0) = f32::NAN;
        assert!(constant_baseline(&gt, Some(&mask)).is_none());
        assert!(plane_baseline(&gt, &k(), None).is_none(), "two valid pixels on one row cannot fix a plane");
    }
}
