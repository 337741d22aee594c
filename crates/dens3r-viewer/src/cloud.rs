//! A coloured point cloud from aligned depth maps, small enough for a browser: every view
//! sampled on one regular pixel stride, points sorted by confidence (highest first) so that a
//! confidence threshold is a prefix of the list.

use crate::page::View;
use glam::{DVec3, Vec3};

/// Points in world coordinates with their colours and confidences, confidence descending.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Cloud {
    /// World positions.
    pub positions: Vec<Vec3>,
    /// sRGB colours.
    pub colors: Vec<[u8; 3]>,
    /// Confidence (the network's; 1 where a view has none), descending.
    pub conf: Vec<f32>,
    /// The median distance between neighbouring samples on the surface (world units): the
    /// footprint of `stride` pixels at each point's depth in its own view.
    pub spacing: f32,
}

/// The pixel stride that keeps at most `max_points` of `valid` pixels.
pub fn stride_for(valid: usize, max_points: usize) -> usize {
    if max_points == 0 {
        return usize::MAX;
    }
    let mut s = 1;
    while valid.div_ceil(s * s) > max_points {
        s += 1;
    }
    s
}

fn valid_at(v: &View, i: usize) -> bool {
    let d = v.depth.data()[i];
    d.is_finite() && d > 0.0 && v.mask.is_none_or(|m| m.data()[i])
}

/// Back-projects every `stride`-th pixel (both ways) of each view's depth into the world.
pub fn cloud(views: &[View], max_points: usize) -> Cloud {
    let valid: usize = views.iter().map(|v| (0..v.depth.data().len()).filter(|&i| valid_at(v, i)).count()).sum();
    let s = stride_for(valid, max_points);
    let mut pts: Vec<(Vec3, [u8; 3], f32)> = Vec::new();
    let mut footprint: Vec<f32> = Vec::new();
    for v in views {
        let (w, h) = (v.depth.width(), v.depth.height());
        let k = &v.camera.intrinsics;
        let rgb_ok = v.rgb.width() as usize == w && v.rgb.height() as usize == h;
        for y in (s / 2..h).step_by(s) {
            for x in (s / 2..w).step_by(s) {
                let i = y * w + x;
                if !valid_at(v, i) {
                    continue;
                }
                let d = v.depth.data()[i] as f64;
                let p = v.camera.cam_to_world.transform_point3(k.unproject(x as f64, y as f64) * d);
                if !p.is_finite() {
                    continue;
                }
                let c = if rgb_ok { v.rgb.get_pixel(x as u32, y as u32).0 } else { [200, 200, 200] };
                let conf = v.conf.map_or(1.0, |c| c.data()[i]);
                pts.push((p.as_vec3(), c, if conf.is_finite() { conf } else { 0.0 }));
                footprint.push((d / k.fx * s as f64) as f32);
            }
        }
    }
    pts.sort_by(|a, b| b.2.total_cmp(&a.2));
    Cloud {
        positions: pts.iter().map(|p| p.0).collect(),
        colors: pts.iter().map(|p| p.1).collect(),
        conf: pts.iter().map(|p| p.2).collect(),
        spacing: median(&mut footprint).unwrap_or(0.0),
    }
}

/// The median of `v` (reordered), `None` when empty.
fn median(v: &mut [f32]) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    Some(*v.select_nth_unstable_by(mid, f32::total_cmp).1)
}

/// Centre and radius holding most of `points` (the 2nd-98th percentile box per axis), so a
/// few stray points do not set the view; falls back to the camera centres.
pub fn bounds(points: &[Vec3], centres: &[DVec3]) -> (Vec3, f32) {
    let from_centres: Vec<Vec3>;
    let pts = if points.len() >= 8 {
        points
    } else {
        from_centres = centres.iter().map(|c| c.as_vec3()).collect();
        &from_centres
    };
    if pts.is_empty() {
        return (Vec3::ZERO, 1.0);
    }
    let mut v = vec![0.0f32; pts.len()];
    let mut q = |axis: usize, p: f32| {
        v.iter_mut().zip(pts).for_each(|(x, pt)| *x = pt[axis]);
        let k = ((v.len() - 1) as f32 * p) as usize;
        *v.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let lo = Vec3::new(q(0, 0.02), q(1, 0.02), q(2, 0.02));
    let hi = Vec3::new(q(0, 0.98), q(1, 0.98), q(2, 0.98));
    let radius = ((hi - lo).length() / 2.0).max(1e-6);
    ((lo + hi) / 2.0, radius)
}
