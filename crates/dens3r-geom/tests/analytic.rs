//! Normals and focal against closed-form geometry: an analytically ray-traced sphere in
//! front of a tilted plane (no renderer involved).

use dens3r_geom::normals::{normals_dens3r, normals_from_pointmap, normals_from_pointmap_robust};
use dens3r_geom::{focal_from_pointmap, focal_or_fallback, FocalMode, Intrinsics, NormalConvention, Raster};
use glam::{DVec3, Vec3};

const W: usize = 320;
const H: usize = 240;
const CENTER: DVec3 = DVec3::new(0.15, -0.1, 3.0);
const RADIUS: f64 = 0.9;

/// Plane through (0,0,5) with this (camera-facing) normal.
fn plane_normal() -> DVec3 {
    DVec3::new(0.3, -0.2, -1.0).normalize()
}

/// (point, analytic normal, is_sphere) of the first hit along pixel (x, y).
fn trace(k: &Intrinsics, x: usize, y: usize) -> (DVec3, DVec3, bool) {
    let d = k.unproject(x as f64, y as f64).normalize();
    let oc = -CENTER;
    let b = oc.dot(d);
    let disc = b * b - (oc.length_squared() - RADIUS * RADIUS);
    if disc > 0.0 {
        let t = -b - disc.sqrt();
        let p = d * t;
        return (p, (p - CENTER) / RADIUS, true);
    }
    let n = plane_normal();
    let t = DVec3::new(0.0, 0.0, 5.0).dot(n) / d.dot(n);
    (d * t, n, false)
}

fn scene(k: &Intrinsics) -> (Raster<Vec3>, Raster<Vec3>, Raster<bool>) {
    let pts = Raster::from_fn(W, H, |x, y| trace(k, x, y).0.as_vec3());
    let nrm = Raster::from_fn(W, H, |x, y| trace(k, x, y).1.as_vec3());
    // "Away from silhouettes": every pixel within 3 px is on the same surface, not grazing.
    let keep = Raster::from_fn(W, H, |x, y| {
        let (p, n, s) = trace(k, x, y);
        if x < 3 || y < 3 || x + 3 >= W || y + 3 >= H || -n.dot(p.normalize()) < 0.3 {
            return false;
        }
        (x - 3..=x + 3).all(|xx| (y - 3..=y + 3).all(|yy| trace(k, xx, yy).2 == s))
    });
    (pts, nrm, keep)
}

fn max_angle_deg(pred: &Raster<Vec3>, gt: &Raster<Vec3>, keep: &Raster<bool>) -> (f64, usize) {
    let mut worst = 0.0f64;
    let mut n = 0;
    for i in 0..gt.data().len() {
        if keep.data()[i] {
            let (a, b) = (pred.data()[i].as_dvec3(), gt.data()[i].as_dvec3());
            worst = worst.max(a.normalize().dot(b.normalize()).clamp(-1.0, 1.0).acos().to_degrees());
            n += 1;
        }
    }
    (worst, n)
}

#[test]
fn sphere_and_plane_normals_within_one_degree() {
    let k = Intrinsics::from_hfov(W, H, 60.0);
    let (pts, gt, keep) = scene(&k);
    let (err, n) = max_angle_deg(&normals_from_pointmap(&pts), &gt, &keep);
    assert!(n > 30_000, "too few pixels tested: {n}");
    assert!(err < 1.0, "central differences: worst {err} deg");
    let (err, _) = max_angle_deg(&normals_from_pointmap_robust(&pts, 0.05), &gt, &keep);
    assert!(err < 1.0, "robust: worst {err} deg");
    // The Dens3R rule gives the raw convention: convert, then compare.
    let raw = normals_dens3r(&pts);
    let cv = raw.map(|n| NormalConvention::Dens3rRaw.to_opencv(*n));
    let (err, _) = max_angle_deg(&cv, &gt, &keep);
    assert!(err < 1.0, "dens3r rule: worst {err} deg");
    // Every analytic normal faces the camera, and so does every estimate.
    assert!(cv.data().iter().zip(pts.data()).all(|(n, p)| n.dot(*p) <= 0.0));
}

#[test]
fn robust_normals_drop_silhouettes_central_differences_do_not() {
    let k = Intrinsics::from_hfov(W, H, 60.0);
    let (pts, gt, _) = scene(&k);
    // Plane pixels whose left neighbour is on the sphere (an occlusion edge, a jump of > 1 m).
    let edge = Raster::from_fn(W, H, |x, y| x > 0 && x + 1 < W && !trace(&k, x, y).2 && trace(&k, x - 1, y).2);
    let count = edge.data().iter().filter(|e| **e).count();
    assert!(count > 20);
    let (central_err, _) = max_angle_deg(&normals_from_pointmap(&pts), &gt, &edge);
    assert!(central_err > 20.0, "central differences should smear across the silhouette ({central_err})");
    // The robust variant uses the forward difference there, which stays on the flat plane.
    let robust = normals_from_pointmap_robust(&pts, 0.05);
    let (err, _) = max_angle_deg(&robust, &gt, &edge);
    assert!(err < 0.5, "robust normals at the occlusion edge: worst {err} deg");
}

#[test]
fn focal_recovered_within_half_percent() {
    for (hfov, w, h) in [(60.0, W, H), (40.0, 200, 300), (85.0, 256, 192)] {
        let k = Intrinsics::from_hfov(w, h, hfov);
        let pts = Raster::from_fn(w, h, |x, y| trace(&k, x, y).0.as_vec3());
        let pp = (w as f64 / 2.0, h as f64 / 2.0);
        for mode in [FocalMode::Weiszfeld, FocalMode::Median] {
            let f = focal_from_pointmap(&pts, pp, mode).unwrap();
            assert!((f / k.fx - 1.0).abs() < 0.005, "{mode:?} {hfov}: {f} vs {}", k.fx);
        }
    }
    // Weiszfeld is robust to a few wild points (the median shrugs them off too).
    let k = Intrinsics::from_hfov(W, H, 60.0);
    let mut pts = Raster::from_fn(W, H, |x, y| trace(&k, x, y).0.as_vec3());
    for i in (0..pts.data().len()).step_by(97) {
        pts.data_mut()[i] *= Vec3::new(3.0, -2.0, 1.0);
    }
    let f = focal_from_pointmap(&pts, (W as f64 / 2.0, H as f64 / 2.0), FocalMode::Weiszfeld).unwrap();
    assert!((f / k.fx - 1.0).abs() < 0.005, "{f} vs {}", k.fx);
    let empty = Raster::filled(4, 4, Vec3::NAN);
    assert_eq!(focal_from_pointmap(&empty, (2.0, 2.0), FocalMode::Weiszfeld), None);
}

/// A pointmap that explains a focal gives it; one that gives none (empty, or mirrored so the
/// least-squares focal is negative, as untrained weights do) falls back to a 60-degree field of
/// view: w / 2 / tan(30 deg).
#[test]
fn focal_or_fallback_takes_the_pointmap_or_sixty_degrees() {
    let k = Intrinsics::from_hfov(200, 150, 45.0);
    let pts = Raster::from_fn(200, 150, |x, y| trace(&k, x, y).0.as_vec3());
    let f = focal_or_fallback(&pts, 200, 150).unwrap();
    assert!((f / k.fx - 1.0).abs() < 0.005, "{f} vs {}", k.fx);
    let sixty = 100.0 / 30f64.to_radians().tan();
    let mirrored = Raster::from_fn(200, 150, |x, y| trace(&k, x, y).0.as_vec3() * Vec3::new(-1.0, -1.0, 1.0));
    for bad in [Raster::filled(200, 150, Vec3::NAN), mirrored] {
        let e = focal_or_fallback(&bad, 200, 150).unwrap_err();
        assert!((e - sixty).abs() < 1e-9, "{e} vs {sixty}");
    }
}
