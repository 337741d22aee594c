//! Which views each reference is matched against: for every pair, the points the reference
//! sees (SfM track points, or samples of the network's depth) that also project into the
//! other view, each weighed by its triangulation angle (OpenMVS / COLMAP: too small an angle
//! cannot tell depth, too large cannot match) and by how alike the two views' footprints
//! are; a view's K best partners whose score is at least a tenth of its best.

use dens3r_geom::PinholeCamera;
use glam::DVec3;

/// Triangulation angle (degrees) at which a shared point counts fully.
const GOOD_ANGLE_DEG: f64 = 10.0;
/// Angles beyond this count less and less, to nothing at 75 degrees.
const WIDE_ANGLE_DEG: f64 = 45.0;

/// Per view: its chosen source views (best first) and the depth range of the points it sees.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSelection {
    /// Source view indices, best first.
    pub neighbours: Vec<usize>,
    /// Scores of those sources.
    pub scores: Vec<f64>,
    /// Near and far depth of the reference's points (widened by a margin).
    pub depth_range: Option<(f32, f32)>,
}

/// Chooses up to `k` source views for every camera from the world points each one sees
/// (`points[i]`: points visible in view `i`).
pub fn select_views(cameras: &[PinholeCamera], points: &[Vec<DVec3>], k: usize) -> Vec<ViewSelection> {
    let w2c: Vec<_> = cameras.iter().map(|c| c.world_to_cam()).collect();
    (0..cameras.len())
        .map(|i| {
            let ci = cameras[i].center();
            let mut depths: Vec<f64> =
                points[i].iter().map(|p| w2c[i].transform_point3(*p).z).filter(|z| *z > 0.0).collect();
            depths.sort_by(|a, b| a.total_cmp(b));
            let depth_range = (!depths.is_empty()).then(|| {
                let q = |f: f64| depths[((depths.len() - 1) as f64 * f).round() as usize];
                ((q(0.01) * 0.75) as f32, (q(0.99) * 1.33) as f32)
            });
            let fi = cameras[i].intrinsics.fx;
            let mut scored: Vec<(usize, f64)> = (0..cameras.len())
                .filter(|&j| j != i)
                .map(|j| {
                    let cj = cameras[j].center();
                    let fj = cameras[j].intrinsics.fx;
                    let mut score = 0.0;
                    for p in &points[i] {
                        let pj = w2c[j].transform_point3(*p);
                        if pj.z <= 0.0 {
                            continue;
                        }
                        let (u, v) = cameras[j].intrinsics.project(pj);
                        if !(u >= 0.0
                            && v >= 0.0
                            && u <= (cameras[j].width - 1) as f64
                            && v <= (cameras[j].height - 1) as f64)
                        {
                            continue;
                        }
                        let (a, b) = (*p - ci, *p - cj);
                        let angle = a.angle_between(b).to_degrees();
                        let w_angle = if angle < GOOD_ANGLE_DEG {
                            (angle / GOOD_ANGLE_DEG).powf(1.5)
                        } else if angle > WIDE_ANGLE_DEG {
                            (1.0 - (angle - WIDE_ANGLE_DEG) / 30.0).max(0.0)
                        } else {
                            1.0
                        };
                        // Footprint ratio: a point 3x larger in one view is hard to match.
                        let ratio = (a.length() / fi) / (b.length() / fj);
                        let r = if ratio > 1.0 { ratio } else { 1.0 / ratio };
                        let w_scale = if r < 1.6 { 1.0 } else { (1.6 / r).powi(2) };
                        score += w_angle * w_scale;
                    }
                    (j, score)
                })
                .filter(|(_, s)| *s > 0.0)
                .collect();
            scored.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
            let best = scored.first().map(|s| s.1).unwrap_or(0.0);
            scored.retain(|s| s.1 >= 0.1 * best);
            scored.truncate(k);
            ViewSelection {
                neighbours: scored.iter().map(|s| s.0).collect(),
                scores: scored.iter().map(|s| s.1).collect(),
                depth_range,
            }
        })
        .collect()
}
