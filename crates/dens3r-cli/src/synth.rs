//! `dens3r synth`: procedural training scenes with their pairs' co-visibility (dens3r-train).

use anyhow::{anyhow, Result};
use clap::Args;
use dens3r_render::synth::Assets;
use dens3r_train::synth::{synthesise, SynthOptions};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Args)]
pub struct SynthArgs {
    /// Output folder (one scene folder per scene, plus synth.json). A rerun completes it.
    #[arg(short, long)]
    output: PathBuf,
    /// Number of scenes.
    #[arg(long, default_value_t = 100)]
    scenes: usize,
    /// Seed of the whole set.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// rooms, objects, mixed (rooms and objects), tabletop (clutter seen from above), bin (a
    /// deep tote seen close from above, as a bin-picking camera does), packed-bin (the same
    /// tote packed full, seen closer) or shelf (a shelf of books against a wall, seen nearly
    /// head-on).
    #[arg(long, default_value = "mixed")]
    kind: String,
    /// Landscape image size WxH (portrait scenes swap it).
    #[arg(long, default_value = "512x384")]
    size: String,
    /// Views per scene.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Folder of photographs used as textures (default: scikit-image's, fetched by
    /// scripts/fetch-data.sh into .cache/data/textures).
    #[arg(long)]
    textures: Option<PathBuf>,
    /// Folder of scanned meshes placed in the scenes (default: .cache/data/meshes).
    #[arg(long)]
    meshes: Option<PathBuf>,
    /// Leave out each scene's gt_mesh.ply.
    #[arg(long)]
    no_gt_mesh: bool,
    /// Render the light's cast shadows and ambient occlusion (darker creases, corners and
    /// contacts), as photographs show them; `synth` takes 1.7-2.1x as long. Off by default.
    #[arg(long)]
    occlusion: bool,
    /// Probability that a scene's walls and ceiling are one flat light colour, as most real
    /// rooms' are (the scene's geometry, cameras and other materials stay those of its seed).
    #[arg(long, default_value_t = 0.0)]
    plain_walls: f64,
}

/// Where scripts/fetch-data.sh caches real material: `$DENS3R_DATA`, else `.cache/data` here,
/// else beside the checkout the binary was built in (`target/<profile>/dens3r`).
pub(crate) fn default_data_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("DENS3R_DATA") {
        return PathBuf::from(d);
    }
    let here = PathBuf::from(".cache/data");
    if here.is_dir() {
        return here;
    }
    std::env::current_exe()
        .ok()
        .and_then(|e| e.parent()?.parent()?.parent().map(|root| root.join(".cache/data")))
        .filter(|d| d.is_dir())
        .unwrap_or(here)
}

pub fn run(a: SynthArgs) -> Result<()> {
    let size = crate::train::parse_size(&a.size)?;
    let opts = SynthOptions {
        scenes: a.scenes,
        seed: a.seed,
        kind: a.kind.clone(),
        size,
        views: a.views,
        gt_mesh: !a.no_gt_mesh,
        occlusion: a.occlusion,
        plain_walls: a.plain_walls,
    };
    opts.check().map_err(|e| anyhow!(e))?;
    let data = default_data_dir();
    let explicit = |p: &Option<PathBuf>, what: &str| -> Result<()> {
        match p {
            Some(p) if !p.is_dir() => Err(anyhow!("--{what} {}: no such folder", p.display())),
            _ => Ok(()),
        }
    };
    explicit(&a.textures, "textures")?;
    explicit(&a.meshes, "meshes")?;
    let textures = a.textures.clone().unwrap_or_else(|| data.join("textures"));
    let meshes = a.meshes.clone().unwrap_or_else(|| data.join("meshes"));
    let assets = Assets::load(Some(&textures), Some(&meshes)).map_err(|e| anyhow!(e))?;
    if assets.photos.is_empty() {
        eprintln!(
            "note: no photographs in {}: procedural textures only (run scripts/fetch-data.sh)",
            textures.display()
        );
    }
    if assets.meshes.is_empty() {
        eprintln!(
            "note: no scanned meshes in {}: primitives and blobs only (run scripts/fetch-data.sh)",
            meshes.display()
        );
    }
    let bar = ProgressBar::new(a.scenes as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} scenes, {elapsed} elapsed, ETA {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let start = std::time::Instant::now();
    let s =
        synthesise(&a.output, &opts, &assets, &mut |done, _| bar.set_position(done as u64)).map_err(|e| anyhow!(e))?;
    bar.finish_and_clear();
    println!(
        "{} scenes in {} ({} rendered: {} rooms, {} object sets, {} tabletops, {} bins, {} shelves; {} kept), {} training pairs (co-visibility 0.1..0.98), {} photographs and {} meshes, {:.1} s",
        a.scenes,
        a.output.display(),
        s.rendered,
        s.rooms,
        s.objects,
        s.tabletops,
        s.bins,
        s.shelves,
        s.kept,
        s.pairs,
        assets.photos.len(),
        assets.meshes.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
