//! `dens3r nsdf`: scene folder -> neural SDF (NeuS-style, normal- and depth-supervised) -> mesh.

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use dens3r_fusion::ExtractOptions;
use dens3r_mesh::TriMesh;
use dens3r_nsdf::{DepthMode, FieldConfig, FitOptions, FitSummary, Progress, TrainData, TrainOptions};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Clone, Copy, ValueEnum)]
pub enum DepthArg {
    /// Depth is metric in the scene frame (rendered scenes, `dens3r reconstruct` output).
    Metric,
    /// Depth is right up to a per-image scale and shift (monocular predictions; MonoSDF).
    ScaleShift,
    /// Do not use depth.
    Off,
}

#[derive(Args)]
pub struct NsdfArgs {
    /// Scene folder with cameras.json, depth/ and normals/ (images/ for colour).
    scene: PathBuf,
    /// Output mesh: .ply (binary), .obj or .glb.
    #[arg(short, long)]
    output: PathBuf,
    /// Training iterations.
    #[arg(long, default_value_t = 1000)]
    iters: usize,
    /// Rays per iteration.
    #[arg(long, default_value_t = 1024)]
    rays: usize,
    /// Samples per ray (inside the occupied space near the observed surface).
    #[arg(long, default_value_t = 32)]
    samples: usize,
    /// Peak learning rate (Adam, warm-up then cosine decay).
    #[arg(long, default_value_t = 1e-2)]
    lr: f64,
    /// Train without the normal loss (ablation).
    #[arg(long)]
    no_normals: bool,
    /// Weight of the normal loss.
    #[arg(long, default_value_t = 0.1)]
    normal_weight: f32,
    /// How depth supervises the rendered distance.
    #[arg(long, value_enum, default_value_t = DepthArg::Metric)]
    depth: DepthArg,
    /// Weight of the colour loss (0 = geometry only).
    #[arg(long, default_value_t = 0.1)]
    color_weight: f32,
    /// Start by fitting the field to the scene's TSDF for this many iterations.
    #[arg(long, num_args = 0..=1, default_missing_value = "300")]
    init_tsdf: Option<usize>,
    /// Mesh voxel size in scene units (default: 1/256 of the scene's bounding cube).
    #[arg(long)]
    voxel: Option<f32>,
    /// Drop connected pieces with fewer triangles than this.
    #[arg(long, default_value_t = 100)]
    min_component: usize,
    /// Checkpoint folder (default: OUTPUT with `.nsdf` appended).
    #[arg(long)]
    checkpoint_dir: Option<PathBuf>,
    /// Iterations between checkpoints.
    #[arg(long, default_value_t = 250)]
    checkpoint_every: usize,
    /// Start over even if the checkpoint folder holds a run.
    #[arg(long)]
    restart: bool,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Hash-grid levels.
    #[arg(long, default_value_t = 12)]
    levels: usize,
    /// Finest hash-grid resolution over the scene's cube.
    #[arg(long, default_value_t = 512)]
    max_res: u32,
    /// Stop after this iteration's checkpoint (for testing resumption).
    #[arg(long, hide = true)]
    stop_after: Option<usize>,
    /// Train on the GPU (needs a build with `--features nsdf-wgpu`).
    #[arg(long)]
    gpu: bool,
}

fn device(gpu: bool) -> Result<burn::tensor::Device> {
    if !gpu {
        return Ok(dens3r_nsdf::cpu_device());
    }
    #[cfg(feature = "nsdf-wgpu")]
    {
        // With burn's wgpu backend compiled in, the default device is the GPU.
        let d = burn::tensor::Device::default();
        if d == burn::tensor::Device::flex() {
            bail!("no GPU device for burn's wgpu backend: install a Vulkan / Metal / DX12 driver, or drop --gpu");
        }
        Ok(burn::tensor::Device::autodiff(d))
    }
    #[cfg(not(feature = "nsdf-wgpu"))]
    bail!("this dens3r was built without GPU training: rebuild with `cargo build --release --features nsdf-wgpu`, or drop --gpu")
}

/// The most rays per iteration `--rays` takes.
const MAX_RAYS: usize = 1 << 16;
/// The most samples per ray `--samples` takes.
const MAX_SAMPLES: usize = 1024;
/// The most field points per iteration (rays x samples): 32 times the default's, about 2 GB
/// of activations and gradients on the CPU.
const MAX_POINTS: usize = 1 << 20;

/// A mesh voxel that the scene's extent can mesh: between 1/4096 and 1/4 of its bounding
/// cube (the default is 1/256); a larger one has no cell to mesh, a smaller one a grid that
/// does not fit in memory.
fn check_voxel(voxel: Option<f32>, data: &TrainData) -> Result<()> {
    let Some(v) = voxel else { return Ok(()) };
    let cube = data.default_voxel() * 256.0;
    if v > cube / 4.0 || v < cube / 4096.0 {
        bail!(
            "--voxel {v}: the scene's bounding cube is {cube:.4} wide; give a voxel between {:.6} and {:.4} (default {:.5})",
            cube / 4096.0,
            cube / 4.0,
            cube / 256.0
        );
    }
    Ok(())
}

/// The checkpoint folder, after refusing options that cannot work and outputs that cannot be
/// written (checked, not created: a run refused later leaves no folder behind).
fn checked_checkpoint_dir(a: &NsdfArgs) -> Result<PathBuf> {
    let ext = a.output.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    if !["ply", "obj", "glb"].contains(&ext.as_str()) {
        bail!("{}: unknown mesh format: use .ply, .obj or .glb", a.output.display());
    }
    if a.iters == 0 || a.iters > 10_000_000 {
        bail!("--iters must be in 1..=10000000");
    }
    if a.voxel.is_some_and(|v| !(v.is_finite() && v > 0.0)) {
        bail!("--voxel must be a positive length");
    }
    // Every ray's samples live at once through the field and its gradients: bounded by memory.
    if a.rays == 0 || a.rays > MAX_RAYS {
        bail!("--rays {}: expected 1 to {MAX_RAYS} rays per iteration (default 1024)", a.rays);
    }
    if a.samples == 0 || a.samples > MAX_SAMPLES {
        bail!("--samples {}: expected 1 to {MAX_SAMPLES} samples per ray (default 32)", a.samples);
    }
    if a.rays * a.samples > MAX_POINTS {
        bail!(
            "--rays {} x --samples {} = {} points per iteration, over the {MAX_POINTS} that fit in memory; lower one of them",
            a.rays,
            a.samples,
            a.rays * a.samples
        );
    }
    if a.levels == 0 || a.levels > 32 {
        bail!("--levels {}: expected 1 to 32 hash-grid levels (default 12)", a.levels);
    }
    if !(2..=1 << 16).contains(&a.max_res) {
        bail!("--max-res {}: expected 2 to 65536 (default 512)", a.max_res);
    }
    // Where the mesh and the checkpoints go must be writable before any training is spent.
    let mut ck_dir = a.checkpoint_dir.clone().unwrap_or_else(|| {
        let mut s = a.output.clone().into_os_string();
        s.push(".nsdf");
        PathBuf::from(s)
    });
    if ck_dir.as_os_str().is_empty() {
        ck_dir = PathBuf::from(".");
    }
    for dir in [a.output.parent().filter(|p| !p.as_os_str().is_empty()), Some(ck_dir.as_path())].into_iter().flatten() {
        if let Some(blocker) = dir.ancestors().find(|p| p.exists()).filter(|p| !p.is_dir()) {
            bail!("{}: cannot hold {} (it is a file, not a folder)", blocker.display(), dir.display());
        }
    }
    Ok(ck_dir)
}

/// Training options of `a`.
fn train_options(a: &NsdfArgs) -> TrainOptions {
    TrainOptions {
        iters: a.iters,
        rays: a.rays,
        samples: a.samples,
        lr: a.lr,
        w_normal: if a.no_normals { 0.0 } else { a.normal_weight },
        w_color: a.color_weight,
        depth_mode: match a.depth {
            DepthArg::Metric => DepthMode::Metric,
            DepthArg::ScaleShift => DepthMode::ScaleShift,
            DepthArg::Off => DepthMode::Off,
        },
        init_tsdf_iters: a.init_tsdf.unwrap_or(0),
        seed: a.seed,
        ..TrainOptions::default()
    }
}

pub fn run(a: NsdfArgs) -> Result<()> {
    let ck_dir = checked_checkpoint_dir(&a)?;
    let device = device(a.gpu)?;
    let t0 = Instant::now();
    let scene = dens3r_scene::Scene::open(&a.scene)?;
    let data = dens3r_nsdf::load_scene(&scene)?;
    check_voxel(a.voxel, &data)?;
    if !data.unusable_normals.is_empty() && !a.no_normals {
        eprintln!(
            "warning: {}: normals/ of frame(s) {} hold no usable normal (NaN, infinite or zero): training without the normal loss",
            a.scene.display(),
            data.unusable_normals.join(", ")
        );
    } else if !data.has_normals && !a.no_normals {
        eprintln!("note: {} has no normals/ for every frame: training without the normal loss", a.scene.display());
    }
    let train = train_options(&a);
    let field =
        FieldConfig { levels: a.levels, max_res: a.max_res, color: a.color_weight > 0.0, ..FieldConfig::default() };
    let init = if train.init_tsdf_iters > 0 { Some(dens3r_nsdf::warm_start_tsdf(&scene, &data)?) } else { None };
    let opts = FitOptions {
        field,
        train,
        voxel: a.voxel,
        checkpoint_dir: Some(ck_dir.clone()),
        checkpoint_every: a.checkpoint_every,
        resume: !a.restart,
        stop_after: a.stop_after,
        extract: ExtractOptions { min_component_triangles: a.min_component, crop: None },
    };
    let bar = indicatif::ProgressBar::new(a.iters as u64).with_style(
        indicatif::ProgressStyle::with_template("nsdf {bar:30} {pos}/{len} it [{elapsed} < {eta}] {msg}")
            .expect("valid template"),
    );
    let (mesh, s) = dens3r_nsdf::fit(&data, &opts, init.as_ref(), device, |p| match p {
        Progress::InitTsdf(i, l) => bar.set_message(format!("TSDF start {i}: L1 {l:.4}")),
        Progress::Resumed(i) => {
            bar.set_position(i as u64);
            bar.suspend(|| eprintln!("resuming from iteration {i} ({})", ck_dir.display()));
        }
        Progress::Step(st) => {
            bar.set_position(st.iter as u64);
            if st.iter % 10 == 0 {
                bar.set_message(format!(
                    "loss {:.4} depth {:.4} normal {:.3} eik {:.3} s {:.0}",
                    st.total, st.depth, st.normal, st.eikonal, st.sharpness
                ));
            }
        }
    })?;
    bar.finish_and_clear();
    if mesh.indices.is_empty() {
        bail!("{}: the field has no surface inside the observed space (too few iterations?)", a.scene.display());
    }
    dens3r_mesh::write_mesh(&a.output, &mesh)?;
    report(&a, &data, &mesh, &s, t0);
    Ok(())
}

/// Prints what was trained and meshed.
fn report(a: &NsdfArgs, data: &TrainData, mesh: &TriMesh, s: &FitSummary, t0: Instant) {
    println!(
        "trained {} iterations ({} rays, {} frames, normals {}) in {:.1}s; last loss {:.4} (depth {:.4}, normal {:.3}, eikonal {:.3}), sharpness {:.0}",
        a.iters - s.start_iter,
        s.rays,
        data.frames,
        if a.no_normals || !data.has_normals { "off" } else { "on" },
        s.train_seconds,
        s.last.total,
        s.last.depth,
        s.last.normal,
        s.last.eikonal,
        s.last.sharpness
    );
    println!(
        "mesh at voxel {:.4}: {} vertices, {} triangles -> {} (extract {:.1}s, total {:.1}s)",
        s.voxel,
        mesh.positions.len(),
        mesh.indices.len(),
        a.output.display(),
        s.extract_seconds,
        t0.elapsed().as_secs_f64()
    );
}
