//! Fusion of the views' depth maps (COLMAP's stereo_fusion rules): a pixel is kept only where
//! at least `min_agreeing` other views see a surface at its depth (relative difference within
//! the tolerance) with its normal (angle within the tolerance); its point is the mean of the
//! agreeing views' points. Sky, moving things and mismatches agree with nothing and drop out.

use crate::options::FusionOptions;
use dens3r_geom::{PinholeCamera, Raster};
use glam::Vec3;
use rayon::prelude::*;

/// One view's dense result, in its working-size camera.
#[derive(Debug, Clone)]
pub struct DepthNormalMap {
    /// Camera at the maps' size.
    pub camera: PinholeCamera,
    /// z-depth (0 = none).
    pub depth: Raster<f32>,
    /// Camera-frame normals facing the camera.
    pub normals: Raster<Vec3>,
    /// Matching cost (0 best .. 2).
    pub cost: Raster<f32>,
}

/// A fused point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedPoint {
    /// World position.
    pub position: Vec3,
    /// World unit normal.
    pub normal: Vec3,
    /// The reference view it came from and its pixel there (for its colour).
    pub view: usize,
    /// Pixel `(x, y)` in that view.
    pub pixel: (u32, u32),
    /// Views that agree, the reference included.
    pub views: u32,
}

/// What fusion keeps of one reference view.
#[derive(Debug, Clone)]
pub struct FusedView {
    /// Pixels that enough other views agree with.
    pub kept: Raster<bool>,
    /// Points this view contributes (pixels whose agreeing views all come after it, so a
    /// surface seen by several views is emitted once).
    pub points: Vec<FusedPoint>,
}

/// For every view, the views its pixels are checked against: its own neighbours and the views
/// that chose it.
pub fn fusion_partners(neighbours: &[Vec<usize>]) -> Vec<Vec<usize>> {
    let mut out: Vec<Vec<usize>> = neighbours.to_vec();
    for (i, ns) in neighbours.iter().enumerate() {
        for &j in ns {
            if !out[j].contains(&i) {
                out[j].push(i);
            }
        }
    }
    out
}

/// Fuses view `i` of `maps` against its `partners`.
pub fn fuse_view(i: usize, maps: &[DepthNormalMap], partners: &[usize], o: &FusionOptions) -> FusedView {
    let m = &maps[i];
    let (w, h) = (m.depth.width(), m.depth.height());
    let c2w_i = m.camera.cam_to_world.as_mat4();
    let rot_i = glam::Mat3::from_mat4(c2w_i);
    let others: Vec<(usize, glam::Mat4, glam::Mat4, glam::Mat3)> = partners
        .iter()
        .filter(|&&j| j != i)
        .map(|&j| {
            let c2w = maps[j].camera.cam_to_world.as_mat4();
            (j, c2w, maps[j].camera.world_to_cam().as_mat4(), glam::Mat3::from_mat4(c2w))
        })
        .collect();
    let cos_tol = o.normal_tolerance_deg.to_radians().cos();
    let ki = m.camera.intrinsics;
    let rows: Vec<(Vec<bool>, Vec<FusedPoint>)> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut kept = vec![false; w];
            let mut points = Vec::new();
            #[allow(clippy::needless_range_loop)] // x is also the pixel's coordinate
            for x in 0..w {
                let d = *m.depth.get(x, y);
                let n = *m.normals.get(x, y);
                if !(d > 0.0 && d.is_finite() && *m.cost.get(x, y) <= o.max_cost && n.length_squared() > 0.5) {
                    continue;
                }
                let ray = ki.unproject(x as f64, y as f64).as_vec3();
                let pw = c2w_i.transform_point3(ray * d);
                let nw = rot_i * n;
                let (mut sum, mut nsum, mut agree, mut first) = (pw, nw, 0u32, true);
                for (j, c2w_j, w2c_j, rot_j) in &others {
                    let mj = &maps[*j];
                    let pj = w2c_j.transform_point3(pw);
                    if pj.z <= 0.0 {
                        continue;
                    }
                    let kj = mj.camera.intrinsics;
                    let u = (kj.fx as f32 * pj.x / pj.z + kj.cx as f32).round();
                    let v = (kj.fy as f32 * pj.y / pj.z + kj.cy as f32).round();
                    if !(u >= 0.0 && v >= 0.0 && (u as usize) < mj.depth.width() && (v as usize) < mj.depth.height()) {
                        continue;
                    }
                    let (uu, vv) = (u as usize, v as usize);
                    let dj = *mj.depth.get(uu, vv);
                    if !(dj > 0.0 && dj.is_finite() && *mj.cost.get(uu, vv) <= o.max_cost) {
                        continue;
                    }
                    if ((pj.z - dj) / dj).abs() > o.depth_tolerance {
                        continue;
                    }
                    let nj = *rot_j * *mj.normals.get(uu, vv);
                    if nj.dot(nw) < cos_tol {
                        continue;
                    }
                    agree += 1;
                    if *j < i {
                        first = false;
                    }
                    let qj = kj.unproject(u as f64, v as f64).as_vec3() * dj;
                    sum += c2w_j.transform_point3(qj);
                    nsum += nj;
                }
                if agree as usize >= o.min_agreeing {
                    kept[x] = true;
                    if first {
                        points.push(FusedPoint {
                            position: sum / (agree + 1) as f32,
                            normal: nsum.normalize_or_zero(),
                            view: i,
                            pixel: (x as u32, y as u32),
                            views: agree + 1,
                        });
                    }
                }
            }
            (kept, points)
        })
        .collect();
    let mut kept = Vec::with_capacity(w * h);
    let mut points = Vec::new();
    for (k, p) in rows {
        kept.extend(k);
        points.extend(p);
    }
    FusedView { kept: Raster::from_vec(w, h, kept).expect("sized"), points }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::{look_at, Intrinsics};
    use glam::DVec3;

    /// Depth and normals of the plane z = 0 seen by `camera` (analytic).
    fn plane_maps(camera: PinholeCamera) -> DepthNormalMap {
        let (w, h) = (camera.width, camera.height);
        let c2w = camera.cam_to_world;
        let w2c = camera.world_to_cam();
        let centre = camera.center();
        let normal_cam = w2c.transform_vector3(DVec3::Z);
        let normal_cam = if normal_cam.z > 0.0 { -normal_cam } else { normal_cam };
        let depth = Raster::from_fn(w, h, |x, y| {
            let ray = c2w.transform_vector3(camera.intrinsics.unproject(x as f64, y as f64));
            let t = -centre.z / ray.z;
            if t > 0.0 {
                t as f32
            } else {
                0.0
            }
        });
        DepthNormalMap {
            camera,
            depth,
            normals: Raster::filled(w, h, normal_cam.as_vec3()),
            cost: Raster::filled(w, h, 0.1),
        }
    }

    fn camera(eye: DVec3, target: DVec3, hfov: f64) -> PinholeCamera {
        PinholeCamera {
            intrinsics: Intrinsics::from_hfov(64, 48, hfov),
            width: 64,
            height: 48,
            cam_to_world: look_at(eye, target, DVec3::Y).unwrap(),
        }
    }

    #[test]
    fn a_pixel_enters_only_where_two_other_views_agree() {
        // View 0 sees wide; views 1 and 2 look at the middle only, so view 0's border is seen
        // by it alone.
        let maps = vec![
            plane_maps(camera(DVec3::new(0.0, 0.0, 3.0), DVec3::ZERO, 90.0)),
            plane_maps(camera(DVec3::new(0.3, 0.0, 3.0), DVec3::ZERO, 30.0)),
            plane_maps(camera(DVec3::new(-0.3, 0.0, 3.0), DVec3::ZERO, 30.0)),
        ];
        let mut disagree = maps.clone();
        // In view 2 a patch 2% too far: view 0's pixels there have one agreeing view, not two.
        let m2 = &mut disagree[2];
        for y in 20..28 {
            for x in 28..36 {
                *m2.depth.get_mut(x, y) *= 1.02;
            }
        }
        let o = FusionOptions::default();
        let f = fuse_view(0, &maps, &[1, 2], &o);
        let g = fuse_view(0, &disagree, &[1, 2], &o);
        let w2c: Vec<_> = maps.iter().map(|m| m.camera.world_to_cam()).collect();
        let (mut alone_kept, mut shared_dropped, mut shared) = (0, 0, 0);
        for y in 0..48 {
            for x in 0..64 {
                let m = &maps[0];
                let d = *m.depth.get(x, y) as f64;
                let p = m.camera.cam_to_world.transform_point3(m.camera.intrinsics.unproject(x as f64, y as f64) * d);
                // Inside views 1 and 2 with a margin of 2 pixels?
                let seen = |j: usize| {
                    let q = w2c[j].transform_point3(p);
                    let (u, v) = maps[j].camera.intrinsics.project(q);
                    u > 2.0 && v > 2.0 && u < 61.0 && v < 45.0
                };
                let outside = |j: usize| {
                    let q = w2c[j].transform_point3(p);
                    let (u, v) = maps[j].camera.intrinsics.project(q);
                    !(u > -1.0 && v > -1.0 && u < 64.0 && v < 48.0)
                };
                if outside(1) && outside(2) {
                    alone_kept += *f.kept.get(x, y) as usize;
                } else if seen(1) && seen(2) {
                    shared += 1;
                    shared_dropped += !*f.kept.get(x, y) as usize;
                }
            }
        }
        assert!(shared > 50, "the test's views overlap in {shared} pixels");
        assert_eq!(alone_kept, 0, "pixels seen by one view only were fused");
        assert_eq!(shared_dropped, 0, "pixels all three views agree on were dropped");
        // The disagreeing patch: fewer kept than with agreement, by the patch's pixels.
        let kept = |v: &FusedView| v.kept.data().iter().filter(|b| **b).count();
        assert!(kept(&g) < kept(&f), "a 2% depth disagreement left {} vs {} pixels", kept(&g), kept(&f));
        // Points are emitted once: view 0 is first among every agreeing set.
        assert_eq!(f.points.len(), kept(&f));
        for p in &f.points {
            assert!(p.position.z.abs() < 1e-3, "a fused point off the plane: {:?}", p.position);
            assert!((p.normal.z.abs() - 1.0).abs() < 1e-4);
        }
    }
}
