//! Which world points a scene's cameras saw: a point is visible in a frame when it projects
//! inside the image onto a valid depth within a tolerance of its own depth. With ground-truth
//! depth this restricts a ground-truth mesh to its observed part, for completeness metrics.

use crate::{Scene, SceneError};
use dens3r_geom::{DMat4, PinholeCamera, Raster};
use glam::Vec3;

/// Depth maps and cameras of a scene, for visibility queries.
pub struct Visibility {
    views: Vec<(PinholeCamera, DMat4, Raster<f32>)>,
    tolerance: f32,
}

impl Visibility {
    /// Loads every frame's depth (frames without depth are skipped); `tolerance` is the largest
    /// depth difference still counted as the same surface.
    pub fn from_scene(scene: &Scene, tolerance: f32) -> Result<Self, SceneError> {
        let mut views = Vec::new();
        for f in scene.frames() {
            if let Some(d) = scene.depth(f)? {
                let cam = f.camera();
                views.push((cam, dens3r_geom::camera::rigid_inverse(&cam.cam_to_world), d));
            }
        }
        Ok(Self { views, tolerance })
    }

    /// True when some frame sees `p` (world coordinates).
    pub fn visible(&self, p: Vec3) -> bool {
        self.views.iter().any(|(cam, w2c, depth)| {
            let pc = w2c.transform_point3(p.as_dvec3());
            if pc.z <= 0.0 {
                return false;
            }
            let (u, v) = cam.intrinsics.project(pc);
            let (u, v) = (u.round(), v.round());
            if u < 0.0 || v < 0.0 || u >= cam.width as f64 || v >= cam.height as f64 {
                return false;
            }
            let d = *depth.get(u as usize, v as usize);
            d.is_finite() && d > 0.0 && (d as f64 - pc.z).abs() <= self.tolerance as f64
        })
    }
}
