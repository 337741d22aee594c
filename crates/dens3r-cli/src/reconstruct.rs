//! `dens3r reconstruct`: photos -> cameras (structure-from-motion, or the network's pairs and
//! global alignment) -> depth and normals -> scene folder, COLMAP / nerfstudio exports, match
//! pictures and a mesh.

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use dens3r_align::cycle_focal::CycleFocalOptions;
use dens3r_align::match_pose::MatchPoseOptions;
use dens3r_align::matching::MatchOptions;
use dens3r_align::{AlignOptions, PairGraph};
use dens3r_backbone::Precision;
use dens3r_recon::oracle::SceneOracle;
use dens3r_recon::predictor::network_cache_id;
use dens3r_recon::{
    begin_outputs, list_images, load_images, reconstruct, write_outputs_into, Cameras, KeypointOptions,
    NetworkPredictor, OutputOptions, OutputSummary, PairCache, ReconOptions, Reconstruction, Stage, TrackOptions,
};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Align {
    /// Cameras by global structure-from-motion on SIFT keypoints (rotation averaging, global
    /// positioning, bundle adjustment); the network gives each photo's depth and normals.
    Sfm,
    /// The network's pairs, placed by keypoints and matches where they agree, then DUSt3R's
    /// dense global alignment.
    Dense,
}

/// How the cameras are found and which photos are paired: shared by `reconstruct` and `pairs`
/// (a shard must compute what the reconstruction will read).
#[derive(Args)]
pub(crate) struct Pairing {
    /// How the cameras are found. With sfm, photos the structure-from-motion does not
    /// register are left out (and named); with fewer than half registered the run falls back
    /// to dense.
    #[arg(long, value_enum, default_value = "sfm")]
    align: Align,
    /// Which photos are matched (sfm), or which pairs the network runs, both orders of each
    /// (dense): complete (every pair), swin (each photo with the next --window: ordered
    /// captures), logwin (those 1, 2, 4, .. ahead), oneref (every photo with the first),
    /// retrieval or retrieval-NA-K (NA key images found by the network's encoder paired
    /// among themselves, each photo with its K most similar, 20 and 10 by default; the
    /// sliding window added when the file order looks like the capture's), or auto: complete
    /// up to 30 photos, retrieval above.
    #[arg(long, default_value = "auto", value_name = "GRAPH")]
    graph: String,
    /// Window of --graph swin / logwin.
    #[arg(long, default_value_t = 3)]
    window: usize,
    /// Close the window around the end (captures that circle the object).
    #[arg(long)]
    cyclic: bool,
}

impl Pairing {
    /// The pair graph (None: auto), or the one-line error naming --graph.
    pub(crate) fn graph(&self) -> Result<Option<PairGraph>> {
        Ok(match self.graph.as_str() {
            "auto" => None,
            g => Some(
                PairGraph::parse(g, self.window, self.cyclic).map_err(|e| anyhow::anyhow!("--graph {e} (or auto)"))?,
            ),
        })
    }

    /// The cameras' source.
    pub(crate) fn cameras(&self) -> Cameras {
        match self.align {
            Align::Sfm => Cameras::Sfm(Box::default()),
            Align::Dense => Cameras::Dense,
        }
    }
}

#[derive(Args)]
pub struct ReconstructArgs {
    /// Photos: a folder (its .png / .jpg / .jpeg / .pgm / .ppm files, sorted by name) or files.
    #[arg(required = true)]
    photos: Vec<PathBuf>,
    /// Output folder (scene/, colmap/, matches/, mesh.glb, cache/).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    model: crate::model_args::ModelArgs,
    #[command(flatten)]
    pairing: Pairing,
    /// Global alignment iterations (DUSt3R: 300; --align dense).
    #[arg(long, default_value_t = 300)]
    iterations: usize,
    /// Keep the estimated focals fixed during alignment (--align dense).
    #[arg(long)]
    fixed_focal: bool,
    /// Focal length of every photo in pixels of the photo as stored (after its EXIF rotation),
    /// kept fixed. Without it a photo's EXIF 35 mm equivalent focal length is used where it has
    /// one, and the other focals are estimated.
    #[arg(long, value_name = "PX")]
    focal: Option<f64>,
    /// Ignore the photos' EXIF focal lengths: estimate every focal not given by --focal.
    #[arg(long)]
    no_exif_focal: bool,
    /// Photos of one size with no focal known share one focal in the alignment (one camera's
    /// photos; COLMAP's single camera; --align dense, where sfm always shares one). Without it each gets its own, as DUSt3R does: a network
    /// misjudging one photo's field of view then costs that focal, not that photo's pose.
    #[arg(long)]
    shared_focal: bool,
    /// Keep the network's focal even where the keypoint pairs' cycles give one (--align dense; by default,
    /// photos of one size with no focal known take the focal at which the rotations of the
    /// pairs placed by keypoints close their cycles, when those pick one clearly).
    #[arg(long)]
    no_cycle_focal: bool,
    /// TSDF voxel in scene units (default: twice the pixel footprint at the median depth).
    #[arg(long)]
    voxel: Option<f32>,
    /// Pixels below this confidence are not fused (default: the model's `"min_conf"` in its
    /// config.json, else DUSt3R's demo threshold, 3).
    #[arg(long)]
    min_conf: Option<f32>,
    /// Object masks: a folder with one picture per photo, named by the photo's file stem
    /// (white = object, black = background, or a cut-out's transparency), at the photo's size.
    /// Only the object's pixels are fused into the mesh; the scene folder keeps them in masks/.
    #[arg(long, value_name = "DIR")]
    masks: Option<PathBuf>,
    /// Stop before the voxel grid exceeds this many MB.
    #[arg(long, default_value_t = 4096.0)]
    budget_mb: f64,
    /// Run the network on the GPU (the default build's `gpu-network` feature, or `cuda`) and fuse
    /// on it (wgpu).
    #[arg(long)]
    gpu: bool,
    /// Keep the network's cross-view pointmaps for every pair (--align dense; by default a pair's second view
    /// is placed by its matches and its own-frame pointmap where enough matches agree on a
    /// camera).
    #[arg(long)]
    no_match_pose: bool,
    /// Do not place pairs by SIFT keypoint matches (--align dense; by default a pair is placed by their
    /// epipolar geometry first, where enough agree, so its rotation needs neither the
    /// network's descriptors nor its depth).
    #[arg(long)]
    no_keypoints: bool,
    /// Align every pair, also those neither keypoints nor matches placed (--align dense; by default these
    /// are left out among images that placed pairs already connect: their cross-view
    /// pointmaps are the network's unchecked guess).
    #[arg(long)]
    keep_unplaced: bool,
    /// Skip the mesh (scene folder and exports only).
    #[arg(long)]
    no_mesh: bool,
    /// Where the dense geometry (the mesh, the page's points) comes from: multi-view stereo
    /// on the cameras with the network's depth and normals as its prior (OUTPUT/mvs/), or the
    /// network's depth alone, fused.
    #[arg(long, value_enum, default_value = "mvs")]
    dense: Dense,
    #[command(flatten)]
    mvs: crate::mvs::MvsSettings,
    /// Skip the page (OUTPUT/index.html and OUTPUT/viewer/).
    #[arg(long)]
    no_page: bool,
    /// Do not keep network outputs in OUTPUT/cache/ (kept by default so re-runs skip the
    /// network).
    #[arg(long)]
    no_cache: bool,
    /// Keep network outputs in this folder instead of OUTPUT/cache/ (one shared by runs, or
    /// filled beforehand by `dens3r pairs --shard`).
    #[arg(long, value_name = "DIR", conflicts_with = "no_cache")]
    cache: Option<PathBuf>,
    /// Most MB the pair cache may take: the least recently used entries are removed to stay
    /// within it (entries are about 1.6 MB a photo at 512 px).
    #[arg(long, value_name = "MB")]
    cache_budget: Option<f64>,
    /// Match pictures for at most this many pairs (0: none).
    #[arg(long, default_value_t = 20)]
    match_pictures: usize,
    /// Benchmarks only: depth and normals read from this rendered scene folder with a
    /// network's errors instead of the network's (`dens3r bench scale`); the network still
    /// compares photos for --graph retrieval.
    #[arg(long, hide = true, value_name = "SCENE")]
    oracle: Option<PathBuf>,
    /// Shortest match track exported as a COLMAP 3-D point.
    #[arg(long, default_value_t = 2)]
    min_track: usize,
}

pub(crate) fn bar(prefix: &str, len: usize, unit: &str) -> ProgressBar {
    ProgressBar::new(len as u64).with_style(
        ProgressStyle::with_template(&format!("{prefix:>9} {{bar:30}} {{pos}}/{{len}} {unit} [{{elapsed}} < {{eta}}]"))
            .expect("valid template"),
    )
}

/// The pair cache in `dir` (none: memory only), within `budget_mb` when given.
pub(crate) fn open_cache(dir: Option<PathBuf>, budget_mb: Option<f64>) -> Result<PairCache> {
    Ok(match (dir, budget_mb) {
        (Some(d), Some(mb)) if mb.is_finite() && mb > 0.0 => PairCache::with_budget(d, (mb * 1e6) as u64),
        (_, Some(mb)) if !(mb.is_finite() && mb > 0.0) => {
            bail!("--cache-budget {mb}: expected a positive number of MB")
        }
        (d, _) => PairCache::new(d),
    })
}

/// The network's id in the pair cache: its files' content, input size and precision (another
/// size or precision gives other outputs).
pub(crate) fn network_id(
    m: &crate::model_args::ModelArgs,
    weights: &std::path::Path,
    config: Option<&std::path::Path>,
    cache: &PairCache,
) -> Result<String> {
    let precision = match m.precision {
        Precision::F32 => String::new(),
        p => format!(" {p}"),
    };
    Ok(network_cache_id(weights, config, cache, m.size, &precision)?)
}

/// The pair graph of `a`, after refusing options that cannot work.
fn checked_graph(a: &ReconstructArgs) -> Result<Option<PairGraph>> {
    crate::model_args::check_size(a.model.size)?;
    let graph = a.pairing.graph()?;
    if a.voxel.is_some_and(|v| !(v.is_finite() && v > 0.0)) {
        bail!("--voxel must be positive");
    }
    if !(a.budget_mb.is_finite() && a.budget_mb > 0.0) {
        bail!("--budget-mb must be positive");
    }
    if a.focal.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
        bail!("--focal must be a positive number of pixels (e.g. 1000 for a 4000-pixel-wide photo at 70 degrees)");
    }
    if let Some(m) = a.min_conf.filter(|m| !m.is_finite()) {
        bail!("--min-conf {m}: expected a finite confidence (e.g. 1.5; confidences are 1 + exp(x))");
    }
    Ok(graph)
}

/// What `load_photos` gives: the photos' paths, the photos, the model's settings, and the
/// warnings naming photos left out.
type Photos = (Vec<PathBuf>, Vec<dens3r_recon::InputImage>, dens3r_recon::model::ModelSettings, Vec<String>);

/// The photos of `a` that show a scene, decoded and preprocessed for the network, with their
/// focals and masks; their paths; the model's settings; the warnings naming photos left out.
fn load_photos(a: &ReconstructArgs, config: Option<&std::path::Path>) -> Result<Photos> {
    let settings = dens3r_recon::model::model_settings(config)?;
    let images = load_images(&list_images(&a.photos)?, a.model.size, a.model.keep_portrait || settings.keep_portrait)?;
    let (mut images, left_out) = scene_photos(images)?;
    let paths = images.iter().map(|im| im.path.clone()).collect();
    for im in &mut images {
        match a.focal {
            Some(f) => {
                im.check_focal(f, "--focal").map_err(|e| anyhow::anyhow!("{e}"))?;
                im.set_focal(Some(f))
            }
            None if a.no_exif_focal => im.set_focal(None),
            None => {}
        }
    }
    if let Some(dir) = &a.masks {
        dens3r_recon::attach_masks(&mut images, dir)?;
    }
    Ok((paths, images, settings, left_out))
}

/// The photos that show a scene ([`dens3r_recon::input::keep_scenes`]) and warnings naming
/// the others; fewer than two left is an error naming them.
pub fn scene_photos(images: Vec<dens3r_recon::InputImage>) -> Result<(Vec<dens3r_recon::InputImage>, Vec<String>)> {
    let (images, left_out) = dens3r_recon::input::keep_scenes(images);
    if images.len() < 2 {
        let why = if left_out.is_empty() { String::new() } else { format!(" ({})", left_out.join("; ")) };
        bail!("reconstruction needs at least 2 photos of a scene, got {}{why}", images.len());
    }
    Ok((images, left_out))
}

/// The reconstruction settings `a` asks for.
fn recon_options(a: &ReconstructArgs, graph: Option<PairGraph>) -> ReconOptions {
    ReconOptions {
        cameras: a.pairing.cameras(),
        graph,
        align: AlignOptions {
            iterations: a.iterations,
            optimize_focal: !a.fixed_focal,
            shared_focal: a.shared_focal,
            ..Default::default()
        },
        matching: MatchOptions::default(),
        tracks: TrackOptions { min_track: a.min_track, ..TrackOptions::default() },
        match_pose: (!a.no_match_pose).then(MatchPoseOptions::default),
        keypoints: (!a.no_keypoints).then(|| KeypointOptions {
            cycle_focal: (!a.no_cycle_focal).then(CycleFocalOptions::default),
            ..KeypointOptions::default()
        }),
        drop_unplaced: !a.keep_unplaced,
    }
}

/// One progress bar per stage, each with its ETA.
struct StageBars {
    keypoints: ProgressBar,
    retrieval: ProgressBar,
    pairs: ProgressBar,
    align: ProgressBar,
}

impl StageBars {
    fn new(iterations: usize) -> Self {
        Self {
            keypoints: bar("keypoints", 0, "photos"),
            retrieval: bar("retrieval", 0, "photos"),
            pairs: bar("pairs", 0, "pairs"),
            align: bar("align", iterations, "iterations"),
        }
    }

    /// Shows `done` of `total` on `stage`'s bar, the bars of the stages before it cleared.
    fn update(&self, stage: Stage, done: usize, total: usize) {
        let (b, before): (&ProgressBar, &[&ProgressBar]) = match stage {
            Stage::Keypoints => (&self.keypoints, &[]),
            Stage::Retrieve => (&self.retrieval, &[&self.keypoints]),
            Stage::Predict => (&self.pairs, &[&self.keypoints, &self.retrieval]),
            Stage::Align => (&self.align, &[&self.pairs]),
        };
        before.iter().for_each(|p| p.finish_and_clear());
        if stage != Stage::Align {
            b.set_length(total as u64);
        }
        b.set_position(done as u64);
    }

    fn finish(&self) {
        for b in [&self.keypoints, &self.retrieval, &self.pairs, &self.align] {
            b.finish_and_clear();
        }
    }
}

/// Where `reconstruct`'s dense geometry comes from.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Dense {
    /// Multi-view stereo with the network as its prior.
    Mvs,
    /// The network's depth alone, fused.
    Network,
}

pub fn run(a: ReconstructArgs) -> Result<()> {
    let graph = checked_graph(&a)?;
    let mvs_options = a.mvs.options()?;
    let (weights, config) = a.model.resolve()?;
    let t0 = Instant::now();
    // Every photo is decoded before the model loads: a bad photo fails in a second.
    let (paths, images, settings, left_out) = load_photos(&a, config.as_deref())?;
    let min_conf = a.min_conf.unwrap_or(settings.min_conf);
    let model = crate::model_args::load_network(&weights, config.as_deref(), a.gpu, a.model.precision)?;
    // The output folder is locked (a second run into it is refused) and staged from here;
    // the pair cache in it is written as it goes, so a rerun after a failure resumes.
    let out_dir = begin_outputs(&a.output)?;
    let cache = open_cache(a.cache.clone().or_else(|| (!a.no_cache).then(|| a.output.join("cache"))), a.cache_budget)?;
    let id = network_id(&a.model, &weights, config.as_deref(), &cache)?;
    let network = NetworkPredictor::new(&model, id);
    let oracle = a.oracle.as_deref().map(|dir| SceneOracle::new(dir, Some(&network))).transpose()?;
    let predictor: &dyn dens3r_recon::PairPredictor = match &oracle {
        Some(o) => o,
        None => &network,
    };
    let bars = StageBars::new(a.iterations);
    let mut rec = reconstruct(&images, predictor, &cache, &recon_options(&a, graph), |s, d, t| bars.update(s, d, t))?;
    bars.finish();
    rec.stats.warnings.splice(0..0, left_out);
    let out_opts = OutputOptions {
        voxel: a.voxel,
        min_conf,
        budget_bytes: (a.budget_mb * 1e6) as usize,
        gpu: a.gpu,
        mesh: !a.no_mesh,
        match_pictures: a.match_pictures,
        page: (!a.no_page).then(dens3r_viewer::PageOptions::default),
        mvs: match a.dense {
            Dense::Mvs => Some(mvs_options),
            Dense::Network => None,
        },
        ..Default::default()
    };
    let fbar = bar(if a.dense == Dense::Mvs { "dense" } else { "fuse" }, images.len(), "steps");
    let summary = write_outputs_into(&rec, &paths, &out_dir, &out_opts, |done, total| {
        fbar.set_length(total as u64);
        fbar.set_position(done as u64);
    })?;
    out_dir.finish()?;
    fbar.finish_and_clear();
    report(&a, &rec, &summary, min_conf, network.encoded_images(), t0);
    Ok(())
}

/// Prints what was reconstructed and where it went.
fn report(
    a: &ReconstructArgs,
    rec: &Reconstruction,
    summary: &OutputSummary,
    min_conf: f32,
    encoded: usize,
    t0: Instant,
) {
    let s = &rec.stats;
    for w in s.warnings.iter().chain(&summary.warnings) {
        eprintln!("warning: {w}");
    }
    let g = &s.graph;
    println!(
        "pair graph: {}, {} pairs{}",
        g.name,
        g.list.len(),
        if g.name.starts_with("retrieval") {
            format!(
                " (photos compared by the encoder in {:.1}s{})",
                g.seconds,
                if g.ordered { "; file order looks like the capture's: each photo also with the next 3" } else { "" }
            )
        } else {
            String::new()
        }
    );
    match &s.sfm {
        Some(sfm) => report_sfm(rec, sfm),
        None => report_dense(a, rec, encoded),
    }
    if let Some(m) = &summary.mvs {
        println!(
            "mvs: {} views at {}x{}, {:.1}s a view (median), {:.1}% of pixels kept by agreeing views, {} points -> {}",
            m.views,
            m.working_size.0,
            m.working_size.1,
            m.seconds_per_view,
            100.0 * m.kept_fraction,
            m.points,
            a.output.join("mvs").display()
        );
    }
    match &summary.mesh {
        Some(m) => println!(
            "mesh: {} triangles at voxel {:.4} in {:.1}s ({}; pixels of confidence {min_conf} or more{}) -> {}",
            summary.triangles,
            summary.voxel,
            summary.fuse_seconds,
            summary.gpu_adapter.as_deref().map_or("CPU".to_string(), |g| format!("GPU: {g}")),
            if a.masks.is_some() { ", within the masks" } else { "" },
            m.display()
        ),
        None if a.no_mesh => println!("mesh: skipped (--no-mesh)"),
        None => println!("mesh: none (see the warning above)"),
    }
    println!(
        "scene: {} (nerfstudio: transforms.json), COLMAP: {} (image path: the scene folder); total {:.1}s",
        summary.scene.display(),
        summary.colmap.display(),
        t0.elapsed().as_secs_f64()
    );
    if let Some(p) = &summary.page {
        println!(
            "page: {} in {:.1}s (open it in a browser, or `dens3r view {}`)",
            p.display(),
            summary.page_seconds,
            a.output.display()
        );
    }
}

/// The cameras' lines of a run on the dense path.
fn report_dense(a: &ReconstructArgs, rec: &Reconstruction, encoded: usize) {
    let s = &rec.stats;
    let tracks = rec.points.len();
    let nmatch: usize = rec.matches.iter().map(|m| m.2.len()).sum();
    println!(
        "{} photos, {} network pairs ({} from the cache; {} images encoded) in {:.1}s; {} matches in {:.1}s -> {} tracks",
        rec.names.len(),
        s.pairs - s.cache_hits,
        s.cache_hits,
        encoded,
        s.predict_seconds,
        nmatch,
        s.match_seconds,
        tracks
    );
    println!(
        "pairs placed by SIFT keypoints: {} of {}{}{} in {:.1}s{}; by the network's matches: {}{}; unplaced pairs left out: {}{}",
        s.posed_by_keypoints,
        s.pairs,
        if a.no_keypoints { " (--no-keypoints)" } else { "" },
        if s.keypoint_inconsistent > 0 {
            format!(" ({} more dropped: their rotation contradicted the others)", s.keypoint_inconsistent)
        } else {
            String::new()
        },
        s.keypoint_seconds,
        if s.fixed_rotations > 0 {
            format!(" (the rotations of the {} cameras they join averaged over them and kept)", s.fixed_rotations)
        } else {
            String::new()
        },
        s.posed_by_matches,
        if a.no_match_pose { " (--no-match-pose)" } else { "" },
        s.pairs_left_out,
        if a.keep_unplaced { " (--keep-unplaced)" } else { "" }
    );
    let known = match (&s.cycle_focal, a.focal) {
        (_, Some(_)) => "all given by --focal".to_string(),
        (Some(c), None) => format!(
            "all from the keypoint pairs' {} cycles, which close within {:.1} deg there against {:.1} at the network's {:.1}",
            c.cycles, c.residual_deg, c.start_residual_deg, c.start_focal
        ),
        (None, None) => "the rest estimated".to_string(),
    };
    println!(
        "alignment: residual {:.4} -> {:.4} (scene units) in {:.1}s; focals {} ({} of {} known, {known})",
        rec.alignment.loss.0,
        rec.alignment.loss.1,
        s.align_seconds,
        rec.alignment.views.iter().map(|v| format!("{:.1}", v.camera.intrinsics.fx)).collect::<Vec<_>>().join(", "),
        s.known_focals,
        rec.names.len()
    );
    println!(
        "tracks: {tracks} points ({} triangulated from the cameras, the rest placed by one view's depth)",
        s.triangulated_points
    );
}

/// The cameras' lines of a run whose cameras came from structure-from-motion.
fn report_sfm(rec: &Reconstruction, sfm: &dens3r_sfm::SfmStats) {
    let s = &rec.stats;
    println!(
        "{} photos: {} network passes for depth and normals ({} from the cache) in {:.1}s; SIFT in {:.1}s",
        s.registered + s.unregistered.len(),
        s.pairs - s.cache_hits,
        s.cache_hits,
        s.predict_seconds,
        s.keypoint_seconds
    );
    let [m, v, r, p, b] = sfm.seconds;
    println!(
        "structure from motion: {} of {} photos registered; pairs: {} matched, {} verified, {} consistent; \
         {} tracks ({} ambiguous dropped) -> {} points, {} observations; reprojection RMS {:.2} -> {:.2} px; \
         {:.1}s (matching {m:.1}, verification {v:.1}, rotations {r:.1}, positions {p:.1}, bundle adjustment {b:.1}{})",
        s.registered,
        s.registered + s.unregistered.len(),
        sfm.matched_pairs,
        sfm.verified_pairs,
        sfm.consistent_pairs,
        sfm.tracks,
        sfm.ambiguous_tracks,
        rec.points.len(),
        sfm.observations,
        sfm.rms_px.0,
        sfm.rms_px.1,
        s.align_seconds,
        if sfm.passes > 1 { format!("; {} passes: adjustment moved the focal", sfm.passes) } else { String::new() }
    );
    let mut focals: Vec<String> =
        rec.alignment.views.iter().map(|v| format!("{:.1}", v.camera.intrinsics.fx)).collect();
    focals.dedup();
    println!(
        "focals: {} px ({} of {} known, the rest refined by bundle adjustment); depth: the network's, scaled per photo onto the points",
        focals.join(", "),
        s.known_focals,
        s.registered
    );
}
