//! `dens3r mvs`: multi-view stereo on a scene folder's cameras, its depth and normals (the
//! network's) as the prior; writes a scene folder of the MVS maps, the fused points, a mesh and
//! the page.

use anyhow::{bail, Result};
use clap::Args;
use dens3r_mvs::output::{write_mvs, write_mvs_page, MeshOptions};
use dens3r_mvs::scene::SceneViews;
use dens3r_mvs::{run_mvs, MvsOptions, Stage};
use std::path::PathBuf;
use std::time::Instant;

/// The dense stage's settings, shared by `mvs` and `reconstruct`.
#[derive(Args, Clone)]
pub struct MvsSettings {
    /// Long side of the images multi-view stereo works on (photos larger are resized).
    #[arg(long, default_value_t = 1600)]
    pub mvs_size: usize,
    /// Source views matched per reference view.
    #[arg(long, default_value_t = 6)]
    pub mvs_neighbours: usize,
    /// Leave out the network's depth and normals as PatchMatch's prior (they still give the
    /// depth range).
    #[arg(long)]
    pub no_prior: bool,
    /// Weight of the network's prior in PatchMatch's cost.
    #[arg(long, default_value_t = dens3r_mvs::PatchMatchOptions::default().prior_weight)]
    pub prior_weight: f32,
    /// Geometric-consistency passes after the photometric one.
    #[arg(long, default_value_t = 1)]
    pub geom_iterations: usize,
    /// Other views that must agree with a pixel for it to be fused.
    #[arg(long, default_value_t = 2)]
    pub min_agreeing: usize,
}

impl MvsSettings {
    /// The options these settings give.
    pub fn options(&self) -> Result<MvsOptions> {
        if self.mvs_size < 64 {
            bail!("--mvs-size {}: at least 64 pixels", self.mvs_size);
        }
        if self.mvs_neighbours == 0 || self.mvs_neighbours > dens3r_mvs::patch_match::MAX_SOURCES {
            bail!("--mvs-neighbours {}: 1 to {}", self.mvs_neighbours, dens3r_mvs::patch_match::MAX_SOURCES);
        }
        if !(self.prior_weight.is_finite() && self.prior_weight >= 0.0) {
            bail!("--prior-weight {}: a weight >= 0", self.prior_weight);
        }
        if self.min_agreeing == 0 {
            bail!("--min-agreeing 0: at least one other view must agree (2 is COLMAP's default)");
        }
        let mut o = MvsOptions { max_size: self.mvs_size, neighbours: self.mvs_neighbours, ..Default::default() };
        o.patch_match.prior_weight = if self.no_prior { 0.0 } else { self.prior_weight };
        o.patch_match.geom_iterations = self.geom_iterations;
        o.fusion.min_agreeing = self.min_agreeing;
        Ok(o)
    }
}

#[derive(Args)]
pub struct MvsArgs {
    /// Scene folder with cameras.json and images (and depth/, normals/, conf/ as the prior:
    /// what `reconstruct` writes in OUT/scene).
    scene: PathBuf,
    /// Output folder: a scene folder of the MVS maps at the working size, points.ply,
    /// mesh.ply, mvs.json and index.html.
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    settings: MvsSettings,
    /// TSDF voxel of the mesh (default: twice the pixel footprint at the median depth).
    #[arg(long)]
    voxel: Option<f32>,
}

/// A progress bar over the stages.
pub fn progress_bar(n: usize) -> (indicatif::ProgressBar, impl FnMut(Stage, usize, usize)) {
    let bar = indicatif::ProgressBar::new(3 * n as u64).with_style(
        indicatif::ProgressStyle::with_template("mvs {bar:30} {msg} [{elapsed} < {eta}]").expect("valid template"),
    );
    let b = bar.clone();
    let f = move |stage: Stage, done: usize, total: usize| {
        let base = match stage {
            Stage::Photometric => 0,
            Stage::Geometric => total,
            Stage::Fusion => 2 * total,
        };
        b.set_position((base + done) as u64);
        b.set_message(format!("{stage:?} {done}/{total}").to_lowercase());
    };
    (bar, f)
}

pub fn run(a: MvsArgs) -> Result<()> {
    let opts = a.settings.options()?;
    if let Some(v) = a.voxel {
        if !(v.is_finite() && v > 0.0) {
            bail!("--voxel {v}: a positive length in scene units");
        }
    }
    let t0 = Instant::now();
    let scene = dens3r_scene::Scene::open(&a.scene)?;
    let dir = dens3r_scene::begin_output(&a.output)?;
    let source = SceneViews::new(&scene);
    let (bar, progress) = progress_bar(scene.frames().len());
    let result = run_mvs(&source, None, &opts, progress);
    bar.finish_and_clear();
    let result = result.map_err(|e| anyhow::anyhow!("{}: {e}", a.scene.display()))?;
    let mesh_opts = MeshOptions { voxel: a.voxel, budget_bytes: Some(8 << 30) };
    let extra = [("source_scene", serde_json::json!(a.scene.display().to_string()))];
    let (summary, mesh) = write_mvs(dir.root(), &source, &result, &mesh_opts, &extra)
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.scene.display()))?;
    let mut json = summary.to_json();
    json["total_seconds"] = serde_json::json!(t0.elapsed().as_secs_f64());
    write_mvs_page(dir.root(), "", &dens3r_viewer::title_of(dir.dest()), &mesh, json)
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.output.display()))?;
    let dest = dir.finish()?;
    println!(
        "mvs: {} views at {}x{}, {:.1} s a view (median), {:.1}% of pixels kept by {}+ agreeing views, {} points; mesh {} triangles at voxel {:.4} -> {}",
        summary.views,
        summary.working_size.0,
        summary.working_size.1,
        summary.seconds_per_view,
        100.0 * summary.kept_fraction,
        opts.fusion.min_agreeing,
        summary.points,
        summary.triangles,
        summary.voxel,
        dest.join("mesh.ply").display()
    );
    println!("total {:.1} s", t0.elapsed().as_secs_f64());
    Ok(())
}
