//! A scene folder's frames as the page's views: what `dens3r predict` wrote (each photo on
//! its own, placed side by side so their point clouds do not overlap) or any scene folder.

use crate::page::View;
use dens3r_geom::{PinholeCamera, Raster};
use dens3r_scene::{Scene, SceneError};
use glam::{DVec3, Vec3};
use image::RgbImage;

/// The longest side of the maps a page is made from.
pub const MAX_SIDE: usize = 512;

/// Every `step`-th pixel of `r` both ways, starting at `step / 2` (the block's centre pixel).
fn every<T: Clone>(r: &Raster<T>, step: usize) -> Raster<T> {
    if step <= 1 {
        return r.clone();
    }
    Raster::from_fn(r.width() / step, r.height() / step, |x, y| r.get(x * step + step / 2, y * step + step / 2).clone())
}

/// A scene folder's frames read into memory.
#[derive(Debug, Clone, Default)]
pub struct SceneViews {
    /// Frame names.
    pub names: Vec<String>,
    /// Cameras.
    pub cameras: Vec<PinholeCamera>,
    /// Images, resized to their depth's size where they differ.
    pub rgb: Vec<RgbImage>,
    /// Depth (frames without depth are left out).
    pub depth: Vec<Raster<f32>>,
    /// Confidence, where written.
    pub conf: Vec<Option<Raster<f32>>>,
    /// Normals, where written.
    pub normals: Vec<Option<Raster<Vec3>>>,
    /// Images relative to the page: `prefix` + the frame's image path.
    pub photos: Vec<String>,
}

impl SceneViews {
    /// Reads the frames of `scene` that have depth, each map kept at most [`MAX_SIDE`] pixels
    /// long (every s-th pixel, the camera to match: a page needs no more, and a hundred
    /// 12-megapixel frames would not fit in memory); `prefix` is the scene folder's path from
    /// the page (`""` when the page is in the scene folder, `"scene/"` beside it).
    pub fn read(scene: &Scene, prefix: &str) -> Result<SceneViews, SceneError> {
        let mut s = SceneViews::default();
        for f in scene.frames() {
            let Some(depth) = scene.depth(f)? else { continue };
            let (w, h) = (depth.width(), depth.height());
            let mut rgb = scene.image(f)?;
            if (rgb.width() as usize, rgb.height() as usize) != (w, h) {
                rgb = image::imageops::resize(&rgb, w as u32, h as u32, image::imageops::FilterType::Triangle);
            }
            let step = w.max(h).div_ceil(MAX_SIDE).max(1);
            let mut camera = f.camera();
            if step > 1 {
                // Pixel x' of the result is pixel x' s + s / 2 of the frame (centres at integers).
                let (k, s_, half) = (&mut camera.intrinsics, step as f64, (step / 2) as f64);
                (k.fx, k.fy, k.cx, k.cy) = (k.fx / s_, k.fy / s_, (k.cx - half) / s_, (k.cy - half) / s_);
                (camera.width, camera.height) = (w / step, h / step);
            }
            // The same pixels as the maps' (see `every`).
            let (st, half) = (step as u32, (step / 2) as u32);
            let rgb = RgbImage::from_fn((w / step) as u32, (h / step) as u32, |x, y| {
                *rgb.get_pixel(x * st + half, y * st + half)
            });
            s.names.push(f.name.clone());
            s.cameras.push(camera);
            s.rgb.push(rgb);
            s.conf.push(scene.conf(f)?.map(|c| every(&c, step)));
            s.normals.push(scene.normals(f)?.map(|n| every(&n, step)));
            s.depth.push(every(&depth, step));
            s.photos.push(format!("{prefix}{}", f.image));
        }
        Ok(s)
    }

    /// Moves each camera along x so that the views' point clouds sit side by side, in order
    /// (for photos predicted one by one, which all sit at the origin).
    pub fn side_by_side(&mut self) {
        let mut x = 0.0;
        for (cam, d) in self.cameras.iter_mut().zip(&self.depth) {
            let mut z: Vec<f32> = d.data().iter().copied().filter(|z| z.is_finite() && *z > 0.0).collect();
            z.sort_by(f32::total_cmp);
            let median = z.get(z.len() / 2).copied().unwrap_or(1.0) as f64;
            let width = median * cam.width as f64 / cam.intrinsics.fx;
            cam.cam_to_world.w_axis += DVec3::new(x + width / 2.0, 0.0, 0.0).extend(0.0);
            x += width * 1.3;
        }
    }

    /// The views the page shows.
    pub fn views(&self) -> Vec<View<'_>> {
        (0..self.names.len())
            .map(|k| View {
                name: &self.names[k],
                camera: self.cameras[k],
                rgb: &self.rgb[k],
                depth: &self.depth[k],
                conf: self.conf[k].as_ref(),
                normals: self.normals[k].as_ref(),
                mask: None,
                photo: Some(self.photos[k].clone()),
            })
            .collect()
    }
}

/// Writes the page of the scene folder `dir/scene_prefix` into `dir`, its views side by side
/// when `side_by_side` (photos predicted one by one).
pub fn write_scene_page(
    dir: &std::path::Path,
    scene_prefix: &str,
    title: &str,
    summary: Option<serde_json::Value>,
    side_by_side: bool,
    opts: &crate::PageOptions,
) -> Result<crate::PageSummary, SceneError> {
    let scene = Scene::open(&dir.join(scene_prefix))?;
    let mut views = SceneViews::read(&scene, scene_prefix)?;
    if side_by_side {
        views.side_by_side();
    }
    let page = crate::Page { title: title.into(), views: views.views(), summary, min_conf: 0.0, ..Default::default() };
    crate::write_page(dir, &page, opts)
}
