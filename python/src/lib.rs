//! `dens3r._native`: the Python module behind the `dens3r` package (python/dens3r). Arrays go
//! out as NumPy arrays that own the Rust buffers (no copy); arrays in are copied once into the
//! Rust types that own their pixels (images, rasters). Long calls release the GIL. Every error
//! is a `dens3r.Dens3rError` (or a `ValueError` / `TypeError` for arrays of the wrong shape or
//! type) with the one-line message the CLI prints.

use dens3r_backbone::predict::{predict_mono, predict_pair, Resolution, TestTimePasses, ViewMaps};
use dens3r_backbone::preprocess::{open_oriented, preprocess, Prepared};
use dens3r_fusion::extract::{extract_mesh, ExtractOptions};
use dens3r_fusion::scene::{fuse_frames, FusionFrame, SceneFusion};
use dens3r_fusion::tsdf::TsdfParams;
use dens3r_geom::{DMat4, Intrinsics, PinholeCamera, Raster, Vec3};
use dens3r_heads::{Backbone, Dens3rBackbone};
use dens3r_mesh::TriMesh;
use dens3r_recon::mono::{mono_camera_known, FocalSource};
use dens3r_scene::{Frame, Scene, SceneWriter};
use image::{DynamicImage, RgbImage};
use numpy::ndarray::{ArrayD, IxDyn};
use numpy::{IntoPyArray, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyException, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::borrow::Cow;
use std::path::{Path, PathBuf};

pyo3::create_exception!(
    dens3r,
    Dens3rError,
    PyException,
    "A dens3r operation failed: the message names the file or setting and what to do."
);

/// Any displayable error as a `Dens3rError`.
fn err(e: impl std::fmt::Display) -> PyErr {
    Dens3rError::new_err(e.to_string())
}

/// A NumPy array of `shape` owning `data` (no copy).
fn array<'py, T: numpy::Element>(py: Python<'py>, data: Vec<T>, shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    let a = ArrayD::from_shape_vec(IxDyn(shape), data).map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py).into_any())
}

fn vec3_array<'py>(py: Python<'py>, r: &Raster<Vec3>) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<f32> = r.data().iter().flat_map(|v| v.to_array()).collect();
    array(py, flat, &[r.height(), r.width(), 3])
}

fn scalar_array<'py>(py: Python<'py>, r: &Raster<f32>) -> PyResult<Bound<'py, PyAny>> {
    array(py, r.data().to_vec(), &[r.height(), r.width()])
}

fn rgb_array<'py>(py: Python<'py>, img: &RgbImage) -> PyResult<Bound<'py, PyAny>> {
    array(py, img.as_raw().clone(), &[img.height() as usize, img.width() as usize, 3])
}

fn k_array<'py>(py: Python<'py>, i: &Intrinsics) -> PyResult<Bound<'py, PyAny>> {
    array(py, vec![i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0], &[3, 3])
}

/// An array's values (copied once, in C order) with its shape; `what` names the
/// argument in errors.
fn values<T: numpy::Element + Copy>(a: &Bound<'_, PyAny>, what: &str, want: &str) -> PyResult<(Vec<T>, Vec<usize>)> {
    let arr: PyReadonlyArrayDyn<T> = a.extract().map_err(|_| {
        let dtype = match std::any::type_name::<T>() {
            "u8" => "uint8",
            "f32" => "float32",
            "f64" => "float64",
            other => other,
        };
        let given = match a.getattr("dtype") {
            Ok(d) => format!("an array of {d}"),
            Err(_) => a.get_type().name().map(|n| n.to_string()).unwrap_or_default(),
        };
        PyTypeError::new_err(format!("{what}: expected a NumPy {dtype} array of {want}; got {given}"))
    })?;
    let shape = arr.shape().to_vec();
    let v = match arr.as_slice() {
        Ok(s) => s.to_vec(),
        Err(_) => arr.as_array().iter().copied().collect(),
    };
    Ok((v, shape))
}

/// An image argument: a path (EXIF orientation applied) or an `(H, W, 3)` uint8 array.
fn image_arg(obj: &Bound<'_, PyAny>) -> PyResult<DynamicImage> {
    if let Ok(p) = obj.extract::<PathBuf>() {
        return open_oriented(&p).map_err(err);
    }
    let (v, shape) = values::<u8>(obj, "image", "shape (H, W, 3), or a path")?;
    if shape.len() != 3 || shape[2] != 3 || shape[0] == 0 || shape[1] == 0 {
        return Err(PyValueError::new_err(format!(
            "image: expected shape (H, W, 3) with RGB uint8 values, got {shape:?} (drop an alpha channel with img[..., :3])"
        )));
    }
    let img = RgbImage::from_raw(shape[1] as u32, shape[0] as u32, v).expect("sizes checked");
    Ok(DynamicImage::ImageRgb8(img))
}

fn raster<T>(w: usize, h: usize, v: Vec<T>, what: &str) -> PyResult<Raster<T>> {
    Raster::from_vec(w, h, v).map_err(|e| PyValueError::new_err(format!("{what}: {e}")))
}

/// A frozen Dens3R network: its predictions and the features heads train on.
#[pyclass(frozen, module = "dens3r")]
struct Model {
    /// Boxed: the network holds over-aligned (cache-line) values, and Python allocates objects
    /// at 16 bytes.
    net: Box<Dens3rBackbone>,
    /// The checkpoint file.
    #[pyo3(get)]
    weights: PathBuf,
    /// The config beside the checkpoint, if any (keys the pair cache with the weights).
    config: Option<PathBuf>,
    /// Long side of the network input.
    #[pyo3(get)]
    size: u32,
    keep_portrait: bool,
    /// The extra passes a single image's prediction averages in (the config's `"tta_scales"`
    /// times `size`, dens3r-s: 0.75; mirrored by its `"tta_mirror"`, dens3r-s: true).
    tta: TestTimePasses,
    /// The line shown when this is the bundled default model (how to use the official
    /// checkpoints instead); None for other weights.
    #[pyo3(get)]
    notice: Option<String>,
    /// The confidence under which `reconstruct` fuses no pixel by default (the config's
    /// `"min_conf"`, else 3).
    #[pyo3(get)]
    min_conf: f32,
}

impl Model {
    /// The network's id in the pair cache (its files' content and input size), as the CLI's.
    fn cache_id(&self, cache: &dens3r_recon::PairCache) -> Result<String, dens3r_io::IoError> {
        dens3r_recon::predictor::network_cache_id(&self.weights, self.config.as_deref(), cache, self.size, "")
    }

    fn prepare(&self, obj: &Bound<'_, PyAny>) -> PyResult<Prepared> {
        self.prepare_image(&image_arg(obj)?)
    }

    fn prepare_image(&self, img: &DynamicImage) -> PyResult<Prepared> {
        preprocess(img, self.size, !self.keep_portrait).map_err(err)
    }
}

/// One view's maps as a dict; `own_frame`: its points are in its own camera's frame, so its
/// depth and intrinsics are meaningful; `known`: a focal (pixels of the maps) its camera takes.
fn view_dict<'py>(py: Python<'py>, v: &ViewMaps, own_frame: bool, known: Option<f64>) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("rgb", rgb_array(py, &v.rgb)?)?;
    d.set_item("pts3d", vec3_array(py, &v.points)?)?;
    d.set_item("frame", v.frame)?;
    if own_frame {
        d.set_item("depth", scalar_array(py, &v.depth)?)?;
        let (cam, source) = mono_camera_known(v, known.map(|f| (f, FocalSource::Given)));
        d.set_item("K", k_array(py, &cam.intrinsics)?)?;
        d.set_item("focal_estimated", source == FocalSource::Pointmap)?;
        d.set_item("focal_source", source.as_str())?;
    }
    if let Some(n) = &v.normals {
        d.set_item("normals", vec3_array(py, n)?)?;
    }
    if let Some(c) = &v.conf {
        d.set_item("conf", scalar_array(py, c)?)?;
    }
    if let Some(m) = &v.desc {
        d.set_item("desc", array(py, m.data.clone(), &[m.height, m.width, m.dim])?)?;
    }
    if let Some(c) = &v.desc_conf {
        d.set_item("desc_conf", scalar_array(py, c)?)?;
    }
    Ok(d)
}

#[pymethods]
impl Model {
    /// Loads a network: `weights` is a `.safetensors` / `.pth` checkpoint, a Hugging Face
    /// style folder, a known name (`dens3r models`; downloaded into the cache when missing),
    /// or None for the bundled dens3r-s. `size` is the long side of the network input;
    /// `precision` what the network computes in ("f32", or "f16" / "bf16" for speed on a GPU;
    /// "bf16" on a CPU with AVX-512 BF16 too: its linear layers' and attention's products in bf16).
    /// Portrait photos are turned to landscape as the official Dens3R does, unless
    /// `keep_portrait` or the model's config says `"keep_portrait": true` (dens3r-s's does).
    /// A single image's prediction averages in passes at the config's `"tta_scales"` of
    /// `size` (dens3r-s: 0.75), as `dens3r predict` does; `predict(..., tta=False)` skips them.
    #[staticmethod]
    #[pyo3(signature = (weights=None, *, config=None, size=512, keep_portrait=false, gpu=false, precision="f32"))]
    fn load(
        py: Python<'_>,
        weights: Option<PathBuf>,
        config: Option<PathBuf>,
        size: u32,
        keep_portrait: bool,
        gpu: bool,
        precision: &str,
    ) -> PyResult<Model> {
        let precision: dens3r_backbone::Precision =
            precision.parse().map_err(|e: String| PyValueError::new_err(format!("precision={precision:?}: {e}")))?;
        let sizes = dens3r_backbone::preprocess::SIZES;
        if !sizes.contains(&size) {
            return Err(PyValueError::new_err(format!(
                "size={size}: the network input's long side must be in {sizes:?} (512, or 1024 for more detail)"
            )));
        }
        py.detach(|| {
            let files = dens3r_recon::model::resolve(weights.as_deref(), config.as_deref(), &mut |k| {
                dens3r_recon::model::fetch_known(k, &mut |line| eprintln!("{line}"), &mut |_, _| {})
            })
            .map_err(err)?;
            let (model, _) = dens3r_recon::model::load_network(&files.weights, files.config.as_deref(), gpu, precision)
                .map_err(err)?;
            let hash = dens3r_heads::features::file_hash(&files.weights).map_err(err)?;
            let net = Dens3rBackbone::new(model, None, hash).map_err(err)?;
            let settings = dens3r_recon::model::model_settings(files.config.as_deref()).map_err(err)?;
            let sizes = dens3r_recon::model::tta_sizes(&settings.tta_scales, size).map_err(err)?;
            Ok(Model {
                tta: TestTimePasses { sizes, mirrored: settings.tta_mirror },
                net: Box::new(net),
                weights: files.weights,
                config: files.config,
                size,
                keep_portrait: keep_portrait || settings.keep_portrait,
                notice: files.default_notice,
                min_conf: settings.min_conf,
            })
        })
    }

    /// Pixels per feature token.
    #[getter]
    fn patch(&self) -> usize {
        self.net.patch()
    }

    /// Channels of each feature layer [`Model::features`] returns.
    #[getter]
    fn feature_dims(&self) -> Vec<usize> {
        self.net.dims()
    }

    /// Identity of the features (checkpoint hash and layers), as heads record it.
    #[getter]
    fn backbone_id(&self) -> String {
        self.net.id()
    }

    /// Predicts one image (its self-pair) or a pair. One image: a dict of `rgb` (H, W, 3)
    /// uint8, `depth` (H, W), `pts3d` and `normals` (H, W, 3, OpenCV camera frame, normals
    /// facing the camera), `conf`, `desc` (H, W, 24), `desc_conf`, `K` (3, 3) and
    /// `focal_estimated` and `focal_source` ("given", "pointmap" or "fallback", as `cameras.json`
    /// records it). A pair: a list of two such dicts, both pointmaps in the first camera's frame
    /// (the second view has no `depth` / `K`); normals each in their own camera frame. Maps are
    /// at the network size, or the photo's with `original_size=True`. `focal` (pixels of the
    /// photo as given) sets a single image's `K`, scaled to the maps, as `dens3r predict --focal`.
    /// A single image averages in the model's extra passes (its config's `"tta_scales"` and
    /// `"tta_mirror"`, as `dens3r predict`) unless `tta=False`; `tta_mirror=True` / `False`
    /// runs them over the mirrored photo or not, whatever the config says.
    #[pyo3(signature = (image, image2=None, *, original_size=false, focal=None, tta=true, tta_mirror=None))]
    #[allow(clippy::too_many_arguments)] // Python's keyword arguments, one parameter each
    fn predict<'py>(
        &self,
        py: Python<'py>,
        image: &Bound<'py, PyAny>,
        image2: Option<&Bound<'py, PyAny>>,
        original_size: bool,
        focal: Option<f64>,
        tta: bool,
        tta_mirror: Option<bool>,
    ) -> PyResult<Bound<'py, PyAny>> {
        if focal.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
            return Err(PyValueError::new_err("focal: must be a positive number of pixels of the photo"));
        }
        if focal.is_some() && image2.is_some() {
            return Err(PyValueError::new_err(
                "focal: applies to a single image, not a pair (use reconstruct(focal=...))",
            ));
        }
        let res = if original_size { Resolution::Original } else { Resolution::Network };
        // Decoded once for every pass.
        let img = image_arg(image)?;
        let first = self.prepare_image(&img)?;
        match image2 {
            None => {
                let passes = if tta {
                    TestTimePasses { mirrored: tta_mirror.unwrap_or(self.tta.mirrored), ..self.tta.clone() }
                } else {
                    TestTimePasses::default()
                };
                let extra = passes.prepare(&img, !self.keep_portrait).map_err(err)?;
                let pred = py.detach(|| {
                    let (model, all) = (self.net.model(), dens3r_backbone::HeadOutputs::ALL);
                    passes.merge(model, predict_mono(model, &first, res, all), res, &extra, all)
                });
                // Pixels of the maps: the photo's at original size, else scaled by the resize.
                let scale = if original_size { 1.0 } else { first.info.resize_factor() };
                Ok(view_dict(py, &pred, true, focal.map(|f| f * scale))?.into_any())
            }
            Some(i2) => {
                let second = self.prepare(i2)?;
                let [a, b] = py.detach(|| predict_pair(self.net.model(), &first, &second, res));
                Ok(PyList::new(py, [view_dict(py, &a, true, None)?, view_dict(py, &b, false, None)?])?.into_any())
            }
        }
    }

    /// The frozen features heads train on (what `dens3r train-head --backbone dens3r` caches):
    /// the image resized so its long side is `size` (sides multiples of the patch), run as its
    /// self-pair; a list of (C, h, w) float32 arrays, one per layer.
    #[pyo3(signature = (image, *, size=224))]
    fn features<'py>(&self, py: Python<'py>, image: &Bound<'py, PyAny>, size: u32) -> PyResult<Bound<'py, PyList>> {
        let patch = self.net.patch() as u32;
        if size < patch {
            return Err(PyValueError::new_err(format!("size={size}: must be at least the patch size {patch}")));
        }
        let img = image_arg(image)?.to_rgb8();
        let f = py.detach(|| {
            let img = dens3r_heads::data::resize_to_patches(img, size, patch);
            self.net.extract(&img)
        });
        let (h, w) = f.grid;
        let layers =
            f.layers.into_iter().zip(&f.dims).map(|(l, &d)| array(py, l, &[d, h, w])).collect::<PyResult<Vec<_>>>()?;
        PyList::new(py, layers)
    }

    /// The network's raw forward pass on two normalised image batches ((B, 3, H, W) float32,
    /// as the official code feeds it): a list of two dicts with the official output names and
    /// layouts (`pts3d`, view 2's `pts3d_in_other_view`, `conf`, `desc`, `desc_conf`, `normal`
    /// in Dens3R's raw convention), for parity checks against PyTorch dumps.
    fn forward<'py>(
        &self,
        py: Python<'py>,
        img1: &Bound<'py, PyAny>,
        img2: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyList>> {
        let batch = |a: &Bound<'py, PyAny>, what: &str| -> PyResult<(Vec<f32>, [usize; 4])> {
            let (v, s) = values::<f32>(a, what, "shape (B, 3, H, W)")?;
            match s[..] {
                [b, 3, h, w] if b > 0 && h > 0 && w > 0 => Ok((v, [b, 3, h, w])),
                _ => Err(PyValueError::new_err(format!("{what}: expected float32 (B, 3, H, W), got {s:?}"))),
            }
        };
        let (a, b) = (batch(img1, "img1")?, batch(img2, "img2")?);
        if a.1[0] != b.1[0] {
            return Err(PyValueError::new_err(format!(
                "img1 {:?} and img2 {:?}: the batch sizes must match",
                a.1, b.1
            )));
        }
        let pred = py.detach(|| {
            let dev = self.net.model().device();
            let t = |(v, s): (Vec<f32>, [usize; 4])| {
                burn::tensor::Tensor::<4>::from_data(burn::tensor::TensorData::new(v, s), dev)
            };
            self.net.model().forward(t(a), t(b))
        });
        fn out<'py, const D: usize>(py: Python<'py>, t: &burn::tensor::Tensor<D>) -> PyResult<Bound<'py, PyAny>> {
            let v = t.to_data().try_to_vec::<f32>().map_err(|e| err(format!("{e:?}")))?;
            array(py, v, &t.dims())
        }
        let views = pred
            .views
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let d = PyDict::new(py);
                d.set_item(if i == 0 { "pts3d" } else { "pts3d_in_other_view" }, out(py, &v.pts3d)?)?;
                if let Some(c) = &v.conf {
                    d.set_item("conf", out(py, c)?)?;
                }
                if let Some(c) = &v.desc {
                    d.set_item("desc", out(py, c)?)?;
                }
                if let Some(c) = &v.desc_conf {
                    d.set_item("desc_conf", out(py, c)?)?;
                }
                if let Some(c) = &v.normal {
                    d.set_item("normal", out(py, c)?)?;
                }
                Ok(d)
            })
            .collect::<PyResult<Vec<_>>>()?;
        PyList::new(py, views)
    }

    fn __repr__(&self) -> String {
        format!("Model(weights={:?}, size={})", self.weights.display().to_string(), self.size)
    }
}

/// A scene folder as arrays: `names`, `K` (N, 3, 3), `cam_to_world` (N, 4, 4, OpenCV
/// camera-to-world), `images` (list of (H, W, 3) uint8), and the layers each frame has:
/// `depth`, `normals` (camera frame), `conf` (lists with None where a frame has none).
#[pyfunction]
fn read_scene<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let scene = Scene::open(&path).map_err(err)?;
    let frames = scene.frames().to_vec();
    type Layers = (RgbImage, Option<Raster<f32>>, Option<Raster<Vec3>>, Option<Raster<f32>>);
    let layers: Vec<Layers> = py.detach(|| {
        frames
            .iter()
            .map(|f| Ok((scene.image(f)?, scene.depth(f)?, scene.normals(f)?, scene.conf(f)?)))
            .collect::<Result<Vec<_>, dens3r_scene::SceneError>>()
            .map_err(err)
    })?;
    let d = PyDict::new(py);
    let n = frames.len();
    d.set_item("path", path)?;
    d.set_item("names", frames.iter().map(|f| f.name.clone()).collect::<Vec<_>>())?;
    let ks: Vec<f64> = frames.iter().flat_map(|f| f.k.iter().flatten().copied().collect::<Vec<_>>()).collect();
    d.set_item("K", array(py, ks, &[n, 3, 3])?)?;
    let poses: Vec<f64> =
        frames.iter().flat_map(|f| f.cam_to_world.iter().flatten().copied().collect::<Vec<_>>()).collect();
    d.set_item("cam_to_world", array(py, poses, &[n, 4, 4])?)?;
    let (mut images, mut depth, mut normals, mut conf) = (vec![], vec![], vec![], vec![]);
    for (img, dp, nm, cf) in &layers {
        images.push(rgb_array(py, img)?);
        depth.push(dp.as_ref().map(|r| scalar_array(py, r)).transpose()?);
        normals.push(nm.as_ref().map(|r| vec3_array(py, r)).transpose()?);
        conf.push(cf.as_ref().map(|r| scalar_array(py, r)).transpose()?);
    }
    d.set_item("images", images)?;
    d.set_item("depth", depth)?;
    d.set_item("normals", normals)?;
    d.set_item("conf", conf)?;
    Ok(d)
}

/// A camera from a (3, 3) K, a (4, 4) camera-to-world pose and the image size.
fn camera(k: &[f64], pose: &[f64], width: usize, height: usize) -> PinholeCamera {
    PinholeCamera {
        intrinsics: Intrinsics { fx: k[0], fy: k[4], cx: k[2], cy: k[5] },
        width,
        height,
        cam_to_world: DMat4::from_cols_array(&pose.try_into().expect("16 values")).transpose(),
    }
}

/// Entry `i` of an optional per-frame list.
fn at<'py>(l: &Option<Vec<Option<Bound<'py, PyAny>>>>, i: usize) -> Option<Bound<'py, PyAny>> {
    l.as_ref().and_then(|v| v[i].clone())
}

/// Per-frame (3, 3) intrinsics and (4, 4) poses of `n` frames, checked.
fn cameras_arg(k: &Bound<'_, PyAny>, poses: &Bound<'_, PyAny>, n: usize) -> PyResult<(Vec<f64>, Vec<f64>)> {
    let (kv, ks) = values::<f64>(k, "K", "shape (N, 3, 3)")?;
    let (pv, ps) = values::<f64>(poses, "cam_to_world", "shape (N, 4, 4)")?;
    if ks != [n, 3, 3] || ps != [n, 4, 4] {
        return Err(PyValueError::new_err(format!(
            "K {ks:?} and cam_to_world {ps:?}: expected ({n}, 3, 3) and ({n}, 4, 4), one per frame"
        )));
    }
    Ok((kv, pv))
}

/// An (H, W) float32 map, or (H, W, 3) with `channels = 3`.
fn map_arg(a: &Bound<'_, PyAny>, what: &str, channels: usize) -> PyResult<(Vec<f32>, usize, usize)> {
    let want = if channels == 1 { "shape (H, W)" } else { "shape (H, W, 3)" };
    let (v, s) = values::<f32>(a, what, want)?;
    let ok = match channels {
        1 => s.len() == 2,
        c => s.len() == 3 && s[2] == c,
    };
    if !ok || s[0] == 0 || s[1] == 0 {
        return Err(PyValueError::new_err(format!("{what}: expected float32 {want}, got {s:?}")));
    }
    Ok((v, s[1], s[0]))
}

/// Writes a scene folder (`docs/scene-format.md`): images ((H, W, 3) uint8), `K` (N, 3, 3),
/// `cam_to_world` (N, 4, 4) and optional per-frame `depth`, `normals` (camera frame) and
/// `conf` lists. Files are written atomically and `cameras.json` last; a folder that already
/// holds a scene is refused unless `overwrite=True`. Returns the folder.
#[pyfunction]
#[pyo3(signature = (path, images, K, cam_to_world, *, depth=None, normals=None, conf=None, names=None, overwrite=false))]
#[allow(non_snake_case, clippy::too_many_arguments)]
fn write_scene(
    py: Python<'_>,
    path: PathBuf,
    images: Vec<Bound<'_, PyAny>>,
    K: &Bound<'_, PyAny>,
    cam_to_world: &Bound<'_, PyAny>,
    depth: Option<Vec<Option<Bound<'_, PyAny>>>>,
    normals: Option<Vec<Option<Bound<'_, PyAny>>>>,
    conf: Option<Vec<Option<Bound<'_, PyAny>>>>,
    names: Option<Vec<String>>,
    overwrite: bool,
) -> PyResult<PathBuf> {
    let n = images.len();
    if n == 0 {
        return Err(PyValueError::new_err("images: a scene needs at least one frame"));
    }
    if !overwrite && dens3r_scene::holds_scene(&path) {
        return Err(err(format!(
            "{}: already holds a scene (cameras.json); write to a new folder, or pass overwrite=True to replace it",
            path.display()
        )));
    }
    let (kv, pv) = cameras_arg(K, cam_to_world, n)?;
    let names = names.unwrap_or_else(|| (0..n).map(|i| format!("{i:05}")).collect());
    for (what, len) in [
        ("names", Some(names.len())),
        ("depth", depth.as_ref().map(Vec::len)),
        ("normals", normals.as_ref().map(Vec::len)),
        ("conf", conf.as_ref().map(Vec::len)),
    ] {
        if len.is_some_and(|l| l != n) {
            return Err(PyValueError::new_err(format!("{what}: {} entries for {n} images", len.unwrap_or(0))));
        }
    }
    let mut frames = Vec::with_capacity(n);
    for i in 0..n {
        let rgb = image_arg(&images[i])?.to_rgb8();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        let sized = |(v, ww, hh): (Vec<f32>, usize, usize), what: &str| {
            if (ww, hh) != (w, h) {
                return Err(PyValueError::new_err(format!(
                    "{what}[{i}]: {ww}x{hh}, but image {i} is {w}x{h}; maps must match their image"
                )));
            }
            Ok(v)
        };
        let dp = at(&depth, i).map(|a| map_arg(&a, "depth", 1).and_then(|m| sized(m, "depth"))).transpose()?;
        let nm = at(&normals, i).map(|a| map_arg(&a, "normals", 3).and_then(|m| sized(m, "normals"))).transpose()?;
        let cf = at(&conf, i).map(|a| map_arg(&a, "conf", 1).and_then(|m| sized(m, "conf"))).transpose()?;
        let cam = camera(&kv[9 * i..9 * i + 9], &pv[16 * i..16 * i + 16], w, h);
        let nm = nm.map(|v| v.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect::<Vec<_>>());
        frames.push((
            Frame::new(&names[i], &cam),
            rgb,
            dp.map(|v| raster(w, h, v, "depth")).transpose()?,
            nm.map(|v| raster(w, h, v, "normals")).transpose()?,
            cf.map(|v| raster(w, h, v, "conf")).transpose()?,
        ));
    }
    py.detach(|| {
        let mut writer = SceneWriter::create(&path)?;
        writer.set_extra("generator", serde_json::json!("dens3r (Python)"));
        for (frame, rgb, dp, nm, cf) in frames {
            let name = frame.name.clone();
            writer.add_frame(frame, &rgb)?;
            if let Some(d) = dp {
                writer.write_depth(&name, &d)?;
            }
            if let Some(nm) = nm {
                writer.write_normals(&name, &nm)?;
            }
            if let Some(c) = cf {
                writer.write_conf(&name, &c)?;
            }
        }
        writer.finish()
    })
    .map_err(err)
}

/// A mesh as a dict of `vertices` (V, 3) float32, `faces` (F, 3) int64 and, where present,
/// `normals` (V, 3) and `colors` (V, 3) uint8.
fn mesh_dict<'py>(py: Python<'py>, m: TriMesh) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let nv = m.positions.len();
    d.set_item("vertices", array(py, m.positions.iter().flat_map(|p| p.to_array()).collect(), &[nv, 3])?)?;
    let faces: Vec<i64> = m.indices.iter().flat_map(|t| t.map(i64::from)).collect();
    d.set_item("faces", array(py, faces, &[m.indices.len(), 3])?)?;
    if let Some(n) = &m.normals {
        d.set_item("normals", array(py, n.iter().flat_map(|p| p.to_array()).collect(), &[nv, 3])?)?;
    }
    if let Some(c) = &m.colors {
        d.set_item("colors", array(py, c.iter().flatten().copied().collect(), &[nv, 3])?)?;
    }
    Ok(d)
}

/// TSDF fusion of depth maps, with `dens3r fuse`'s defaults: `depths` (list of (H, W)
/// float32, 0 / NaN = invalid), `K` (N, 3, 3), `cam_to_world` (N, 4, 4, OpenCV), `voxel` in
/// scene units; optional `images` for colour, `confs` weighting pixels (those under
/// `min_conf` dropped), `trunc` in voxels, depth outside `[min_depth, max_depth]` ignored, a
/// memory budget; marching cubes drop components under `min_component` triangles. Returns the
/// mesh dict.
#[pyfunction]
#[pyo3(signature = (depths, K, cam_to_world, *, voxel=0.01, images=None, confs=None, min_conf=0.0, trunc=4.0, min_depth=0.05, max_depth=10.0, min_component=100, budget_mb=8192.0, gpu=false))]
#[allow(non_snake_case, clippy::too_many_arguments)]
fn fuse<'py>(
    py: Python<'py>,
    depths: Vec<Bound<'py, PyAny>>,
    K: &Bound<'py, PyAny>,
    cam_to_world: &Bound<'py, PyAny>,
    voxel: f32,
    images: Option<Vec<Bound<'py, PyAny>>>,
    confs: Option<Vec<Bound<'py, PyAny>>>,
    min_conf: f32,
    trunc: f32,
    min_depth: f32,
    max_depth: f32,
    min_component: usize,
    budget_mb: f64,
    gpu: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let n = depths.len();
    if !(voxel.is_finite() && voxel > 0.0) {
        return Err(PyValueError::new_err(format!("voxel={voxel}: must be positive (scene units)")));
    }
    if !(trunc.is_finite() && trunc > 0.0) {
        return Err(PyValueError::new_err(format!("trunc={trunc}: must be positive (voxels)")));
    }
    for (what, len) in [("images", images.as_ref().map(Vec::len)), ("confs", confs.as_ref().map(Vec::len))] {
        if len.is_some_and(|l| l != n) {
            return Err(PyValueError::new_err(format!("{what}: {} entries for {n} depth maps", len.unwrap_or(0))));
        }
    }
    let (kv, pv) = cameras_arg(K, cam_to_world, n)?;
    let mut frames = Vec::with_capacity(n);
    for i in 0..n {
        let (dv, w, h) = map_arg(&depths[i], "depths", 1)?;
        let color = images.as_ref().map(|v| image_arg(&v[i]).map(|im| im.to_rgb8())).transpose()?;
        if color.as_ref().is_some_and(|c| (c.width() as usize, c.height() as usize) != (w, h)) {
            return Err(PyValueError::new_err(format!("images[{i}]: its size differs from depths[{i}] ({w}x{h})")));
        }
        let conf = confs.as_ref().map(|v| map_arg(&v[i], "confs", 1)).transpose()?;
        if conf.as_ref().is_some_and(|c| (c.1, c.2) != (w, h)) {
            return Err(PyValueError::new_err(format!("confs[{i}]: its size differs from depths[{i}] ({w}x{h})")));
        }
        frames.push(FusionFrame {
            name: Cow::Owned(format!("frame {i}")),
            camera: camera(&kv[9 * i..9 * i + 9], &pv[16 * i..16 * i + 16], w, h),
            depth: Cow::Owned(raster(w, h, dv, "depths")?),
            mask: None,
            color: color.map(Cow::Owned),
            conf: conf.map(|(v, w, h)| raster(w, h, v, "confs")).transpose()?.map(Cow::Owned),
            normals: None,
        });
    }
    if !(budget_mb.is_finite() && budget_mb > 0.0) {
        return Err(PyValueError::new_err(format!("budget_mb={budget_mb}: must be positive")));
    }
    let mut params = TsdfParams::new(voxel);
    params.trunc = trunc * voxel;
    params.depth_range = (min_depth, max_depth);
    params.color = images.is_some();
    params.budget_bytes = Some((budget_mb * 1e6) as usize);
    let opts = SceneFusion { params, use_conf: confs.is_some(), min_conf, use_normals: false, gpu };
    let mesh = py.detach(|| {
        let (tsdf, _) = fuse_frames("the depth maps", frames.into_iter().map(Ok), &opts, |_, _| {}).map_err(err)?;
        PyResult::Ok(extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: min_component, crop: None }))
    })?;
    mesh_dict(py, mesh)
}

/// Reads a mesh file (`.ply`, `.obj`, `.off`, `.glb`) as a mesh dict.
#[pyfunction]
fn read_mesh<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let m = py.detach(|| dens3r_mesh::read_mesh(&path)).map_err(err)?;
    mesh_dict(py, m)
}

/// Where the cameras come from, as `dens3r reconstruct --align` names it.
fn align_arg(align: &str) -> PyResult<dens3r_recon::Cameras> {
    match align {
        "sfm" => Ok(dens3r_recon::Cameras::Sfm(Box::default())),
        "dense" => Ok(dens3r_recon::Cameras::Dense),
        a => Err(PyValueError::new_err(format!("align={a:?}: expected sfm or dense"))),
    }
}

/// `model`, else the bundled default loaded into `slot`.
fn model_or_default<'a>(
    py: Python<'_>,
    model: Option<&'a Model>,
    slot: &'a mut Option<Model>,
    gpu: bool,
) -> PyResult<&'a Model> {
    match model {
        Some(m) => Ok(m),
        None => Ok(slot.insert(Model::load(py, None, None, 512, false, gpu, "f32")?)),
    }
}

/// The pair graph named as `dens3r reconstruct --graph` names it ("auto": None, the default).
fn pair_graph(graph: &str, window: usize, cyclic: bool) -> PyResult<Option<dens3r_align::PairGraph>> {
    if graph == "auto" {
        return Ok(None);
    }
    dens3r_align::PairGraph::parse(graph, window, cyclic)
        .map(Some)
        .map_err(|e| PyValueError::new_err(format!("graph={e} (or auto)")))
}

/// Photos -> cameras, depth, normals and a mesh, as `dens3r reconstruct PHOTOS -o OUTPUT`
/// (the same pipeline and outputs: `OUTPUT/scene/`, `colmap/`, `matches/`, `mesh.glb`).
/// Returns `read_scene` of the scene folder plus `output`, `mesh` (a mesh dict, or None) and
/// `summary` (alignment residuals, pairs, photos registered, warnings). `align` is "sfm"
/// (cameras by structure-from-motion, the default) or "dense" (the network's pairs and the
/// dense alignment). `progress(stage, done, total)` is called
/// with stage "predict", "align" or "fuse". `focal` (pixels of the photos) fixes every focal;
/// without it a photo's EXIF 35 mm equivalent focal length is kept where it has one.
/// `min_conf` defaults to the model's (`Model.min_conf`); `masks` is a folder of object masks,
/// one per photo by file stem, as `reconstruct --masks` (only the object is fused).
#[pyfunction]
#[pyo3(signature = (photos, output, *, model=None, align="sfm".to_string(), graph="auto".to_string(), window=3, cyclic=false, iterations=300, fixed_focal=false, focal=None, voxel=None, min_conf=None, masks=None, mesh=true, cache=true, cache_dir=None, match_pictures=20, gpu=false, progress=None))]
#[allow(clippy::too_many_arguments)]
fn reconstruct<'py>(
    py: Python<'py>,
    photos: Vec<PathBuf>,
    output: PathBuf,
    model: Option<&Model>,
    align: String,
    graph: String,
    window: usize,
    cyclic: bool,
    iterations: usize,
    fixed_focal: bool,
    focal: Option<f64>,
    voxel: Option<f32>,
    min_conf: Option<f32>,
    masks: Option<PathBuf>,
    mesh: bool,
    cache: bool,
    cache_dir: Option<PathBuf>,
    match_pictures: usize,
    gpu: bool,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let graph = pair_graph(&graph, window, cyclic)?;
    let cameras = align_arg(&align)?;
    if voxel.is_some_and(|v| !(v.is_finite() && v > 0.0)) {
        return Err(PyValueError::new_err("voxel: must be positive"));
    }
    if focal.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
        return Err(PyValueError::new_err("focal: must be a positive number of pixels of the photos"));
    }
    let mut loaded = None;
    let model = model_or_default(py, model, &mut loaded, gpu)?;
    let report = |stage: &str, done: usize, total: usize| {
        if let Some(cb) = &progress {
            Python::attach(|py| {
                if let Err(e) = cb.call1(py, (stage, done, total)) {
                    e.print(py);
                }
            });
        }
    };
    let (summary, rec_stats) = py.detach(|| {
        use dens3r_recon::{list_images, load_images, write_outputs_into, NetworkPredictor, OutputOptions, PairCache};
        let loaded = load_images(&list_images(&photos).map_err(err)?, model.size, model.keep_portrait).map_err(err)?;
        let (mut images, left_out) = dens3r_recon::input::keep_scenes(loaded);
        let paths: Vec<std::path::PathBuf> = images.iter().map(|im| im.path.clone()).collect();
        if focal.is_some() {
            images.iter_mut().for_each(|im| im.set_focal(focal));
        }
        if images.len() < 2 {
            let why = if left_out.is_empty() { String::new() } else { format!(" ({})", left_out.join("; ")) };
            return Err(err(format!("reconstruction needs at least 2 photos of a scene, got {}{why}", images.len())));
        }
        if let Some(dir) = &masks {
            dens3r_recon::attach_masks(&mut images, dir).map_err(err)?;
        }
        // Locked and staged from here (the pair cache in it written as it goes).
        let out_dir = dens3r_recon::begin_outputs(&output).map_err(err)?;
        let cache = PairCache::new(cache_dir.clone().or_else(|| cache.then(|| output.join("cache"))));
        let predictor = NetworkPredictor::new(model.net.model(), model.cache_id(&cache).map_err(err)?);
        let opts = dens3r_recon::ReconOptions {
            cameras,
            graph,
            align: dens3r_align::AlignOptions { iterations, optimize_focal: !fixed_focal, ..Default::default() },
            matching: dens3r_align::matching::MatchOptions::default(),
            tracks: dens3r_recon::TrackOptions::default(),
            match_pose: Some(dens3r_align::match_pose::MatchPoseOptions::default()),
            keypoints: Some(dens3r_recon::KeypointOptions::default()),
            drop_unplaced: true,
        };
        let mut rec = dens3r_recon::reconstruct(&images, &predictor, &cache, &opts, |stage, done, total| match stage {
            dens3r_recon::Stage::Predict => report("predict", done, total),
            dens3r_recon::Stage::Align => report("align", done, iterations.max(total)),
            dens3r_recon::Stage::Retrieve => report("retrieve", done, total),
            dens3r_recon::Stage::Keypoints => report("keypoints", done, total),
        })
        .map_err(err)?;
        rec.stats.warnings.splice(0..0, left_out);
        let min_conf = min_conf.unwrap_or(model.min_conf);
        let out_opts = OutputOptions { voxel, min_conf, gpu, mesh, match_pictures, ..Default::default() };
        let summary = write_outputs_into(&rec, &paths, &out_dir, &out_opts, |done, total| report("fuse", done, total))
            .map_err(err)?;
        out_dir.finish().map_err(err)?;
        let stats = serde_json::json!({
            "alignment_loss": [rec.alignment.loss.0, rec.alignment.loss.1],
            "pairs": rec.stats.pairs,
            "graph": rec.stats.graph.name,
            "pairs_from_cache": rec.stats.cache_hits,
            "pairs_placed_by_matches": rec.stats.posed_by_matches,
            "pairs_placed_by_keypoints": rec.stats.posed_by_keypoints,
            "pairs_left_out": rec.stats.pairs_left_out,
            "tracks": rec.points.len(),
            "triangulated_points": rec.stats.triangulated_points,
            "registered": rec.stats.registered,
            "unregistered": rec.stats.unregistered,
            "sfm_rms_px": rec.stats.sfm.as_ref().map(|s| [s.rms_px.0, s.rms_px.1]),
            "warnings": rec.stats.warnings.iter().chain(&summary.warnings).collect::<Vec<_>>(),
            "voxel": summary.voxel,
            "triangles": summary.triangles,
        });
        Ok((summary, stats))
    })?;
    let d = read_scene(py, summary.scene.clone())?;
    d.set_item("output", output)?;
    d.set_item("page", summary.page.as_ref().map(|p| p.display().to_string()))?;
    d.set_item("mesh", summary.mesh.map(|p| read_mesh(py, p)).transpose()?)?;
    let json = py.import("json")?;
    d.set_item("summary", json.call_method1("loads", (rec_stats.to_string(),))?)?;
    Ok(d)
}

/// One shard of a reconstruction's network runs into the pair cache `cache_dir`, as
/// `dens3r pairs PHOTOS --cache DIR --shard I/N`: `reconstruct(..., cache_dir=DIR)` with the
/// same model, `align` and `graph` then runs no network. `shard` is `(I, N)`. Returns the
/// counts: `entries` (this shard's), `cached` (of those, already there), `total`.
#[pyfunction]
#[pyo3(signature = (photos, cache_dir, *, model=None, align="sfm".to_string(), graph="auto".to_string(), window=3, cyclic=false, shard=(0, 1), gpu=false))]
#[allow(clippy::too_many_arguments)]
fn compute_shard<'py>(
    py: Python<'py>,
    photos: Vec<PathBuf>,
    cache_dir: PathBuf,
    model: Option<&Model>,
    align: String,
    graph: String,
    window: usize,
    cyclic: bool,
    shard: (usize, usize),
    gpu: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let graph = pair_graph(&graph, window, cyclic)?;
    let cameras = align_arg(&align)?;
    let shard = dens3r_recon::Shard::parse(&format!("{}/{}", shard.0, shard.1)).map_err(PyValueError::new_err)?;
    let mut loaded = None;
    let model = model_or_default(py, model, &mut loaded, gpu)?;
    let stats = py.detach(|| {
        use dens3r_recon::{list_images, load_images, NetworkPredictor, PairCache};
        let paths = list_images(&photos).map_err(err)?;
        let (images, _) =
            dens3r_recon::input::keep_scenes(load_images(&paths, model.size, model.keep_portrait).map_err(err)?);
        let cache = PairCache::new(Some(cache_dir));
        let predictor = NetworkPredictor::new(model.net.model(), model.cache_id(&cache).map_err(err)?);
        let opts = dens3r_recon::ReconOptions { cameras, graph, ..Default::default() };
        let mut warnings = Vec::new();
        dens3r_recon::compute_shard(&images, &predictor, &cache, &opts, shard, &mut warnings, &mut |_, _, _| {})
            .map_err(err)
    })?;
    let d = PyDict::new(py);
    d.set_item("entries", stats.entries)?;
    d.set_item("cached", stats.cached)?;
    d.set_item("total", stats.total)?;
    Ok(d)
}

/// Whether `path` holds a scene folder (`cameras.json`).
#[pyfunction]
fn holds_scene(path: PathBuf) -> bool {
    dens3r_scene::holds_scene(Path::new(&path))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("Dens3rError", m.py().get_type::<Dens3rError>())?;
    m.add_class::<Model>()?;
    m.add_function(wrap_pyfunction!(read_scene, m)?)?;
    m.add_function(wrap_pyfunction!(write_scene, m)?)?;
    m.add_function(wrap_pyfunction!(fuse, m)?)?;
    m.add_function(wrap_pyfunction!(read_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct, m)?)?;
    m.add_function(wrap_pyfunction!(compute_shard, m)?)?;
    m.add_function(wrap_pyfunction!(holds_scene, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
