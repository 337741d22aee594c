//! A predicted scene scored against a ground-truth one, frame by frame (`dens3r eval`):
//! frames paired by name, depth and normal metrics per frame with the frames that cannot be
//! scored set apart (and why), relative camera errors, and the image-blind baselines a
//! predictor must beat. The metrics themselves are dens3r-geom's.

use crate::{Frame, Scene, SceneError};
use dens3r_geom::metrics::{
    camera_metrics, constant_baseline, depth_metrics, disparity_scores, normal_metrics, plane_baseline, CameraMetrics,
    DepthAlign, DepthMetrics, DisparityScores, MetricError, NormalMetrics,
};
use dens3r_geom::normals::normals_from_pointmap_robust;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{NormalConvention, PinholeCamera, Raster, Vec3};
use std::path::Path;

/// A predicted and a ground-truth scene with the frames both hold, matched by name.
pub struct Paired {
    /// The prediction.
    pub pred: Scene,
    /// The ground truth.
    pub gt: Scene,
    /// `(predicted frame, ground-truth frame)`, in the ground truth's order.
    pub frames: Vec<(Frame, Frame)>,
    /// The ground truth's frames the prediction does not hold (scored nowhere).
    pub missing: Vec<String>,
}

/// Opens both scenes and pairs their frames by name; an error when a shared frame differs in
/// size or none is shared.
pub fn pair(pred: &Path, gt: &Path) -> Result<Paired, SceneError> {
    let (p, g) = (Scene::open(pred)?, Scene::open(gt)?);
    let mut frames = Vec::new();
    let mut missing = Vec::new();
    for gf in g.frames() {
        if p.frame(&gf.name).is_none() {
            missing.push(gf.name.clone());
        }
        if let Some(pf) = p.frame(&gf.name) {
            if (pf.width, pf.height) != (gf.width, gf.height) {
                return Err(SceneError::new(
                    pred,
                    format!(
                        "frame '{}' is {}x{} here but {}x{} in {}: resample one of them first",
                        gf.name,
                        pf.width,
                        pf.height,
                        gf.width,
                        gf.height,
                        gt.display()
                    ),
                ));
            }
            frames.push((pf.clone(), gf.clone()));
        }
    }
    if frames.is_empty() {
        return Err(SceneError::new(
            pred,
            format!("this scene and {} share no frame names: nothing to compare", gt.display()),
        ));
    }
    Ok(Paired { pred: p, gt: g, frames, missing })
}

/// Per frame: its name and metrics, or why it could not be scored (no pixel valid in both maps:
/// NaN, infinite or zero values, or an empty mask).
pub type Scores<M> = Vec<(String, Result<M, MetricError>)>;

/// A layer a frame must have.
fn need<T>(v: Option<T>, scene: &Scene, f: &Frame, what: &str) -> Result<T, SceneError> {
    v.ok_or_else(|| {
        SceneError::new(scene.root(), format!("frame '{}' has no {what} file ({what}/{}.npy)", f.name, f.name))
    })
}

/// The predicted depth of every paired frame, with its ground-truth frame.
pub fn pred_depths(p: &Paired) -> Result<Vec<(Raster<f32>, Frame)>, SceneError> {
    p.frames.iter().map(|(pf, gf)| Ok((need(p.pred.depth(pf)?, &p.pred, pf, "depth")?, gf.clone()))).collect()
}

/// Depth maps, each with its ground-truth frame.
pub type FrameDepths = Vec<(Raster<f32>, Frame)>;

/// Depth maps of a folder of `NAME.npy` files (`predict --head` output) for `gt`'s frames, and
/// the frames with none; an error for a map of another size or when none is there.
pub fn npy_depths(dir: &Path, gt: &Scene) -> Result<(FrameDepths, Vec<String>), SceneError> {
    let mut out = Vec::new();
    let mut missing = Vec::new();
    for gf in gt.frames() {
        let path = dir.join(format!("{}.npy", gf.name));
        if !path.is_file() {
            missing.push(gf.name.clone());
            continue;
        }
        let (shape, data) = crate::npy::read_f32(&path)?;
        if shape != [gf.height, gf.width] {
            return Err(SceneError::new(
                &path,
                format!(
                    "{shape:?} does not fit frame '{}' ({}x{}); predict with --original-size",
                    gf.name, gf.width, gf.height
                ),
            ));
        }
        let r = Raster::from_vec(gf.width, gf.height, data).map_err(|e| SceneError::new(&path, e.to_string()))?;
        out.push((r, gf.clone()));
    }
    if out.is_empty() {
        return Err(SceneError::new(dir, format!("no NAME.npy depth map for any frame of {}", gt.root().display())));
    }
    Ok((out, missing))
}

/// Depth metrics of each predicted map against `gt`'s depth (within its masks).
pub fn depth_scores(
    pred: &[(Raster<f32>, Frame)],
    gt: &Scene,
    align: DepthAlign,
) -> Result<Scores<DepthMetrics>, SceneError> {
    pred.iter()
        .map(|(pd, gf)| {
            let gd = need(gt.depth(gf)?, gt, gf, "depth")?;
            Ok((gf.name.clone(), depth_metrics(pd, &gd, gt.mask(gf)?.as_ref(), align)))
        })
        .collect()
}

/// Where the predicted normals come from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NormalSource {
    /// The prediction's `normals/`, stored in this convention.
    Layer(NormalConvention),
    /// Derived from the prediction's depth (discontinuity-robust central differences).
    FromDepth,
}

/// Normal metrics of every paired frame against the ground truth's normals (within its masks).
pub fn normal_scores(p: &Paired, source: NormalSource) -> Result<Scores<NormalMetrics>, SceneError> {
    let (ps, gs) = (&p.pred, &p.gt);
    p.frames
        .iter()
        .map(|(pf, gf)| {
            let pred: Raster<Vec3> = match source {
                NormalSource::FromDepth => {
                    let d = need(ps.depth(pf)?, ps, pf, "depth")?;
                    normals_from_pointmap_robust(&depth_to_pointmap(&d, &pf.camera().intrinsics), 0.05)
                }
                NormalSource::Layer(conv) => need(ps.normals(pf)?, ps, pf, "normals")?.map(|n| conv.to_opencv(*n)),
            };
            let gt = need(gs.normals(gf)?, gs, gf, "normals")?;
            Ok((gf.name.clone(), normal_metrics(&pred, &gt, gs.mask(gf)?.as_ref())))
        })
        .collect()
}

/// The cameras of the frames both scenes hold (matched by name, in `gt`'s order): `pred`'s, then
/// `gt`'s.
fn shared_cameras(pred: &Path, gt: &Path) -> Result<SharedCameras, SceneError> {
    let (p, g) = (Scene::open(pred)?, Scene::open(gt)?);
    let (mut est, mut truth, mut missing) = (Vec::new(), Vec::new(), Vec::new());
    for gf in g.frames() {
        match p.frame(&gf.name) {
            Some(pf) => {
                est.push(pf.camera());
                truth.push(gf.camera());
            }
            None => missing.push(gf.name.clone()),
        }
    }
    Ok((est, truth, missing))
}

/// `pred`'s and `gt`'s cameras of the frames both hold, and the names of `gt`'s frames that
/// `pred` lacks.
type SharedCameras = (Vec<PinholeCamera>, Vec<PinholeCamera>, Vec<String>);

/// Relative camera errors over every pair of the frames both scenes hold; with the number of
/// those frames and the ground truth's frames the prediction lacks. An error when fewer than
/// 2 are shared.
pub fn camera_scores(pred: &Path, gt: &Path) -> Result<(usize, Vec<String>, CameraMetrics), SceneError> {
    let (est, truth, missing) = shared_cameras(pred, gt)?;
    if truth.len() < 2 {
        return Err(SceneError::new(
            pred,
            format!(
                "this scene and {} share {} frame name(s): relative poses need at least 2",
                gt.display(),
                truth.len()
            ),
        ));
    }
    Ok((truth.len(), missing, camera_metrics(&est, &truth)))
}

/// The similarity (scale, rotation, translation) taking scene `pred`'s frame to scene `gt`'s:
/// least squares over the centres of the cameras both hold (frames matched by name), with
/// the number of those cameras. Puts a reconstruction, known only up to scale, where its
/// ground truth is, e.g. to score its mesh. An error for fewer than 3 shared cameras or
/// centres on one line.
pub fn camera_similarity(pred: &Path, gt: &Path) -> Result<(dens3r_geom::transform::Sim3, usize), SceneError> {
    let (est, truth, _) = shared_cameras(pred, gt)?;
    let src: Vec<_> = est.iter().map(PinholeCamera::center).collect();
    let dst: Vec<_> = truth.iter().map(PinholeCamera::center).collect();
    let n = src.len();
    let sim = dens3r_geom::umeyama(&src, &dst, None, true).map_err(|e| {
        SceneError::new(
            pred,
            format!(
                "cannot place this scene's cameras on those of {} ({n} shared by name; at least 3 not on one line are needed): {e}",
                gt.display()
            ),
        )
    })?;
    Ok((sim, n))
}

/// Depth and normal metrics of each frame of one image-blind baseline.
pub type BaselineScores = (Vec<DepthMetrics>, Vec<NormalMetrics>);

/// The two image-blind baselines on every frame of `gt` with depth (frames without, e.g. the
/// second view of a stereo pair, are not scored): the median depth facing the camera
/// (unaligned), and the best-fit plane (depth aligned by `plane_align`).
pub fn baseline_scores(gt: &Scene, plane_align: DepthAlign) -> Result<[BaselineScores; 2], SceneError> {
    let mut rows: [BaselineScores; 2] = Default::default();
    for gf in gt.frames() {
        let Some(gd) = gt.depth(gf)? else { continue };
        let mask = gt.mask(gf)?;
        let gn = gt.normals(gf)?;
        let k = gf.camera().intrinsics;
        let made = [
            (constant_baseline(&gd, mask.as_ref()), DepthAlign::None),
            (plane_baseline(&gd, &k, mask.as_ref()), plane_align),
        ];
        let frame_err = |m: String| SceneError::new(gt.root(), format!("frame '{}': {m}", gf.name));
        for ((b, align), row) in made.into_iter().zip(rows.iter_mut()) {
            let b = b.ok_or_else(|| frame_err("too few valid depth pixels".into()))?;
            row.0.push(depth_metrics(&b.depth, &gd, mask.as_ref(), align).map_err(|e| frame_err(e.to_string()))?);
            if let Some(gn) = &gn {
                row.1.push(normal_metrics(&b.normals, gn, mask.as_ref()).map_err(|e| frame_err(e.to_string()))?);
            }
        }
    }
    if rows[0].0.is_empty() {
        return Err(SceneError::new(gt.root(), "no frame has depth (depth/NAME.npy): nothing to fit a baseline to"));
    }
    Ok(rows)
}

/// A 2-D float map: a float `.npy`, a grey `.pfm`, or a grey 8- or 16-bit PNG (values as
/// they are).
fn read_map(path: &Path, what: &str) -> Result<Raster<f32>, SceneError> {
    let ext = |x: &str| path.extension().is_some_and(|e| e.eq_ignore_ascii_case(x));
    if ext("pfm") {
        let (w, h, data) = crate::pfm::read_pfm(path)?;
        return Raster::from_vec(w, h, data).map_err(|e| SceneError::new(path, e.to_string()));
    }
    if ext("npy") {
        let (shape, data) = crate::npy::read_f32(path)?;
        let &[h, w] = shape.as_slice() else {
            return Err(SceneError::new(path, format!("{what} must be a 2-D array (height x width), not {shape:?}")));
        };
        return Raster::from_vec(w, h, data).map_err(|e| SceneError::new(path, e.to_string()));
    }
    Ok(crate::reader::read_grey_png(path, what)?.map(|v| *v as f32))
}

/// Predicted depth (`PRED.npy`, as `predict --original-size` writes it) scored against a
/// disparity map whose calibration is unknown, beside the image-blind fits (see
/// `dens3r_geom::metrics::disparity`). The disparity: a grey PNG (Middlebury 2006's convention:
/// the value is the disparity, 0 unknown; KITTI's 16-bit PNGs hold 256x it, `scale` 256), a
/// float `.npy`, or a `.pfm` (Middlebury 2014, Scene Flow: infinity unknown); its values are
/// divided by `scale`. `mask`: a PNG whose non-zero pixels are scored.
pub fn disparity_file_scores(
    pred: &Path,
    gt: &Path,
    scale: f32,
    mask: Option<&Path>,
) -> Result<DisparityScores, SceneError> {
    if !(scale.is_finite() && scale > 0.0) {
        return Err(SceneError::new(gt, format!("the disparity scale must be a positive number, not {scale}")));
    }
    let p = read_map(pred, "predicted depth")?;
    let g = read_map(gt, "disparity")?.map(|d| d / scale);
    let m = mask.map(|m| crate::reader::read_grey_png(m, "a mask").map(|r| r.map(|v| *v != 0))).transpose()?;
    let size = |r: &Raster<f32>| format!("{}x{}", r.width(), r.height());
    if !p.same_size(&g) {
        return Err(SceneError::new(
            pred,
            format!("is {} but the disparity {} is {}: predict with --original-size", size(&p), gt.display(), size(&g)),
        ));
    }
    if let (Some(m), Some(mp)) = (&m, mask) {
        if !m.same_size(&g) {
            return Err(SceneError::new(
                mp,
                format!("mask is {}x{}, the disparity {}", m.width(), m.height(), size(&g)),
            ));
        }
    }
    disparity_scores(&p, &g, m.as_ref()).map_err(|e| {
        SceneError::new(gt, format!("{e} (zero or non-finite disparity, zero or NaN depth of {})", pred.display()))
    })
}
