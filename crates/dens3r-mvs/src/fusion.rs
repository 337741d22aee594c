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
