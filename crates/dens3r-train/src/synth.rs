//! `dens3r synth`: a training set of procedural scenes (dens3r-render's [`synth_scene`]) written
//! as scene folders, each with `pairs.json`, the measured co-visibility of every ordered frame
//! pair (the fraction of one view's pixels that reproject, unoccluded, into the other), from
//! which training draws its pairs as DUSt3R's are drawn. The same options and assets give the
//! same bytes; a rerun after an interruption keeps the finished scenes.

use crate::pair::{covisibility, View};
use crate::TrainError;
use dens3r_render::procedural::classes;
use dens3r_render::render_cameras_to_scene;
use dens3r_render::synth::{add_occlusion, plain_enclosure, scene_seed, synth_scene, Assets, SynthKind};
use dens3r_scene::Scene;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The file of a scene folder that lists its pairs' co-visibility.
pub const PAIRS_FILE: &str = "pairs.json";
/// The dataset manifest at the top of a `synth` output.
pub const MANIFEST_FILE: &str = "synth.json";

/// What to synthesise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SynthOptions {
    /// Number of scenes.
    pub scenes: usize,
    /// Seed of the whole set (scene `k` is drawn from `scene_seed(seed, k)`).
    pub seed: u64,
    /// `rooms`, `objects`, `mixed`, `tabletop`, `bin`, `packed-bin` or `shelf`.
    pub kind: String,
    /// Landscape image size `(W, H)` (portrait scenes swap it).
    pub size: (usize, usize),
    /// Views per scene.
    pub views: usize,
    /// Write each scene's `gt_mesh.ply`.
    pub gt_mesh: bool,
    /// Render cast shadows and ambient occlusion ([`add_occlusion`]); sets made before this
    /// option existed read as `false`.
    #[serde(default)]
    pub occlusion: bool,
    /// Probability that a scene's walls and ceiling are one flat light colour
    /// ([`plain_enclosure`]); sets made before this option existed read as 0.
    #[serde(default)]
    pub plain_walls: f64,
}

impl SynthOptions {
    /// Checks the options; returns the kind.
    pub fn check(&self) -> Result<SynthKind, TrainError> {
        let kind = SynthKind::parse(&self.kind).ok_or_else(|| {
            TrainError::invalid(format!(
                "--kind {:?}: expected rooms, objects, mixed, tabletop, bin, packed-bin or shelf",
                self.kind
            ))
        })?;
        let (w, h) = self.size;
        if !(16..=4096).contains(&w) || !(16..=4096).contains(&h) {
            return Err(TrainError::invalid(format!("--size {w}x{h}: each side must be 16..4096 pixels")));
        }
        if !(0.0..=1.0).contains(&self.plain_walls) {
            return Err(TrainError::invalid(format!(
                "--plain-walls {}: expected a probability 0..1",
                self.plain_walls
            )));
        }
        if !(2..=1000).contains(&self.views) || !(1..=1_000_000).contains(&self.scenes) {
            return Err(TrainError::invalid("--views must be 2..1000 and --scenes 1..1000000"));
        }
        Ok(kind)
    }
}

#[derive(Serialize, Deserialize)]
struct Manifest {
    format: String,
    options: SynthOptions,
    assets: Vec<String>,
}

#[derive(Serialize, Deserialize)]
struct PairsFile {
    format: String,
    frames: Vec<String>,
    /// Row-major `n x n`: entry `i * n + j` is the co-visibility of frame `i` in frame `j`.
    covisibility: Vec<f64>,
}

const PAIRS_FORMAT: &str = "dens3r-pairs/1";
const MANIFEST_FORMAT: &str = "dens3r-synth/1";

/// What [`synthesise`] did.
#[derive(Debug, Clone, Default)]
pub struct SynthSummary {
    /// Scenes rendered by this call.
    pub rendered: usize,
    /// Scenes already complete (kept).
    pub kept: usize,
    /// Ordered pairs with co-visibility in `[0.1, 0.98]`, over all scenes.
    pub pairs: usize,
    /// Rooms and object scenes rendered by this call.
    pub rooms: usize,
    /// See `rooms`.
    pub objects: usize,
    /// See `rooms`.
    pub tabletops: usize,
    /// See `rooms`.
    pub bins: usize,
    /// See `rooms`.
    pub shelves: usize,
}

/// The folder of scene `k` under `out`.
pub fn scene_dir(out: &Path, k: usize) -> PathBuf {
    out.join(format!("scene_{k:05}"))
}

/// Writes (or completes) the set into `out`; `progress(done, total)` after each scene.
pub fn synthesise(
    out: &Path,
    opts: &SynthOptions,
    assets: &Assets,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SynthSummary, TrainError> {
    let kind = opts.check()?;
    std::fs::create_dir_all(out).map_err(|e| TrainError::file(out, format!("cannot create ({e})")))?;
    let manifest = Manifest { format: MANIFEST_FORMAT.into(), options: opts.clone(), assets: assets.names.clone() };
    let mpath = out.join(MANIFEST_FILE);
    if mpath.is_file() {
        let text = std::fs::read_to_string(&mpath).map_err(|e| TrainError::file(&mpath, format!("{e}")))?;
        let old: Manifest = serde_json::from_str(&text).map_err(|e| {
            TrainError::file(&mpath, format!("damaged manifest ({e}); delete the folder to start over"))
        })?;
        // A rerun with more scenes extends the set; anything else must match.
        let same = old.format == manifest.format
            && old.assets == manifest.assets
            && SynthOptions { scenes: opts.scenes, ..old.options.clone() } == *opts;
        if !same {
            return Err(TrainError::file(
                &mpath,
                "this folder holds a set made with other options or assets; use another -o or delete it",
            ));
        }
    } else if std::fs::read_dir(out)?.next().is_some() {
        return Err(TrainError::file(
            out,
            format!("the folder is not empty and holds no {MANIFEST_FILE}; give a new folder"),
        ));
    }
    let text = serde_json::to_string_pretty(&manifest)?;
    dens3r_io::write_atomic(&mpath, |f| f.write_all(text.as_bytes()))
        .map_err(|e| TrainError::file(&mpath, format!("{e}")))?;
    let mut summary = SynthSummary::default();
    for k in 0..opts.scenes {
        let dir = scene_dir(out, k);
        if dir.join(PAIRS_FILE).is_file() {
            summary.kept += 1;
        } else {
            // Render beside the final folder, then rename: a killed run leaves no half scene.
            let tmp = out.join(format!(".scene_{k:05}.tmp"));
            // A scene that lost its pairs.json is rendered again, if everything in it is
            // dens3r's own output; anything else by the scene's name is left alone.
            if dir.exists() {
                dens3r_io::output::remove_own(&dir).map_err(|e| TrainError::file(&e.path, e.message))?;
            }
            if tmp.exists() {
                std::fs::remove_dir_all(&tmp).map_err(|e| TrainError::file(&tmp, format!("cannot remove ({e})")))?;
            }
            let _staged = dens3r_io::cleanup::stage(&tmp);
            let mut scene = synth_scene(kind, scene_seed(opts.seed, k), opts.size, opts.views, assets)?;
            if opts.occlusion {
                add_occlusion(&mut scene);
            }
            plain_enclosure(&mut scene, scene_seed(opts.seed, k), opts.plain_walls);
            render_cameras_to_scene(&scene.world, &scene.cameras, &classes(), opts.gt_mesh, &tmp, |_| {})?;
            write_pairs(&tmp)?;
            std::fs::rename(&tmp, &dir).map_err(|e| TrainError::file(&dir, format!("cannot rename ({e})")))?;
            summary.rendered += 1;
            match scene.kind {
                "room" => summary.rooms += 1,
                "objects" => summary.objects += 1,
                "bin" | "packed-bin" => summary.bins += 1,
                "shelf" => summary.shelves += 1,
                _ => summary.tabletops += 1,
            }
        }
        let s = Scene::open(&dir)?;
        let n = s.frames().len();
        let table = read_pairs(&s)?.unwrap_or_default();
        summary.pairs += (0..n * n).filter(|&i| i / n != i % n && (0.1..=0.98).contains(&table[i])).count();
        progress(k + 1, opts.scenes);
    }
    Ok(summary)
}

/// Measures the co-visibility of every ordered frame pair of the scene in `dir` (at full
/// resolution) and writes its `pairs.json`.
pub fn write_pairs(dir: &Path) -> Result<(), TrainError> {
    let scene = Scene::open(dir)?;
    let views =
        scene.frames().iter().map(|f| View::load(&scene, f, (f.width, f.height))).collect::<Result<Vec<_>, _>>()?;
    let n = views.len();
    let covisibility = (0..n * n)
        .map(|k| if k / n == k % n { 1.0 } else { (covisibility(&views[k / n], &views[k % n]) * 1e4).round() / 1e4 })
        .collect();
    let file =
        PairsFile { format: PAIRS_FORMAT.into(), frames: views.iter().map(|v| v.name.clone()).collect(), covisibility };
    let text = serde_json::to_string(&file)?;
    let path = dir.join(PAIRS_FILE);
    dens3r_io::write_atomic(&path, |f| f.write_all(text.as_bytes()))
        .map_err(|e| TrainError::file(&path, format!("{e}")))
}

/// The co-visibility table (`n x n`, row-major) of a scene's `pairs.json`, if it has one that
/// lists exactly its frames.
pub fn read_pairs(scene: &Scene) -> Result<Option<Vec<f64>>, TrainError> {
    let path = scene.root().join(PAIRS_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).map_err(|e| TrainError::file(&path, format!("{e}")))?;
    let file: PairsFile = serde_json::from_str(&text).map_err(|e| {
        TrainError::file(&path, format!("damaged ({e}); delete it to have co-visibility measured again"))
    })?;
    let names: Vec<&str> = scene.frames().iter().map(|f| f.name.as_str()).collect();
    let n = names.len();
    if file.format != PAIRS_FORMAT
        || file.frames.iter().map(|s| s.as_str()).collect::<Vec<_>>() != names
        || file.covisibility.len() != n * n
        || file.covisibility.iter().any(|c| !c.is_finite())
    {
        return Err(TrainError::file(
            &path,
            "does not list this scene's frames; delete it to have co-visibility measured again",
        ));
    }
    Ok(Some(file.covisibility))
}
