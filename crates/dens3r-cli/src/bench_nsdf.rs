//! `dens3r bench nsdf`: the neural SDF against TSDF fusion (`dens3r fuse`) on a rendered object
//! orbit with noisy depth and normals, and the ablation without the normal loss: wall time on
//! this machine and each mesh's Chamfer-L1 / F-score / normal consistency against the
//! ground-truth mesh, over the part of it the cameras saw, measured by the same code for all.

use anyhow::{Context, Result};
use clap::Args;
use dens3r_fusion::scene::{fuse_scene, SceneFusion};
use dens3r_fusion::{extract_mesh, ExtractOptions, TsdfParams};
use dens3r_mesh::metrics::{mesh_metrics_where, MeshMetrics, MeshMetricsOptions};
use dens3r_mesh::TriMesh;
use dens3r_nsdf::{FitOptions, TrainOptions};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct NsdfBenchArgs {
    /// Views of the orbit.
    #[arg(long, default_value_t = 24)]
    views: usize,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "320x240")]
    size: String,
    /// Depth noise (multiplicative sigma).
    #[arg(long, default_value_t = 0.01)]
    depth_noise: f32,
    /// Normal noise, RMS degrees.
    #[arg(long, default_value_t = 5.0)]
    normal_noise: f32,
    /// Voxel of both meshes (TSDF voxel, marching-cubes grid of the field).
    #[arg(long, default_value_t = 0.01)]
    voxel: f32,
    /// TSDF voxel sizes to compare besides `--voxel` (comma separated; the TSDF's best is
    /// reported too).
    #[arg(long, default_value = "0.01,0.015,0.02")]
    tsdf_voxels: String,
    /// Neural SDF iterations.
    #[arg(long, default_value_t = 1000)]
    iters: usize,
    /// Skip the run without normals.
    #[arg(long)]
    no_ablation: bool,
    /// Working folder (default: a temporary folder).
    #[arg(long)]
    workdir: Option<PathBuf>,
    /// Points sampled per mesh for the metrics.
    #[arg(long, default_value_t = 200_000)]
    samples: usize,
}

pub fn run(a: NsdfBenchArgs) -> Result<()> {
    let (w, h) = a.size.split_once('x').context("--size is WIDTHxHEIGHT")?;
    let (w, h): (usize, usize) = (w.parse()?, h.parse()?);
    let tmp = tempfile::tempdir()?;
    let dir = a.workdir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    std::fs::create_dir_all(&dir)?;
    let clean = dir.join("object");
    let noisy = dir.join("object_noisy");
    crate::bench_fusion::render_procedural("blob", a.views, (w, h), &clean)?;
    let noise = dens3r_render::noise::Noise { depth_sigma: a.depth_noise, normal_deg: a.normal_noise, seed: 7 };
    crate::bench_fusion::noisy_copy(&clean, &noisy, &noise)?;

    let gt = dens3r_mesh::read_mesh(&clean.join("gt_mesh.ply"))?;
    let seen = dens3r_scene::visibility::Visibility::from_scene(&dens3r_scene::Scene::open(&clean)?, 0.02)?;
    let seen = |p: glam::Vec3| seen.visible(p);
    let mopts = MeshMetricsOptions { samples: a.samples, thresholds: vec![0.01, 0.02], seed: 0 };
    let extract = ExtractOptions { min_component_triangles: 100, crop: None };
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "object orbit, {} views {w}x{h}, depth noise {:.1}%, normal noise {:.1} deg RMS, CPU ({threads} threads)",
        a.views,
        100.0 * a.depth_noise,
        a.normal_noise
    );
    println!("  metrics against the ground-truth mesh over the part the cameras saw (2 cm visibility tolerance)");
    println!(
        "{:<26} {:>7} {:>8} {:>10} {:>10} {:>10} {:>7} {:>7} {:>7}",
        "method", "voxel", "time s", "chamfer", "accuracy", "complete", "F@1cm", "F@2cm", "NC"
    );
    let row = |name: &str, voxel: f32, secs: f64, mesh: &TriMesh| -> Result<f64> {
        let m = mesh_metrics_where(mesh, &gt, &mopts, &seen).map_err(anyhow::Error::msg)?;
        print_row(name, voxel, secs, &m);
        Ok(m.chamfer_l1)
    };
    let scene = dens3r_scene::Scene::open(&noisy)?;
    let mut tsdf_voxels: Vec<f32> = a.tsdf_voxels.split(',').map(|v| v.trim().parse()).collect::<Result<_, _>>()?;
    if !tsdf_voxels.contains(&a.voxel) {
        tsdf_voxels.insert(0, a.voxel);
    }
    let mut best_tsdf = f64::INFINITY;
    for &v in &tsdf_voxels {
        let t = Instant::now();
        let params = TsdfParams::new(v);
        let (tsdf, _) = fuse_scene(&scene, &SceneFusion::new(params), |_, _| {}).map_err(anyhow::Error::msg)?;
        let mesh = extract_mesh(tsdf.grid(), &extract);
        let secs = t.elapsed().as_secs_f64();
        dens3r_mesh::write_mesh(&dir.join(format!("tsdf_{v}.ply")), &mesh)?;
        best_tsdf = best_tsdf.min(row("TSDF (dens3r fuse)", v, secs, &mesh)?);
    }
    let data = dens3r_nsdf::load_scene(&scene)?;
    let mut results = Vec::new();
    for normals in if a.no_ablation { vec![true] } else { vec![true, false] } {
        let train = TrainOptions {
            iters: a.iters,
            w_normal: if normals { TrainOptions::default().w_normal } else { 0.0 },
            ..TrainOptions::default()
        };
        let opts = FitOptions { train, voxel: Some(a.voxel), extract: extract.clone(), ..FitOptions::default() };
        let t = Instant::now();
        let (mesh, _) = dens3r_nsdf::fit(&data, &opts, None, dens3r_nsdf::cpu_device(), |_| {})?;
        let secs = t.elapsed().as_secs_f64();
        let name = if normals { "neural SDF" } else { "neural SDF, no normal loss" };
        dens3r_mesh::write_mesh(&dir.join(format!("nsdf_normals_{normals}.ply")), &mesh)?;
        results.push((name, row(name, a.voxel, secs, &mesh)?));
    }
    for (name, c) in results {
        println!("{name}: Chamfer {:.2}x the best TSDF's ({c:.5} vs {best_tsdf:.5})", c / best_tsdf);
    }
    Ok(())
}

/// One row of the table.
fn print_row(name: &str, voxel: f32, secs: f64, m: &MeshMetrics) {
    println!(
        "{:<26} {:>7.4} {:>8.1} {:>10.5} {:>10.5} {:>10.5} {:>7.3} {:>7.3} {:>7.3}",
        name,
        voxel,
        secs,
        m.chamfer_l1,
        m.accuracy,
        m.completeness,
        m.fscores[0].fscore,
        m.fscores[1].fscore,
        m.normal_consistency
    );
}
