//! What `dens3r mvs` and `reconstruct` write of the dense stage into a (staged) folder: the
//! views at the working size as a scene folder (kept depth, normals, confidence), the fused
//! points (`points.ply`), the TSDF mesh (`mesh.ply`), `mvs.json` (what ran and how long), and
//! the page.

use crate::pipeline::{MvsError, MvsResult, ViewSource};
use crate::scene::{points_mesh, tsdf_mesh, write_frames};
use dens3r_mesh::TriMesh;
use dens3r_scene::{Scene, SceneWriter};
use serde_json::json;
use std::path::Path;
use std::time::Instant;

/// How the mesh is made.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MeshOptions {
    /// TSDF voxel; `None`: twice the pixel footprint at the median kept depth.
    pub voxel: Option<f32>,
    /// Stop before the voxel grid exceeds this many bytes.
    pub budget_bytes: Option<usize>,
}

/// What was written.
#[derive(Debug, Clone)]
pub struct MvsSummary {
    /// Views.
    pub views: usize,
    /// Fused points.
    pub points: usize,
    /// Share of the working-size pixels fusion kept.
    pub kept_fraction: f64,
    /// Median seconds of PatchMatch per view.
    pub seconds_per_view: f64,
    /// Seconds of fusion.
    pub fusion_seconds: f64,
    /// Mesh triangles.
    pub triangles: usize,
    /// TSDF voxel used.
    pub voxel: f32,
    /// Seconds of meshing.
    pub mesh_seconds: f64,
    /// Working size of the first view.
    pub working_size: (usize, usize),
}

impl MvsSummary {
    /// As JSON (for `summary.json` / `mvs.json`).
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "views": self.views,
            "points": self.points,
            "kept_fraction": self.kept_fraction,
            "seconds_per_view": self.seconds_per_view,
            "fusion_seconds": self.fusion_seconds,
            "mesh_triangles": self.triangles,
            "voxel": self.voxel,
            "mesh_seconds": self.mesh_seconds,
            "working_size": [self.working_size.0, self.working_size.1],
        })
    }
}

fn setting(e: impl std::fmt::Display) -> MvsError {
    MvsError::Setting(e.to_string())
}

/// Writes `result` into the folder `dir` (inside an output being staged): the scene folder,
/// `points.ply`, `mesh.ply` and `mvs.json`; `extra` goes into `cameras.json`'s top level.
/// Returns the summary and the mesh.
pub fn write_mvs(
    dir: &Path,
    source: &dyn ViewSource,
    result: &MvsResult,
    mesh: &MeshOptions,
    extra: &[(&str, serde_json::Value)],
) -> Result<(MvsSummary, TriMesh), MvsError> {
    let mut w = SceneWriter::in_folder(dir).map_err(setting)?;
    w.set_extra("generator", json!("dens3r mvs"));
    for (k, v) in extra {
        w.set_extra(k, v.clone());
    }
    write_frames(&mut w, source, result)?;
    w.finish().map_err(setting)?;
    let points = points_mesh(result);
    if !points.positions.is_empty() {
        dens3r_mesh::write_mesh(&dir.join("points.ply"), &points).map_err(setting)?;
    }
    let t = Instant::now();
    let (mesh, voxel) = tsdf_mesh(result, source, mesh.voxel, mesh.budget_bytes)?;
    if mesh.indices.is_empty() {
        return Err(MvsError::Setting(format!(
            "the kept depth has no surface at voxel {voxel} (too few pixels agree across views)"
        )));
    }
    dens3r_mesh::write_mesh(&dir.join("mesh.ply"), &mesh).map_err(setting)?;
    let mut secs = result.seconds_per_view.clone();
    let summary = MvsSummary {
        views: result.views.len(),
        points: result.points.len(),
        kept_fraction: result.kept_fraction(),
        seconds_per_view: dens3r_geom::focal::median(&mut secs).unwrap_or(0.0),
        fusion_seconds: result.fusion_seconds,
        triangles: mesh.indices.len(),
        voxel,
        mesh_seconds: t.elapsed().as_secs_f64(),
        working_size: result.views.first().map(|v| (v.maps.camera.width, v.maps.camera.height)).unwrap_or((0, 0)),
    };
    let text = serde_json::to_string_pretty(&summary.to_json()).expect("plain JSON");
    dens3r_io_write(&dir.join("mvs.json"), &text)?;
    Ok((summary, mesh))
}

fn dens3r_io_write(path: &Path, text: &str) -> Result<(), MvsError> {
    dens3r_io::write_atomic(path, |w| std::io::Write::write_all(w, text.as_bytes())).map_err(setting)
}

/// Writes the page of the dense result in `dir` (its scene folder at `dir/scene_prefix`).
pub fn write_mvs_page(
    dir: &Path,
    scene_prefix: &str,
    title: &str,
    mesh: &TriMesh,
    summary: serde_json::Value,
) -> Result<(), MvsError> {
    let scene = Scene::open(&dir.join(scene_prefix)).map_err(setting)?;
    let views = dens3r_viewer::scene_views::SceneViews::read(&scene, scene_prefix).map_err(setting)?;
    let page = dens3r_viewer::Page {
        title: title.into(),
        views: views.views(),
        mesh: Some(mesh),
        summary: Some(summary),
        ..Default::default()
    };
    dens3r_viewer::write_page(dir, &page, &dens3r_viewer::PageOptions::default()).map_err(setting)?;
    Ok(())
}
