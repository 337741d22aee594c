//! Normal-supervised neural SDF for dens3r (`dens3r nsdf`): the reconstruction the official
//! Dens3R pipeline leaves to a separate NeuS project, natively.
//!
//! Split the nerfstudio way: [`field`] (hash grid + MLP, geometric initialisation), [`render`]
//! (NeuS volume rendering), [`train`] (rays, losses, Adam, coarse-to-fine), [`data`] (scene
//! folder -> rays in a normalised frame, occupancy), [`checkpoint`] (safetensors + JSON, resume),
//! [`extract`] (SDF on a sparse grid -> dens3r-fusion's marching cubes). [`fit`] runs it all on a
//! scene folder. Tensors and gradients are burn's (flex CPU; wgpu with the `wgpu` feature).
//!
//! Conventions: the scene's cameras (OpenCV, camera-to-world), depth as z, normals in the camera
//! frame facing it; meshes come out in the scene's world frame.

pub mod checkpoint;
pub mod data;
pub mod extract;
pub mod field;
pub mod options;
pub mod render;
pub mod train;

pub use data::{load_scene, Bounds, TrainData};
pub use field::FieldConfig;
pub use train::{DepthMode, StepStats, TrainOptions, Trainer};

use burn::tensor::Device;
use dens3r_fusion::{ExtractOptions, SparseTsdf};
use dens3r_mesh::TriMesh;
use std::path::PathBuf;
use std::time::Instant;

/// A field or training option out of range (one line saying which and the range).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct OptionError(pub String);

/// What can go wrong.
#[derive(Debug, thiserror::Error)]
pub enum NsdfError {
    /// The scene cannot be used.
    #[error("{0}")]
    Scene(String),
    /// Options out of range.
    #[error("invalid option: {0}")]
    Options(String),
    /// A checkpoint cannot be read or written.
    #[error("checkpoint {0}")]
    Checkpoint(String),
    /// The loss became NaN or infinite.
    #[error("training diverged at iteration {0} (loss {1}); lower --lr or check the scene's depth")]
    Diverged(usize, f32),
    /// Stopped on request after a checkpoint (`stop_after`).
    #[error("stopped after iteration {0}")]
    Stopped(usize),
}

/// A whole run.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// Field architecture.
    pub field: FieldConfig,
    /// Training.
    pub train: TrainOptions,
    /// Mesh voxel size in world units (`None`: [`TrainData::default_voxel`]).
    pub voxel: Option<f32>,
    /// Folder for the checkpoint (`None`: no checkpoints).
    pub checkpoint_dir: Option<PathBuf>,
    /// Iterations between checkpoints.
    pub checkpoint_every: usize,
    /// Continue from the checkpoint in `checkpoint_dir` when there is one.
    pub resume: bool,
    /// Stop with [`NsdfError::Stopped`] after this iteration's checkpoint (tests of resuming).
    pub stop_after: Option<usize>,
    /// Mesh extraction.
    pub extract: ExtractOptions,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            field: FieldConfig::default(),
            train: TrainOptions::default(),
            voxel: None,
            checkpoint_dir: None,
            checkpoint_every: 250,
            resume: true,
            stop_after: None,
            extract: ExtractOptions::default(),
        }
    }
}

/// Progress events.
pub enum Progress<'a> {
    /// Fitting the TSDF start: iteration, loss.
    InitTsdf(usize, f32),
    /// One training iteration.
    Step(&'a StepStats),
    /// Resumed at this iteration.
    Resumed(usize),
}

/// What [`fit`] did.
#[derive(Debug, Clone)]
pub struct FitSummary {
    /// Rays available.
    pub rays: usize,
    /// Iteration the run started from (0, or where it resumed).
    pub start_iter: usize,
    /// Last iteration's losses.
    pub last: StepStats,
    /// Seconds training.
    pub train_seconds: f64,
    /// Seconds extracting.
    pub extract_seconds: f64,
    /// Mesh voxel used.
    pub voxel: f32,
    /// Normalisation of the scene.
    pub bounds: Bounds,
}

/// The default autodiff CPU device.
pub fn cpu_device() -> Device {
    Device::autodiff(Device::flex())
}

/// Trains a field on a loaded scene and extracts its mesh. With `train.init_tsdf_iters > 0`
/// the field first fits `init` (a TSDF of the same scene in its world frame: [`warm_start_tsdf`]).
pub fn fit(
    data: &TrainData,
    opts: &FitOptions,
    init: Option<&SparseTsdf>,
    device: Device,
    mut progress: impl FnMut(Progress),
) -> Result<(TriMesh, FitSummary), NsdfError> {
    let ck = opts.checkpoint_dir.as_ref().map(|d| train::checkpoint_path(d));
    let mut trainer = match &ck {
        Some(p) if opts.resume && p.is_file() => {
            let t = Trainer::resume(p, &opts.field, opts.train.clone(), data, device.clone())?;
            progress(Progress::Resumed(t.iter));
            t
        }
        _ => {
            let mut t = Trainer::new(opts.field.clone(), opts.train.clone(), data, device.clone())?;
            if opts.train.init_tsdf_iters > 0 {
                let tsdf = init.ok_or_else(|| NsdfError::Options("a TSDF start needs a fused TSDF".into()))?;
                let (pts, vals) = tsdf_targets(tsdf, &data.bounds)?;
                t.fit_sdf(&pts, &vals, opts.train.init_tsdf_iters, |i, l| progress(Progress::InitTsdf(i, l)));
            }
            t
        }
    };
    let start_iter = trainer.iter;
    let t0 = Instant::now();
    let mut last = StepStats::default();
    while trainer.iter < opts.train.iters {
        last = trainer.step(data);
        if !last.total.is_finite() {
            return Err(NsdfError::Diverged(last.iter, last.total));
        }
        progress(Progress::Step(&last));
        let done = trainer.iter;
        if let Some(p) = &ck {
            if done % opts.checkpoint_every.max(1) == 0 || done == opts.train.iters {
                std::fs::create_dir_all(p.parent().expect("checkpoint folder"))
                    .map_err(|e| NsdfError::Checkpoint(format!("{}: {e}", p.display())))?;
                trainer.save(p, data)?;
            }
        }
        if opts.stop_after == Some(done) {
            return Err(NsdfError::Stopped(done));
        }
    }
    let train_seconds = t0.elapsed().as_secs_f64();
    let voxel = opts.voxel.unwrap_or_else(|| data.default_voxel());
    let t1 = Instant::now();
    let mesh = extract::extract(
        &trainer.values(),
        &trainer.config,
        &data.bounds,
        &data.occupancy,
        voxel,
        &device.inner(),
        &opts.extract,
    )?;
    Ok((
        mesh,
        FitSummary {
            rays: data.rays.len(),
            start_iter,
            last,
            train_seconds,
            extract_seconds: t1.elapsed().as_secs_f64(),
            voxel,
            bounds: data.bounds,
        },
    ))
}

/// The TSDF the field's start fits (`train.init_tsdf_iters`): `scene` fused at the field's
/// default voxel (1/256 of the normalised cube, [`TrainData::default_voxel`]), geometry only,
/// every depth kept. Pass it to [`fit`] as `init`.
pub fn warm_start_tsdf(scene: &dens3r_scene::Scene, data: &TrainData) -> Result<SparseTsdf, NsdfError> {
    let mut params = dens3r_fusion::TsdfParams::new(data.default_voxel());
    params.color = false;
    params.depth_range = (0.0, f32::MAX);
    let fusion = dens3r_fusion::scene::SceneFusion::new(params);
    let (tsdf, _) =
        dens3r_fusion::scene::fuse_scene(scene, &fusion, |_, _| {}).map_err(|e| NsdfError::Scene(e.to_string()))?;
    Ok(tsdf)
}

/// SDF targets for the TSDF start: observed voxels of `tsdf` inside its truncation band, as
/// normalised positions and distances.
pub fn tsdf_targets(tsdf: &SparseTsdf, bounds: &Bounds) -> Result<(Vec<glam::Vec3>, Vec<f32>), NsdfError> {
    use dens3r_fusion::tsdf::{block_voxel, BLOCK_VOXELS};
    let trunc = tsdf.params().trunc as f64;
    let mut pts = Vec::new();
    let mut vals = Vec::new();
    for (k, b) in tsdf.blocks() {
        for i in 0..BLOCK_VOXELS {
            let (w, f) = (b.weight[i], b.tsdf[i]);
            if w > 0.0 && f.abs() < 0.99 {
                let p = bounds.to_unit(tsdf.voxel_center(block_voxel(k, i)).as_dvec3());
                if p.abs().max_element() < 1.0 {
                    pts.push(p);
                    vals.push((f as f64 * trunc / bounds.scale) as f32);
                }
            }
        }
    }
    if pts.is_empty() {
        return Err(NsdfError::Scene(
            "the TSDF start has no observed voxel near a surface inside the scene bounds".into(),
        ));
    }
    Ok((pts, vals))
}
