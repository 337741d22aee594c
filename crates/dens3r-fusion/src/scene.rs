//! Fusing a scene folder: every frame's depth (masked by `masks/` when present), colour from
//! its image, and optional per-pixel weights from `conf/` and from the angle between `normals/`
//! and the viewing ray.

use crate::tsdf::{angle_weights, FrameInput, FusionError, SparseTsdf, TsdfParams};
use dens3r_geom::{PinholeCamera, Raster, Vec3};
use dens3r_scene::Scene;
use image::RgbImage;
use std::borrow::Cow;
use std::time::Instant;

/// Scene-level fusion options on top of [`TsdfParams`].
#[derive(Debug, Clone, PartialEq)]
pub struct SceneFusion {
    /// Volume parameters.
    pub params: TsdfParams,
    /// Weight each pixel by its confidence (`conf/`), dropping those below `min_conf`.
    pub use_conf: bool,
    /// Confidence below which a pixel is ignored (with `use_conf`).
    pub min_conf: f32,
    /// Weight each pixel by `|cos|` of the normal-to-ray angle (`normals/`).
    pub use_normals: bool,
    /// Integrate on the GPU (needs the `gpu` feature and a wgpu adapter).
    pub gpu: bool,
}

impl SceneFusion {
    /// Plain depth (+ colour) fusion with these volume parameters.
    pub fn new(params: TsdfParams) -> Self {
        Self { params, use_conf: false, min_conf: 0.0, use_normals: false, gpu: false }
    }
}

/// What a fusion run did.
#[derive(Debug, Clone, Default)]
pub struct FusionSummary {
    /// Frames integrated.
    pub frames: usize,
    /// Frames that had no valid depth at all.
    pub empty_frames: usize,
    /// Frames with valid depth but no pixel weighted above zero (confidences NaN or under the
    /// threshold, or every normal grazing): they add nothing.
    pub unweighted_frames: usize,
    /// Blocks allocated.
    pub blocks: usize,
    /// Grid memory, bytes.
    pub memory_bytes: usize,
    /// Seconds spent integrating (excluding file reading).
    pub integrate_seconds: f64,
    /// Seconds spent reading the scene.
    pub read_seconds: f64,
    /// The GPU adapter used, `None` on the CPU path.
    pub gpu_adapter: Option<String>,
}

/// The volume being integrated into: on the CPU, or on the GPU with the host grid kept in step.
enum Volume {
    Cpu(SparseTsdf),
    #[cfg(feature = "gpu")]
    Gpu(Box<crate::gpu::GpuTsdf>),
}

impl Volume {
    fn new(opts: &SceneFusion) -> Result<Self, FusionError> {
        if !opts.gpu {
            return SparseTsdf::new(opts.params.clone()).map(Volume::Cpu);
        }
        #[cfg(feature = "gpu")]
        return crate::gpu::GpuTsdf::new(opts.params.clone()).map(|g| Volume::Gpu(Box::new(g)));
        #[cfg(not(feature = "gpu"))]
        Err(FusionError::Gpu(
            "this build has no GPU support: rebuild with `--features gpu` or fuse without --gpu".into(),
        ))
    }

    fn integrate(&mut self, f: &FrameInput) -> Result<(), FusionError> {
        match self {
            Volume::Cpu(t) => t.integrate(f),
            #[cfg(feature = "gpu")]
            Volume::Gpu(g) => g.integrate(f),
        }
    }

    fn adapter(&self) -> Option<String> {
        match self {
            Volume::Cpu(_) => None,
            #[cfg(feature = "gpu")]
            Volume::Gpu(g) => Some(g.adapter().to_string()),
        }
    }

    /// The finished grid (waits for the GPU and copies its voxels back).
    fn finish(self) -> Result<SparseTsdf, FusionError> {
        match self {
            Volume::Cpu(t) => Ok(t),
            #[cfg(feature = "gpu")]
            Volume::Gpu(g) => g.finish(),
        }
    }
}

/// Why [`fuse_scene`] failed: the volume's own error (budget, GPU, bad frame), or the scene's.
#[derive(Debug, thiserror::Error)]
pub enum SceneFusionError {
    /// Raised by the volume while integrating or reading back.
    #[error(transparent)]
    Fusion(#[from] FusionError),
    /// A scene without frames, depth or valid depth, or a layer that cannot be read.
    #[error("{0}")]
    Scene(String),
}

/// One frame to fuse, read from a scene folder or handed over from memory (a reconstruction
/// that has its aligned depth in hand need not write and re-read it).
pub struct FusionFrame<'a> {
    /// Frame name (for errors).
    pub name: Cow<'a, str>,
    /// Camera (OpenCV frame, camera-to-world pose).
    pub camera: PinholeCamera,
    /// Depth (z; 0 or NaN = invalid).
    pub depth: Cow<'a, Raster<f32>>,
    /// Pixels to keep (`false` drops the depth), e.g. a scene's `masks/`.
    pub mask: Option<Cow<'a, Raster<bool>>>,
    /// Colour image (needed when the parameters integrate colour).
    pub color: Option<Cow<'a, RgbImage>>,
    /// Confidence, used with [`SceneFusion::use_conf`].
    pub conf: Option<Cow<'a, Raster<f32>>>,
    /// Camera-frame normals, used with [`SceneFusion::use_normals`].
    pub normals: Option<Cow<'a, Raster<Vec3>>>,
}

/// Integrates every frame of `scene` ([`fuse_frames`] over its frames, read one at a time);
/// `progress(done, total)` is called after each.
pub fn fuse_scene(
    scene: &Scene,
    opts: &SceneFusion,
    progress: impl FnMut(usize, usize),
) -> Result<(SparseTsdf, FusionSummary), SceneFusionError> {
    let err = |e: dens3r_scene::SceneError| SceneFusionError::Scene(e.to_string());
    let root = scene.root().display().to_string();
    let read = |f: &'_ dens3r_scene::Frame| -> Result<FusionFrame<'static>, SceneFusionError> {
        let Some(depth) = scene.depth(f).map_err(err)? else {
            return Err(SceneFusionError::Scene(format!(
                "{root}: frame '{}' has no depth/{}.npy: fusion needs depth for every frame (run dens3r predict or render)",
                f.name, f.name
            )));
        };
        Ok(FusionFrame {
            name: Cow::Owned(f.name.clone()),
            camera: f.camera(),
            depth: Cow::Owned(depth),
            mask: scene.mask(f).map_err(err)?.map(Cow::Owned),
            color: if opts.params.color { Some(Cow::Owned(scene.image(f).map_err(err)?)) } else { None },
            conf: if opts.use_conf { scene.conf(f).map_err(err)?.map(Cow::Owned) } else { None },
            normals: if opts.use_normals { scene.normals(f).map_err(err)?.map(Cow::Owned) } else { None },
        })
    };
    fuse_frames(&root, scene.frames().iter().map(read), opts, progress)
}

/// Integrates `frames` (produced one at a time, so a large set is never held whole) into a new
/// volume: depth masked by `mask`, weighted by confidence (below `min_conf` dropped) and by the
/// normal-to-ray angle as `opts` says, with colour. `what` names the source in errors (a scene
/// folder). `progress(done, total)` is called after each frame.
pub fn fuse_frames<'a>(
    what: &str,
    frames: impl ExactSizeIterator<Item = Result<FusionFrame<'a>, SceneFusionError>>,
    opts: &SceneFusion,
    mut progress: impl FnMut(usize, usize),
) -> Result<(SparseTsdf, FusionSummary), SceneFusionError> {
    let total = frames.len();
    if total == 0 {
        return Err(SceneFusionError::Scene(format!("{what}: the scene has no frames")));
    }
    let mut volume = Volume::new(opts)?;
    let mut summary = FusionSummary { gpu_adapter: volume.adapter(), ..Default::default() };
    let mut any_depth = false;
    let mut frames = frames;
    for i in 0..total {
        let t = Instant::now();
        let f = frames.next().expect("an exact-size iterator")?;
        let mut depth = f.depth;
        if let Some(mask) = &f.mask {
            depth.to_mut().data_mut().iter_mut().zip(mask.data()).filter(|(_, &m)| !m).for_each(|(d, _)| *d = 0.0);
        }
        let mut weight: Option<Raster<f32>> = None;
        if opts.use_conf {
            if let Some(conf) = &f.conf {
                weight = Some(conf.map(|&c| if c.is_finite() && c >= opts.min_conf { c } else { 0.0 }));
            }
        }
        if opts.use_normals {
            if let Some(n) = &f.normals {
                let a = angle_weights(n, &f.camera);
                weight = Some(match weight {
                    Some(w) => Raster::from_fn(w.width(), w.height(), |x, y| w.get(x, y) * a.get(x, y)),
                    None => a,
                });
            }
        }
        summary.read_seconds += t.elapsed().as_secs_f64();
        let valid = depth.data().iter().any(|&d| opts.params.depth_valid(d));
        if valid {
            any_depth = true;
            if weight.as_ref().is_some_and(|w| !w.data().iter().any(|&v| v > 0.0)) {
                summary.unweighted_frames += 1;
            }
        } else {
            summary.empty_frames += 1;
        }
        let t = Instant::now();
        let color = f.color.as_deref().filter(|_| opts.params.color);
        let input = FrameInput { name: &f.name, camera: &f.camera, depth: &depth, color, weight: weight.as_ref() };
        volume.integrate(&input)?;
        summary.integrate_seconds += t.elapsed().as_secs_f64();
        progress(i + 1, total);
    }
    if !any_depth {
        return Err(SceneFusionError::Scene(format!(
            "{what}: no frame has valid depth in [{}, {}] (all zero, NaN or out of range)",
            opts.params.depth_range.0, opts.params.depth_range.1
        )));
    }
    // The GPU runs asynchronously: its time ends when the voxels are back.
    let t = Instant::now();
    let tsdf = volume.finish()?;
    summary.integrate_seconds += t.elapsed().as_secs_f64();
    summary.frames = tsdf.frame_count();
    summary.blocks = tsdf.block_count();
    summary.memory_bytes = tsdf.memory_bytes();
    Ok((tsdf, summary))
}
