//! Opening and reading a scene folder.

use crate::cameras::{CamerasFile, Frame};
use crate::error::SceneError;
use crate::npy;
use dens3r_geom::{Raster, Vec3};
use dens3r_mesh::TriMesh;
use image::RgbImage;
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};

/// A per-frame layer of a scene folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Layer {
    /// `depth/<name>.npy`, float32 HxW.
    Depth,
    /// `normals/<name>.npy`, float32 HxWx3.
    Normals,
    /// `conf/<name>.npy`, float32 HxW.
    Conf,
    /// `masks/<name>.png`, 8-bit, 0 = ignore.
    Mask,
    /// `labels/<name>.png`, semantic ids.
    Labels,
    /// `instances/<name>.png`, instance ids.
    Instances,
}

impl Layer {
    /// Every layer.
    pub const ALL: [Layer; 6] =
        [Layer::Depth, Layer::Normals, Layer::Conf, Layer::Mask, Layer::Labels, Layer::Instances];

    /// Folder and extension of the layer's files.
    pub fn location(self) -> (&'static str, &'static str) {
        match self {
            Layer::Depth => ("depth", "npy"),
            Layer::Normals => ("normals", "npy"),
            Layer::Conf => ("conf", "npy"),
            Layer::Mask => ("masks", "png"),
            Layer::Labels => ("labels", "png"),
            Layer::Instances => ("instances", "png"),
        }
    }

    /// Path of this layer's file for frame `name` under `root`.
    pub fn path(self, root: &Path, name: &str) -> PathBuf {
        let (dir, ext) = self.location();
        root.join(dir).join(format!("{name}.{ext}"))
    }
}

/// A validated scene folder.
#[derive(Debug, Clone)]
pub struct Scene {
    root: PathBuf,
    cameras: CamerasFile,
}

impl Scene {
    /// Opens and validates `dir`: `cameras.json` must parse, use the `opencv` convention, list
    /// at least one frame with a unique name, a valid `K` and a rigid pose, and every image
    /// file must exist.
    pub fn open(dir: &Path) -> Result<Scene, SceneError> {
        if !dir.is_dir() {
            return Err(SceneError::new(
                dir,
                "scene folder not found (make one with `dens3r render`, see docs/scene-format.md)",
            ));
        }
        let cam_path = dir.join("cameras.json");
        if !cam_path.is_file() {
            return Err(SceneError::new(
                &cam_path,
                "missing: a scene folder needs cameras.json (see docs/scene-format.md)",
            ));
        }
        let text =
            std::fs::read_to_string(&cam_path).map_err(|e| SceneError::new(&cam_path, format!("cannot read: {e}")))?;
        let cameras: CamerasFile = serde_json::from_str(&text)
            .map_err(|e| SceneError::new(&cam_path, format!("invalid cameras.json: {e} (see docs/scene-format.md)")))?;
        if cameras.convention != "opencv" {
            return Err(SceneError::new(
                &cam_path,
                format!("convention '{}' is not supported: store OpenCV camera-to-world poses and set \"convention\": \"opencv\"", cameras.convention),
            ));
        }
        if cameras.frames.is_empty() {
            return Err(SceneError::new(&cam_path, "no frames listed: a scene needs at least one view"));
        }
        let mut names = HashSet::new();
        for f in &cameras.frames {
            f.check().map_err(|m| SceneError::new(&cam_path, m.0))?;
            if !names.insert(f.name.as_str()) {
                return Err(SceneError::new(
                    &cam_path,
                    format!("frame name '{}' is used twice; names must be unique", f.name),
                ));
            }
            let img = dir.join(&f.image);
            if !img.is_file() {
                return Err(SceneError::new(
                    &img,
                    format!("image of frame '{}' is missing (listed in cameras.json)", f.name),
                ));
            }
        }
        Ok(Scene { root: dir.to_path_buf(), cameras })
    }

    /// The scene folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The parsed `cameras.json`.
    pub fn cameras(&self) -> &CamerasFile {
        &self.cameras
    }

    /// The frames, in file order.
    pub fn frames(&self) -> &[Frame] {
        &self.cameras.frames
    }

    /// The frame called `name`.
    pub fn frame(&self, name: &str) -> Option<&Frame> {
        self.cameras.frames.iter().find(|f| f.name == name)
    }

    /// True when frame `f` has a file for `layer`.
    pub fn has(&self, f: &Frame, layer: Layer) -> bool {
        layer.path(&self.root, &f.name).is_file()
    }

    /// The RGB image of a frame (decoded; other colour types are converted).
    pub fn image(&self, f: &Frame) -> Result<RgbImage, SceneError> {
        let path = self.root.join(&f.image);
        let img = image::open(&path)
            .map_err(|e| SceneError::new(&path, format!("unreadable image ({e}); re-save it as PNG or JPEG")))?;
        check_size(&path, f, img.width() as usize, img.height() as usize)?;
        Ok(img.to_rgb8())
    }

    /// Depth of a frame, if present.
    pub fn depth(&self, f: &Frame) -> Result<Option<Raster<f32>>, SceneError> {
        self.read_scalar(f, Layer::Depth)
    }

    /// Confidence of a frame, if present.
    pub fn conf(&self, f: &Frame) -> Result<Option<Raster<f32>>, SceneError> {
        self.read_scalar(f, Layer::Conf)
    }

    /// Normals of a frame (OpenCV camera frame, facing the camera), if present.
    pub fn normals(&self, f: &Frame) -> Result<Option<Raster<Vec3>>, SceneError> {
        let path = Layer::Normals.path(&self.root, &f.name);
        if !path.is_file() {
            return Ok(None);
        }
        let (shape, data) = npy::read_f32(&path)?;
        if shape != [f.height, f.width, 3] {
            return Err(SceneError::new(
                &path,
                format!("shape {shape:?} should be [{}, {}, 3] (HxWx3) for frame '{}'", f.height, f.width, f.name),
            ));
        }
        let v: Vec<Vec3> = data.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect();
        Ok(Some(Raster::from_vec(f.width, f.height, v).expect("shape checked")))
    }

    /// Mask of a frame (`true` = use), if present.
    pub fn mask(&self, f: &Frame) -> Result<Option<Raster<bool>>, SceneError> {
        Ok(self.read_ids(f, Layer::Mask)?.map(|m| m.map(|v| *v != 0)))
    }

    /// Semantic labels of a frame, if present.
    pub fn labels(&self, f: &Frame) -> Result<Option<Raster<u16>>, SceneError> {
        self.read_ids(f, Layer::Labels)
    }

    /// Instance ids of a frame, if present.
    pub fn instances(&self, f: &Frame) -> Result<Option<Raster<u16>>, SceneError> {
        self.read_ids(f, Layer::Instances)
    }

    /// Class names from `classes.json` (id -> name), empty when absent.
    pub fn classes(&self) -> Result<BTreeMap<u16, String>, SceneError> {
        let path = self.root.join("classes.json");
        if !path.is_file() {
            return Ok(BTreeMap::new());
        }
        crate::read_classes(&path)
    }

    /// The ground-truth mesh `gt_mesh.ply`, if present.
    pub fn gt_mesh(&self) -> Result<Option<TriMesh>, SceneError> {
        let path = self.root.join("gt_mesh.ply");
        if !path.is_file() {
            return Ok(None);
        }
        Ok(Some(dens3r_mesh::read_mesh(&path)?))
    }

    fn read_scalar(&self, f: &Frame, layer: Layer) -> Result<Option<Raster<f32>>, SceneError> {
        let path = layer.path(&self.root, &f.name);
        if !path.is_file() {
            return Ok(None);
        }
        let (shape, data) = npy::read_f32(&path)?;
        if shape != [f.height, f.width] {
            return Err(SceneError::new(
                &path,
                format!("shape {shape:?} should be [{}, {}] (HxW) for frame '{}'", f.height, f.width, f.name),
            ));
        }
        Ok(Some(Raster::from_vec(f.width, f.height, data).expect("shape checked")))
    }

    fn read_ids(&self, f: &Frame, layer: Layer) -> Result<Option<Raster<u16>>, SceneError> {
        let path = layer.path(&self.root, &f.name);
        if !path.is_file() {
            return Ok(None);
        }
        let ids = read_grey_png(&path, "ids")?;
        check_size(&path, f, ids.width(), ids.height())?;
        Ok(Some(ids))
    }
}

/// A single-channel 8- or 16-bit PNG's values as they are (ids, masks, Middlebury's disparity);
/// `what` names its content in the error.
pub(crate) fn read_grey_png(path: &Path, what: &str) -> Result<Raster<u16>, SceneError> {
    let img = image::open(path).map_err(|e| SceneError::new(path, format!("unreadable PNG ({e})")))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let values = match img {
        image::DynamicImage::ImageLuma8(g) => g.into_raw().into_iter().map(u16::from).collect(),
        image::DynamicImage::ImageLuma16(g) => g.into_raw(),
        other => {
            return Err(SceneError::new(
                path,
                format!("must be a single-channel (grey) 8- or 16-bit PNG of {what}, got {:?}", other.color()),
            ));
        }
    };
    Ok(Raster::from_vec(w, h, values).expect("the image's own size"))
}

fn check_size(path: &Path, f: &Frame, w: usize, h: usize) -> Result<(), SceneError> {
    if (w, h) != (f.width, f.height) {
        return Err(SceneError::new(
            path,
            format!("is {w}x{h} but cameras.json says {}x{} for frame '{}'", f.width, f.height, f.name),
        ));
    }
    Ok(())
}
