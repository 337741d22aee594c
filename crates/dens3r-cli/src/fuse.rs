//! `dens3r fuse`: scene folder -> mesh (sparse TSDF + marching cubes), PLY / OBJ / GLB.

use anyhow::{bail, Result};
use clap::Args;
use dens3r_fusion::scene::{fuse_scene, FusionSummary, SceneFusion};
use dens3r_fusion::{extract_mesh, ExtractOptions, SparseTsdf, TsdfParams};
use dens3r_mesh::TriMesh;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct FuseArgs {
    /// Scene folder with cameras.json and depth/ (images/ for colour).
    scene: PathBuf,
    /// Output mesh: .ply (binary), .obj or .glb.
    #[arg(short, long)]
    output: PathBuf,
    /// Voxel size in scene units (metres for rendered scenes).
    #[arg(long, default_value_t = 0.01)]
    voxel: f32,
    /// Truncation distance in voxels.
    #[arg(long, default_value_t = 4.0)]
    trunc: f32,
    /// Ignore depth beyond this.
    #[arg(long, default_value_t = 10.0)]
    max_depth: f32,
    /// Ignore depth below this.
    #[arg(long, default_value_t = 0.05)]
    min_depth: f32,
    /// Stop with an error before the voxel grid exceeds this many MB.
    #[arg(long, default_value_t = 8192.0)]
    budget_mb: f64,
    /// Weight pixels by confidence (conf/), dropping those below --min-conf.
    #[arg(long)]
    conf_weight: bool,
    /// With --conf-weight: confidence below which pixels are dropped.
    #[arg(long, default_value_t = 0.0)]
    min_conf: f32,
    /// Weight pixels by |cos| of the angle between normal (normals/) and ray.
    #[arg(long)]
    normal_weight: bool,
    /// Skip colour integration.
    #[arg(long)]
    no_color: bool,
    /// Drop connected pieces with fewer triangles than this.
    #[arg(long, default_value_t = 100)]
    min_component: usize,
    /// Keep only the box xmin,ymin,zmin,xmax,ymax,zmax (negative values too: `--crop -2,-2,-2,2,2,2`).
    #[arg(long, allow_hyphen_values = true)]
    crop: Option<String>,
    /// Integrate on the GPU (wgpu: Vulkan, Metal or DX12); extraction stays on the CPU.
    #[arg(long)]
    gpu: bool,
    /// Allow OUTPUT to replace an existing file inside the input scene folder (such as its
    /// gt_mesh.ply), which is refused otherwise.
    #[arg(long)]
    overwrite: bool,
}

/// The widest truncation band `--trunc` takes, in voxels.
pub const MAX_TRUNC_VOXELS: f32 = 64.0;

/// Whether `out` is an existing file inside the folder `scene` (one of its files).
pub fn inside_existing(out: &std::path::Path, scene: &std::path::Path) -> bool {
    match (out.canonicalize(), scene.canonicalize()) {
        (Ok(o), Ok(s)) => o.is_file() && o.starts_with(s),
        _ => false,
    }
}

/// `xmin,ymin,zmin,xmax,ymax,zmax` with each min below its max.
fn parse_crop(s: &str) -> Result<(glam::Vec3, glam::Vec3)> {
    let v: Vec<f32> = s.split(',').map(|x| x.trim().parse::<f32>()).collect::<Result<_, _>>().unwrap_or_default();
    if v.len() != 6 || v.iter().any(|x| !x.is_finite()) || !(v[0] < v[3] && v[1] < v[4] && v[2] < v[5]) {
        bail!("--crop {s}: expected six numbers xmin,ymin,zmin,xmax,ymax,zmax with each min below its max");
    }
    Ok((glam::Vec3::new(v[0], v[1], v[2]), glam::Vec3::new(v[3], v[4], v[5])))
}

/// The crop box, after refusing options that cannot work and an output inside the scene.
fn checked_crop(a: &FuseArgs) -> Result<Option<(glam::Vec3, glam::Vec3)>> {
    let ext = a.output.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    if !["ply", "obj", "glb"].contains(&ext.as_str()) {
        bail!("{}: unknown mesh format: use .ply, .obj or .glb", a.output.display());
    }
    if !a.overwrite && inside_existing(&a.output, &a.scene) {
        bail!(
            "{}: a file of the input scene {}; write the mesh elsewhere (or pass --overwrite to replace it)",
            a.output.display(),
            a.scene.display()
        );
    }
    if a.trunc.is_nan() || a.trunc < 1.0 {
        bail!("--trunc {} must be at least 1 voxel", a.trunc);
    }
    // Each depth sample updates the voxels within the band: a wider one only costs time.
    if a.trunc > MAX_TRUNC_VOXELS {
        bail!("--trunc {}: at most {MAX_TRUNC_VOXELS} voxels (3 to 8 is usual; the band's voxels are visited for every pixel)", a.trunc);
    }
    if a.budget_mb.is_nan() || a.budget_mb <= 0.0 {
        bail!("--budget-mb must be positive");
    }
    if !a.min_conf.is_finite() {
        bail!("--min-conf {}: expected a finite confidence (e.g. 1.5; confidences are 1 + exp(x))", a.min_conf);
    }
    a.crop.as_deref().map(parse_crop).transpose()
}

pub fn run(a: FuseArgs) -> Result<()> {
    let crop = checked_crop(&a)?;
    let scene = dens3r_scene::Scene::open(&a.scene)?;
    let mut params = TsdfParams::new(a.voxel);
    params.trunc = a.trunc * a.voxel;
    params.depth_range = (a.min_depth, a.max_depth);
    params.color = !a.no_color;
    params.budget_bytes = Some((a.budget_mb * 1e6) as usize);
    let opts =
        SceneFusion { params, use_conf: a.conf_weight, min_conf: a.min_conf, use_normals: a.normal_weight, gpu: a.gpu };
    let bar = indicatif::ProgressBar::new(scene.frames().len() as u64).with_style(
        indicatif::ProgressStyle::with_template("fuse {bar:30} {pos}/{len} frames [{elapsed} < {eta}]")
            .expect("valid template"),
    );
    let t0 = Instant::now();
    let (tsdf, summary) =
        fuse_scene(&scene, &opts, |done, _| bar.set_position(done as u64)).map_err(anyhow::Error::msg)?;
    bar.finish_and_clear();
    let t = Instant::now();
    let mesh = extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: a.min_component, crop });
    let extract_s = t.elapsed().as_secs_f64();
    if mesh.indices.is_empty() {
        let why = why_empty(&a, &tsdf, &summary, crop);
        bail!("{}: {why}", a.scene.display());
    }
    dens3r_mesh::write_mesh(&a.output, &mesh)?;
    report(&a, &summary, &mesh, extract_s, t0);
    Ok(())
}

/// Which filter left no triangle: the volume's surface, the crop, or the piece size.
fn why_empty(
    a: &FuseArgs,
    tsdf: &SparseTsdf,
    summary: &FusionSummary,
    crop: Option<(glam::Vec3, glam::Vec3)>,
) -> String {
    let whole = extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: 0, crop: None });
    let cropped = extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: 0, crop });
    if whole.indices.is_empty() {
        format!(
            "the fused volume has no surface ({} of {} frames had no valid depth, {} no pixel weighted above zero: confidences NaN or under --min-conf, or grazing normals; too few views, or depth outside [{}, {}])",
            summary.empty_frames, summary.frames, summary.unweighted_frames, a.min_depth, a.max_depth
        )
    } else if cropped.indices.is_empty() {
        format!(
            "the surface ({} triangles) lies outside --crop {}",
            whole.indices.len(),
            a.crop.as_deref().unwrap_or_default()
        )
    } else {
        format!(
            "every piece of the surface ({} triangles) is smaller than --min-component {}; lower it",
            cropped.indices.len(),
            a.min_component
        )
    }
}

/// Prints what was fused, meshed and how long each part took.
fn report(a: &FuseArgs, summary: &FusionSummary, mesh: &TriMesh, extract_s: f64, t0: Instant) {
    println!(
        "fused {} frames ({} without valid depth) into {} blocks ({:.0} MB) at voxel {}: {} vertices, {} triangles -> {}",
        summary.frames,
        summary.empty_frames,
        summary.blocks,
        summary.memory_bytes as f64 / 1e6,
        a.voxel,
        mesh.positions.len(),
        mesh.indices.len(),
        a.output.display()
    );
    println!(
        "time: read {:.2}s, integrate {:.2}s ({:.1} ms/frame, {}), extract {:.2}s, total {:.2}s",
        summary.read_seconds,
        summary.integrate_seconds,
        1e3 * summary.integrate_seconds / summary.frames.max(1) as f64,
        summary.gpu_adapter.as_deref().map_or("CPU".to_string(), |a| format!("GPU: {a}")),
        extract_s,
        t0.elapsed().as_secs_f64()
    );
}
