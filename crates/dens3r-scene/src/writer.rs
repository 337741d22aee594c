//! Writing a scene folder.

use crate::cameras::{CamerasFile, Frame};
use crate::error::SceneError;
use crate::npy;
use crate::reader::Layer;
use dens3r_geom::{Raster, Vec3};
use dens3r_io::output::OutputDir;
use dens3r_io::write_atomic;
use dens3r_mesh::TriMesh;
use image::{ImageEncoder, RgbImage};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Writes a scene folder file by file (each atomically); [`SceneWriter::finish`] writes
/// `cameras.json` last.
///
/// [`SceneWriter::create`] writes the scene as one transaction ([`dens3r_io::output`]): every
/// file is staged and moved into the folder only by `finish`, so a failure or a stop leaves the
/// folder as it was; an earlier scene there (which may hold this run's inputs) stays intact and
/// readable until then, its files that the new scene does not write are removed, and files of
/// the user's beside it are never touched. [`SceneWriter::in_folder`] writes a scene inside an
/// output the caller stages itself.
#[derive(Debug)]
pub struct SceneWriter {
    root: PathBuf,
    /// The transaction this writer owns (`create`), finished by `finish`.
    out: Option<OutputDir>,
    frames: Vec<Frame>,
    extra: serde_json::Map<String, serde_json::Value>,
}

/// Whether `dir` holds a scene folder (its `cameras.json`).
pub fn holds_scene(dir: &Path) -> bool {
    dir.join("cameras.json").is_file()
}

/// Starts the output folder `dir` of a command that writes scenes there (its lock taken, its
/// outputs staged; see [`OutputDir`]). Only files its manifest lists, unchanged since, are
/// dens3r's: a scene written by hand or by another tool is never replaced.
pub fn begin_output(dir: &Path) -> Result<OutputDir, SceneError> {
    Ok(OutputDir::begin(dir)?)
}

impl SceneWriter {
    /// Starts a scene in `dir` (created if missing), staged until `finish`; fails, naming
    /// `dir`, when another run is writing it.
    pub fn create(dir: &Path) -> Result<Self, SceneError> {
        let out = begin_output(dir)?;
        let root = out.root().to_path_buf();
        Ok(Self { root, out: Some(out), frames: Vec::new(), extra: Default::default() })
    }

    /// Starts a scene in `dir` inside an output the caller stages (the caller's staging
    /// folder or a subfolder of it); `finish` only writes `cameras.json`.
    pub fn in_folder(dir: &Path) -> Result<Self, SceneError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| SceneError::new(dir, format!("cannot create the scene folder: {e}")))?;
        Ok(Self { root: dir.to_path_buf(), out: None, frames: Vec::new(), extra: Default::default() })
    }

    /// The folder being written: the staging folder of `create`, the folder of `in_folder`
    /// (write every other file of the scene here too).
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Adds a top-level key to `cameras.json` (e.g. provenance).
    pub fn set_extra(&mut self, key: &str, value: serde_json::Value) {
        self.extra.insert(key.to_string(), value);
    }

    /// Adds a frame and writes its image (PNG at `frame.image`).
    pub fn add_frame(&mut self, frame: Frame, rgb: &RgbImage) -> Result<(), SceneError> {
        let cam = self.root.join("cameras.json");
        frame.check().map_err(|m| SceneError::new(&cam, m.0))?;
        if self.frames.iter().any(|f| f.name == frame.name) {
            return Err(SceneError::new(&cam, format!("frame name '{}' added twice", frame.name)));
        }
        let path = self.root.join(&frame.image);
        self.check_size(&path, &frame, rgb.width() as usize, rgb.height() as usize)?;
        write_png(&path, rgb.as_raw(), rgb.width(), rgb.height(), image::ExtendedColorType::Rgb8)?;
        self.frames.push(frame);
        Ok(())
    }

    /// Writes `depth/<name>.npy`.
    pub fn write_depth(&self, name: &str, depth: &Raster<f32>) -> Result<(), SceneError> {
        self.write_scalar(name, Layer::Depth, depth)
    }

    /// Writes `conf/<name>.npy`.
    pub fn write_conf(&self, name: &str, conf: &Raster<f32>) -> Result<(), SceneError> {
        self.write_scalar(name, Layer::Conf, conf)
    }

    /// Writes `normals/<name>.npy` (OpenCV camera frame, facing the camera).
    pub fn write_normals(&self, name: &str, normals: &Raster<Vec3>) -> Result<(), SceneError> {
        let (path, f) = self.target(name, Layer::Normals)?;
        self.check_size(&path, f, normals.width(), normals.height())?;
        let flat: Vec<f32> = normals.data().iter().flat_map(|n| n.to_array()).collect();
        npy::write_f32(&path, &[f.height, f.width, 3], &flat)
    }

    /// Writes `masks/<name>.png` (255 where `true`).
    pub fn write_mask(&self, name: &str, mask: &Raster<bool>) -> Result<(), SceneError> {
        let (path, f) = self.target(name, Layer::Mask)?;
        self.check_size(&path, f, mask.width(), mask.height())?;
        let px: Vec<u8> = mask.data().iter().map(|&m| if m { 255 } else { 0 }).collect();
        write_png(&path, &px, f.width as u32, f.height as u32, image::ExtendedColorType::L8)
    }

    /// Writes `labels/<name>.png` (8-bit when every id fits, else 16-bit).
    pub fn write_labels(&self, name: &str, labels: &Raster<u16>) -> Result<(), SceneError> {
        self.write_ids(name, Layer::Labels, labels)
    }

    /// Writes `instances/<name>.png` (8-bit when every id fits, else 16-bit).
    pub fn write_instances(&self, name: &str, ids: &Raster<u16>) -> Result<(), SceneError> {
        self.write_ids(name, Layer::Instances, ids)
    }

    /// Writes `classes.json`.
    pub fn write_classes(&self, classes: &BTreeMap<u16, String>) -> Result<(), SceneError> {
        crate::write_classes(&self.root.join("classes.json"), classes)
    }

    /// Writes the ground-truth mesh `gt_mesh.ply` (world coordinates).
    pub fn write_gt_mesh(&self, mesh: &TriMesh) -> Result<(), SceneError> {
        Ok(dens3r_mesh::write_mesh(&self.root.join("gt_mesh.ply"), mesh)?)
    }

    /// Writes `cameras.json`, completing the scene; returns its path.
    pub fn finish(mut self) -> Result<PathBuf, SceneError> {
        let path = self.root.join("cameras.json");
        if self.frames.is_empty() {
            return Err(SceneError::new(&path, "no frames were added; nothing to write"));
        }
        let file = CamerasFile {
            convention: "opencv".into(),
            frames: std::mem::take(&mut self.frames),
            extra: std::mem::take(&mut self.extra),
        };
        let text = serde_json::to_string_pretty(&file).expect("cameras serialise");
        write_atomic(&path, |w| std::io::Write::write_all(w, text.as_bytes()))?;
        match self.out.take() {
            Some(out) => Ok(out.finish()?.join("cameras.json")),
            None => Ok(path),
        }
    }

    fn target(&self, name: &str, layer: Layer) -> Result<(PathBuf, &Frame), SceneError> {
        let path = layer.path(&self.root, name);
        let f = self.frames.iter().find(|f| f.name == name).ok_or_else(|| {
            SceneError::new(&path, format!("frame '{name}' must be added (add_frame) before its layers"))
        })?;
        Ok((path, f))
    }

    fn check_size(&self, path: &Path, f: &Frame, w: usize, h: usize) -> Result<(), SceneError> {
        if (w, h) != (f.width, f.height) {
            return Err(SceneError::new(
                path,
                format!("data is {w}x{h} but frame '{}' is {}x{}", f.name, f.width, f.height),
            ));
        }
        Ok(())
    }

    fn write_scalar(&self, name: &str, layer: Layer, r: &Raster<f32>) -> Result<(), SceneError> {
        let (path, f) = self.target(name, layer)?;
        self.check_size(&path, f, r.width(), r.height())?;
        npy::write_f32(&path, &[f.height, f.width], r.data())
    }

    fn write_ids(&self, name: &str, layer: Layer, ids: &Raster<u16>) -> Result<(), SceneError> {
        let (path, f) = self.target(name, layer)?;
        self.check_size(&path, f, ids.width(), ids.height())?;
        write_id_png(&path, ids.data(), f.width as u32, f.height as u32)
    }
}

/// Writes per-pixel ids as a grey PNG atomically: 8-bit when every id fits, else 16-bit.
pub fn write_id_png(path: &Path, ids: &[u16], w: u32, h: u32) -> Result<(), SceneError> {
    if ids.iter().all(|&v| v <= 255) {
        let px: Vec<u8> = ids.iter().map(|&v| v as u8).collect();
        write_png(path, &px, w, h, image::ExtendedColorType::L8)
    } else {
        // PNG stores 16-bit samples big-endian; the encoder takes native-endian bytes.
        let px: Vec<u8> = ids.iter().flat_map(|v| v.to_ne_bytes()).collect();
        write_png(path, &px, w, h, image::ExtendedColorType::L16)
    }
}

/// Encodes a PNG in memory, then writes it atomically.
/// Writes an RGB image as PNG atomically (visualisations and other extra pictures).
pub fn write_rgb_png(path: &Path, img: &RgbImage) -> Result<(), SceneError> {
    write_png(path, img.as_raw(), img.width(), img.height(), image::ExtendedColorType::Rgb8)
}

pub(crate) fn write_png(
    path: &Path,
    px: &[u8],
    w: u32,
    h: u32,
    color: image::ExtendedColorType,
) -> Result<(), SceneError> {
    let mut buf = Vec::new();
    image::codecs::png::PngEncoder::new(&mut buf)
        .write_image(px, w, h, color)
        .map_err(|e| SceneError::new(path, format!("cannot encode PNG: {e}")))?;
    write_atomic(path, |f| std::io::Write::write_all(f, &buf))?;
    Ok(())
}
