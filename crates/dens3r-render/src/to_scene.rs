//! Rendering a camera path into a scene folder.

use crate::world::World;
use dens3r_geom::{DMat4, Intrinsics, PinholeCamera};
use dens3r_scene::{Frame, SceneError, SceneWriter};
use std::collections::BTreeMap;
use std::path::Path;

/// What [`render_to_scene`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSummary {
    /// Views written.
    pub frames: usize,
    /// Fraction of pixels with valid depth, over all views.
    pub coverage: f64,
    /// Triangles in `gt_mesh.ply`.
    pub gt_triangles: usize,
}

/// Renders every pose with the same intrinsics into `dir`: images, depth, normals, masks
/// (valid depth), labels, instances, `classes.json`, `gt_mesh.ply` and finally
/// `cameras.json`. `progress(k)` is called after each view.
pub fn render_to_scene(
    world: &World,
    intrinsics: Intrinsics,
    size: (usize, usize),
    poses: &[DMat4],
    classes: &BTreeMap<u16, String>,
    dir: &Path,
    progress: impl FnMut(usize),
) -> Result<RenderSummary, SceneError> {
    let cameras: Vec<PinholeCamera> = poses
        .iter()
        .map(|pose| PinholeCamera { intrinsics, width: size.0, height: size.1, cam_to_world: *pose })
        .collect();
    render_cameras_to_scene(world, &cameras, classes, true, dir, progress)
}

/// [`render_to_scene`] with one camera per view (each its own intrinsics and size);
/// `gt_mesh: false` leaves out `gt_mesh.ply`.
pub fn render_cameras_to_scene(
    world: &World,
    cameras: &[PinholeCamera],
    classes: &BTreeMap<u16, String>,
    gt_mesh: bool,
    dir: &Path,
    mut progress: impl FnMut(usize),
) -> Result<RenderSummary, SceneError> {
    let mut writer = SceneWriter::create(dir)?;
    let (mut valid, mut total) = (0usize, 0usize);
    for (k, cam) in cameras.iter().enumerate() {
        let view = world.render(cam);
        let name = format!("{k:04}");
        writer.add_frame(Frame::new(&name, cam), &view.rgb)?;
        writer.write_depth(&name, &view.depth)?;
        writer.write_normals(&name, &view.normals)?;
        writer.write_mask(&name, &view.depth.map(|d| *d > 0.0))?;
        writer.write_labels(&name, &view.labels)?;
        writer.write_instances(&name, &view.instances)?;
        valid += view.depth.data().iter().filter(|d| **d > 0.0).count();
        total += view.depth.data().len();
        progress(k + 1);
    }
    writer.write_classes(classes)?;
    let mut gt_triangles = 0;
    if gt_mesh {
        let mesh = world.gt_mesh();
        writer.write_gt_mesh(&mesh)?;
        gt_triangles = mesh.indices.len();
    }
    writer.set_extra("generator", serde_json::json!("dens3r render"));
    writer.finish()?;
    Ok(RenderSummary { frames: cameras.len(), coverage: valid as f64 / total.max(1) as f64, gt_triangles })
}
