//! The dense stage on a scene folder: its cameras and photos, its depth / normals / confidence
//! (the network's, from `reconstruct` or `predict`) as the prior; the result written as a
//! scene folder at the working size (MVS depth, normals and confidence of the pixels fusion
//! kept), the fused points, and a TSDF mesh of the kept depth.

use crate::pipeline::{MvsError, MvsResult, PriorMaps, ViewSource};
use dens3r_fusion::scene::{fuse_frames, FusionFrame, SceneFusion};
use dens3r_fusion::{extract_mesh, ExtractOptions, TsdfParams};
use dens3r_geom::{PinholeCamera, Raster};
use dens3r_mesh::TriMesh;
use dens3r_scene::{Frame, Scene, SceneError, SceneWriter};
use image::RgbImage;
use std::borrow::Cow;

/// A scene folder's frames as views, their depth / normals / confidence as the prior
/// (`PatchMatchOptions::prior_weight` 0 uses the depth for the depth range only).
pub struct SceneViews<'s> {
    scene: &'s Scene,
}

impl<'s> SceneViews<'s> {
    /// The views of `scene`.
    pub fn new(scene: &'s Scene) -> Self {
        Self { scene }
    }
}

fn input(e: SceneError) -> MvsError {
    MvsError::Input(e.to_string())
}

impl ViewSource for SceneViews<'_> {
    fn len(&self) -> usize {
        self.scene.frames().len()
    }

    fn camera(&self, i: usize) -> PinholeCamera {
        self.scene.frames()[i].camera()
    }

    fn name(&self, i: usize) -> String {
        self.scene.frames()[i].name.clone()
    }

    fn image(&self, i: usize) -> Result<RgbImage, MvsError> {
        self.scene.image(&self.scene.frames()[i]).map_err(input)
    }

    fn prior(&self, i: usize) -> Result<Option<PriorMaps>, MvsError> {
        let f = &self.scene.frames()[i];
        let Some(depth) = self.scene.depth(f).map_err(input)? else { return Ok(None) };
        let normals = self.scene.normals(f).map_err(input)?;
        let conf = self.scene.conf(f).map_err(input)?;
        Ok(Some(PriorMaps { depth, normals, conf }))
    }
}

/// The confidence written for a kept pixel: `2 - cost` (0..2, higher is better).
pub fn confidence(cost: f32) -> f32 {
    (2.0 - cost).clamp(0.0, 2.0)
}

/// Writes `result` as scene frames into `w`: each view at its working size with the photo
/// resized, and the kept pixels' depth, normals and confidence (others 0).
pub fn write_frames(w: &mut SceneWriter, source: &dyn ViewSource, result: &MvsResult) -> Result<(), MvsError> {
    let err = |e: SceneError| MvsError::Input(e.to_string());
    for (i, v) in result.views.iter().enumerate() {
        let name = source.name(i);
        let cam = source.camera(i);
        let img = source.image(i)?;
        let (small, _) = crate::image::resize_view(&img, &cam.intrinsics, (v.maps.camera.width, v.maps.camera.height));
        w.add_frame(Frame::new(&name, &v.maps.camera), &small).map_err(err)?;
        let depth = result.filtered_depth(i);
        let normals = Raster::from_fn(depth.width(), depth.height(), |x, y| {
            if *v.kept.get(x, y) {
                *v.maps.normals.get(x, y)
            } else {
                glam::Vec3::ZERO
            }
        });
        let conf = Raster::from_fn(depth.width(), depth.height(), |x, y| {
            if *v.kept.get(x, y) {
                confidence(*v.maps.cost.get(x, y))
            } else {
                0.0
            }
        });
        w.write_depth(&name, &depth).map_err(err)?;
        w.write_normals(&name, &normals).map_err(err)?;
        w.write_conf(&name, &conf).map_err(err)?;
    }
    Ok(())
}

/// The fused points as a vertex-only mesh (positions, normals, colours), for PLY.
pub fn points_mesh(result: &MvsResult) -> TriMesh {
    TriMesh {
        positions: result.points.iter().map(|p| p.position).collect(),
        indices: Vec::new(),
        normals: Some(result.points.iter().map(|p| p.normal).collect()),
        colors: Some(result.colors.clone()),
    }
}

/// Twice the pixel footprint at the median kept depth over the views.
pub fn auto_voxel(result: &MvsResult) -> Option<f32> {
    let mut per_view: Vec<f64> = (0..result.views.len())
        .filter_map(|i| {
            let d = result.filtered_depth(i);
            let mut v: Vec<f64> = d.data().iter().filter(|d| **d > 0.0).map(|&d| d as f64).collect();
            let fx = result.views[i].maps.camera.intrinsics.fx;
            dens3r_geom::focal::median(&mut v).map(|m| 2.0 * m / fx)
        })
        .collect();
    dens3r_geom::focal::median(&mut per_view).map(|v| v as f32).filter(|v| v.is_finite() && *v > 0.0)
}

/// A TSDF mesh of the kept depth (weighted by the normal-to-ray angle, coloured), at `voxel`
/// (automatic when `None`); returns the mesh and the voxel used.
pub fn tsdf_mesh(
    result: &MvsResult,
    source: &dyn ViewSource,
    voxel: Option<f32>,
    budget_bytes: Option<usize>,
) -> Result<(TriMesh, f32), MvsError> {
    let Some(voxel) = voxel.or_else(|| auto_voxel(result)) else {
        return Err(MvsError::Setting(
            "fusion kept no pixel: no two views agree on any surface (too few views overlap, or the photos have no texture)"
                .into(),
        ));
    };
    let mut params = TsdfParams::new(voxel);
    params.trunc = 4.0 * voxel;
    params.depth_range = (voxel * 1e-3, f32::MAX);
    params.budget_bytes = budget_bytes;
    let opts = SceneFusion { params, use_conf: false, min_conf: 0.0, use_normals: true, gpu: false };
    let frames = (0..result.views.len()).map(|i| {
        let v = &result.views[i];
        let cam = source.camera(i);
        let img = source.image(i).map_err(|e| dens3r_fusion::scene::SceneFusionError::Scene(e.to_string()))?;
        let (small, _) = crate::image::resize_view(&img, &cam.intrinsics, (v.maps.camera.width, v.maps.camera.height));
        Ok(FusionFrame {
            name: Cow::Owned(source.name(i)),
            camera: v.maps.camera,
            depth: Cow::Owned(result.filtered_depth(i)),
            mask: None,
            color: Some(Cow::Owned(small)),
            conf: None,
            normals: Some(Cow::Borrowed(&v.maps.normals)),
        })
    });
    let (tsdf, _) =
        fuse_frames("multi-view stereo", frames, &opts, |_, _| {}).map_err(|e| MvsError::Setting(e.to_string()))?;
    let mesh = extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: 100, crop: None });
    Ok((mesh, voxel))
}
