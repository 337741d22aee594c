//! `dens3r bench fusion`: our TSDF fusion vs Open3D 0.20's `VoxelBlockGrid` (CPU) on the same
//! rendered scenes (a 4 m room walk and an object orbit), with and without 1% depth noise, at
//! each voxel size: integration time per frame, extraction time, peak RSS (each side in its own
//! process) and both meshes' Chamfer-L1 / F-score against the ground-truth mesh, measured by the
//! same code for both.

use crate::bench_peer::{bench_python, child_json, peak_rss_mb};
use anyhow::{bail, Context, Result};
use clap::Args;
use dens3r_fusion::scene::{fuse_scene, SceneFusion};
use dens3r_fusion::{extract_mesh, ExtractOptions, TsdfParams};
use dens3r_mesh::metrics::{mesh_metrics_where, MeshMetrics, MeshMetricsOptions};
use dens3r_render::noise::Noise;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// `dens3r bench fusion`: ours against Open3D on rendered scenes.
#[derive(Args)]
pub struct FusionArgs {
    /// Views per scene.
    #[arg(long, default_value_t = 30)]
    pub(crate) views: usize,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "640x480")]
    pub(crate) size: String,
    /// Voxel sizes (comma separated).
    #[arg(long, default_value = "0.01,0.02")]
    pub(crate) voxels: String,
    /// Python with open3d (default: .cache/bench-venv/bin/python3, else python3).
    #[arg(long)]
    pub(crate) python: Option<PathBuf>,
    /// Working folder for the rendered scenes (default: a temporary folder).
    #[arg(long)]
    pub(crate) workdir: Option<PathBuf>,
    /// Points sampled per mesh for Chamfer / F-score.
    #[arg(long, default_value_t = 200_000)]
    pub(crate) samples: usize,
    /// Also fuse on the GPU (ours through wgpu, Open3D on CUDA:0 where its wheel has CUDA) and
    /// print those rows.
    #[arg(long)]
    pub(crate) gpu: bool,
}

/// Fuses one scene (no component filtering, like Open3D) and prints a JSON line.
pub fn run_fuse(scene: &Path, voxel: f32, out: &Path, gpu: bool) -> Result<()> {
    let scene = dens3r_scene::Scene::open(scene)?;
    let mut params = TsdfParams::new(voxel);
    params.depth_range = (0.0, 10.0);
    let opts = SceneFusion { gpu, ..SceneFusion::new(params) };
    let (tsdf, summary) = fuse_scene(&scene, &opts, |_, _| {}).map_err(anyhow::Error::msg)?;
    let t = Instant::now();
    let mesh = extract_mesh(tsdf.grid(), &ExtractOptions::default());
    let extract = t.elapsed().as_secs_f64();
    dens3r_mesh::write_mesh(out, &mesh)?;
    println!(
        "{}",
        serde_json::json!({
            "frames": summary.frames,
            "integrate_ms_per_frame": 1e3 * summary.integrate_seconds / summary.frames.max(1) as f64,
            "extract_seconds": extract,
            "vertices": mesh.positions.len(),
            "triangles": mesh.indices.len(),
            "peak_rss_mb": peak_rss_mb(),
            "device": summary.gpu_adapter.unwrap_or_else(|| "CPU".into()),
        })
    );
    Ok(())
}

/// Renders procedural scene `kind` along its default path into `out` with this binary's
/// `render`, unless `out` already holds a scene (a reused `--workdir`).
pub(crate) fn render_procedural(kind: &str, views: usize, (w, h): (usize, usize), out: &Path) -> Result<()> {
    if out.join("cameras.json").is_file() {
        return Ok(());
    }
    eprintln!("rendering {kind} ({views} views, {w}x{h}) ...");
    let st = Command::new(std::env::current_exe()?)
        .args(["render", "--procedural", kind, "--views", &views.to_string()])
        .args(["--width", &w.to_string(), "--height", &h.to_string(), "-o"])
        .arg(out)
        .stdout(std::process::Stdio::null())
        .status()?;
    if !st.success() {
        bail!("rendering the {kind} scene into {} failed", out.display());
    }
    Ok(())
}

/// A fresh copy of `src` at `dst` with seeded depth / normal noise.
pub(crate) fn noisy_copy(src: &Path, dst: &Path, noise: &Noise) -> Result<()> {
    if dst.exists() {
        std::fs::remove_dir_all(dst)?;
    }
    copy_dir(src, dst)?;
    dens3r_render::noise::add_noise(dst, noise)?;
    Ok(())
}

/// Copies a folder tree.
fn copy_dir(src: &Path, dst: &Path) -> Result<()> {
    std::fs::create_dir_all(dst)?;
    for e in std::fs::read_dir(src)? {
        let e = e?;
        let to = dst.join(e.file_name());
        if e.file_type()?.is_dir() {
            copy_dir(&e.path(), &to)?;
        } else {
            std::fs::copy(e.path(), &to)?;
        }
    }
    Ok(())
}

pub fn fusion(a: FusionArgs) -> Result<()> {
    let (w, h) = a.size.split_once('x').context("--size is WIDTHxHEIGHT")?;
    let (w, h): (usize, usize) = (w.parse()?, h.parse()?);
    let voxels: Vec<f32> = a.voxels.split(',').map(|v| v.trim().parse::<f32>()).collect::<Result<_, _>>()?;
    if voxels.iter().any(|v| v.is_nan() || *v <= 0.0) {
        bail!("--voxels must be positive lengths");
    }
    let tmp = tempfile::tempdir()?;
    let dir = a.workdir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    std::fs::create_dir_all(&dir)?;
    let exe = std::env::current_exe()?;
    let python = bench_python(a.python.clone());
    let o3d_ok =
        Command::new(&python).args(["-c", "import open3d, PIL, numpy"]).output().is_ok_and(|o| o.status.success());
    if !o3d_ok {
        eprintln!("note: {} lacks open3d / pillow / numpy: run scripts/bench-setup.sh; Rust only", python.display());
    }
    let scenes = bench_scenes(&dir, a.views, (w, h))?;
    let devices: Vec<bool> = if a.gpu { vec![false, true] } else { vec![false] };
    print_header(a.views, (w, h), a.gpu);
    for (name, scene, clean) in &scenes {
        let gt = dens3r_mesh::read_mesh(&clean.join("gt_mesh.ply"))?;
        let seen = dens3r_scene::visibility::Visibility::from_scene(&dens3r_scene::Scene::open(clean)?, 0.02)?;
        let seen = |p: glam::Vec3| seen.visible(p);
        for (&voxel, gpu) in voxels.iter().flat_map(|v| devices.iter().map(move |&g| (v, g))) {
            let tag = format!("{}_{voxel}{}", name.replace('+', "_"), if gpu { "_gpu" } else { "" });
            let ours_path = dir.join(format!("{tag}_dens3r.ply"));
            let o3d_path = dir.join(format!("{tag}_open3d.ply"));
            let mut cmd = Command::new(&exe);
            cmd.args(["bench", "run-fuse"]).arg(scene).arg(voxel.to_string()).arg(&ours_path);
            if gpu {
                cmd.arg("--gpu");
            }
            let r = match child_json(&mut cmd, "Rust fusion") {
                Ok(r) => r,
                Err(e) if gpu => {
                    println!("{:<12} {:>6} GPU: {e:#}", name, voxel);
                    continue;
                }
                Err(e) => return Err(e),
            };
            let o = if o3d_ok { open3d_fusion(&python, scene, voxel, &o3d_path, gpu)? } else { None };
            if gpu {
                println!("  GPU row: ours on {}", r["device"].as_str().unwrap_or("?"));
            }
            let opts = MeshMetricsOptions { samples: a.samples, thresholds: vec![0.01, 0.02], seed: 0 };
            let ours = mesh_metrics_where(&dens3r_mesh::read_mesh(&ours_path)?, &gt, &opts, &seen)
                .map_err(anyhow::Error::msg)?;
            let theirs = match &o {
                Some(_) => Some(
                    mesh_metrics_where(&dens3r_mesh::read_mesh(&o3d_path)?, &gt, &opts, &seen)
                        .map_err(anyhow::Error::msg)?,
                ),
                None => None,
            };
            let label = if gpu { format!("{name} gpu") } else { name.clone() };
            print_row(&label, voxel, &r, o.as_ref(), &ours, theirs.as_ref());
        }
    }
    Ok(())
}

/// The room and the object, each clean and with 1% depth noise: (name, scene, clean scene).
fn bench_scenes(dir: &Path, views: usize, size: (usize, usize)) -> Result<Vec<(String, PathBuf, PathBuf)>> {
    let mut scenes = Vec::new();
    for (name, proc_) in [("room", "room"), ("object", "blob")] {
        let out = dir.join(name);
        render_procedural(proc_, views, size, &out)?;
        let noisy = dir.join(format!("{name}_noise1"));
        noisy_copy(&out, &noisy, &Noise { depth_sigma: 0.01, normal_deg: 0.0, seed: 42 })?;
        scenes.push((name.to_string(), out.clone(), out.clone()));
        scenes.push((format!("{name}+1%"), noisy, out.clone()));
    }
    Ok(scenes)
}

/// Open3D's fusion of `scene` into `out` through `bench/open3d_fusion.py`; `None` (said) when
/// it cannot run on the device.
fn open3d_fusion(python: &Path, scene: &Path, voxel: f32, out: &Path, gpu: bool) -> Result<Option<serde_json::Value>> {
    let o = child_json(
        Command::new(python)
            .arg("bench/open3d_fusion.py")
            .arg(scene)
            .arg(voxel.to_string())
            .arg(out)
            .args(["--device", if gpu { "CUDA:0" } else { "CPU:0" }])
            .env("OMP_NUM_THREADS", rayon_threads().to_string()),
        "Open3D fusion",
    )?;
    Ok(match o.get("error") {
        Some(e) => {
            println!("  (Open3D {}: {e})", if gpu { "GPU" } else { "CPU" });
            None
        }
        None => Some(o),
    })
}

fn print_header(views: usize, (w, h): (usize, usize), gpu: bool) {
    println!(
        "TSDF fusion, {views} views {w}x{h}, truncation 4 voxels, CPU ({} threads){}",
        rayon_threads(),
        if gpu { " and GPU rows (ours: wgpu; Open3D: CUDA:0)" } else { "" }
    );
    println!(
        "{:<12} {:>6} {:>9} {:>9} {:>7} {:>8} {:>8} {:>7} {:>7} {:>9} {:>9} {:>7} {:>7} {:>7} {:>7}",
        "scene",
        "voxel",
        "ms/frame",
        "o3d ms/f",
        "speed",
        "extr s",
        "o3d s",
        "MB",
        "o3d MB",
        "chamfer",
        "o3d ch",
        "F@1cm",
        "o3d F1",
        "F@2cm",
        "o3d F2"
    );
    println!("  chamfer / F: Chamfer-L1 (m) and F-score against the ground-truth mesh, completeness and recall over");
    println!("  the part of it the cameras saw (clean rendered depth, 2 cm tolerance); same evaluation for both");
}

/// One row: ours (`r`, `ours`) against Open3D's (`o`, `theirs`, NaN where it did not run).
fn print_row(
    label: &str,
    voxel: f32,
    r: &serde_json::Value,
    o: Option<&serde_json::Value>,
    ours: &MeshMetrics,
    theirs: Option<&MeshMetrics>,
) {
    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap_or(f64::NAN);
    let of = |k: &str| o.map_or(f64::NAN, |o| f(o, k));
    let (rt, ot) = (f(r, "integrate_ms_per_frame"), of("integrate_ms_per_frame"));
    let tm = |i: usize| theirs.map_or(f64::NAN, |m| m.fscores[i].fscore);
    println!(
        "{:<12} {:>6} {:>9.1} {:>9.1} {:>6.2}x {:>8.2} {:>8.2} {:>7.0} {:>7.0} {:>9.5} {:>9.5} {:>7.3} {:>7.3} {:>7.3} {:>7.3}",
        label,
        voxel,
        rt,
        ot,
        ot / rt,
        f(r, "extract_seconds"),
        of("extract_seconds"),
        f(r, "peak_rss_mb"),
        of("peak_rss_mb"),
        ours.chamfer_l1,
        theirs.map_or(f64::NAN, |m| m.chamfer_l1),
        ours.fscores[0].fscore,
        tm(0),
        ours.fscores[1].fscore,
        tm(1),
    );
}

fn rayon_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}
