//! `dens3r predict`: images -> scene folder (depth, normals, confidence, intrinsics, pointmaps,
//! visualisations), and trained heads (`--head`) on the same backbone pass.

use crate::model_args::{load_network, open_backbone, resolve_model};
use anyhow::{bail, Context, Result};
use clap::Args;
use dens3r_backbone::predict::{predict_mono, predict_mono_features, to_image_grid, Resolution, TestTimePasses};
use dens3r_backbone::preprocess::{decode_oriented, preprocess, Prepared};
use dens3r_geom::FALLBACK_HFOV_DEG;
use dens3r_heads::data::resize_nearest;
use dens3r_heads::features::file_hash;
use dens3r_heads::infer::{check_head, infer, write_head_output, HeadOutput};
use dens3r_heads::{Backbone, Dens3rBackbone, Head, Task};
use dens3r_recon::mono::{write_mono_frame, FocalSource};
use dens3r_scene::SceneWriter;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct PredictArgs {
    /// Dens3R checkpoint (.safetensors, .pth or a Hugging Face folder) for depth, normals,
    /// confidence, intrinsics and pointmaps; default: the bundled dens3r-s (not run when only
    /// --head outputs on another --backbone are asked for).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// JSON with the head counts (enc_num_heads, dec_num_heads, or the converter's "args");
    /// default: head dim 64.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Long side of the network input (512, or 1024 for more detail; `512x384` is read as its
    /// long side).
    #[arg(long, default_value_t = 512, value_parser = crate::model_args::parse_long_side)]
    size: u32,
    /// Keep portrait images as they are (upstream DUSt3R / MASt3R) instead of rotating them to
    /// landscape as the official Dens3R does (a model whose config says `"keep_portrait": true`,
    /// dens3r-s included, keeps them without it).
    #[arg(long)]
    keep_portrait: bool,
    /// Also run the network at these fractions of --size and average the depth (geometric
    /// mean after matching medians) and normals into the --size prediction (test-time
    /// augmentation; each costs one more network pass). Default: the model's config
    /// (`"tta_scales"`; dens3r-s: 0.75), else none.
    #[arg(long, value_delimiter = ',', conflicts_with = "no_tta")]
    tta_scales: Option<Vec<f64>>,
    /// Those extra passes see the photo mirrored left-right (read back mirrored). Default: the
    /// model's config (`"tta_mirror"`; dens3r-s: true), else not.
    #[arg(long, conflicts_with_all = ["no_tta", "no_tta_mirror"])]
    tta_mirror: bool,
    /// Those extra passes see the photo as it is, whatever the model's config says.
    #[arg(long, conflicts_with = "no_tta")]
    no_tta_mirror: bool,
    /// One network pass at --size only, whatever the model's config says.
    #[arg(long)]
    no_tta: bool,
    /// A head written by `dens3r train-head` (its .json); repeat for several. Every head runs
    /// on the same backbone pass: the Dens3R network of --weights for heads trained on it,
    /// else the backbone of --backbone. Outputs go to OUTPUT/heads/HEAD/ (label PNGs with
    /// the VOC palette + classes.json, or depth .npy) and OUTPUT/viz/.
    #[arg(long = "head")]
    heads: Vec<PathBuf>,
    /// Backbone of the heads when it is not the --weights network: `dinov2:MODEL.onnx`,
    /// `dens3r:WEIGHTS.safetensors` or `pixels`, as given to train-head.
    #[arg(long)]
    backbone: Option<String>,
    /// Write every map at the original image size (the official `rescale_to_orig`: edge
    /// padding, nearest neighbour) with the original pixels as colours, so depth, normals and
    /// intrinsics line up with the input photos (COLMAP, nerfstudio). Default: network size.
    #[arg(long)]
    original_size: bool,
    /// Focal length in pixels of the photos as read (after their EXIF orientation, before
    /// resizing), for every image: the cameras take it and the pointmaps follow. Without it a
    /// photo's EXIF 35 mm equivalent focal length is used where it has one, and the rest are
    /// estimated from the pointmap.
    #[arg(long)]
    focal: Option<f64>,
    /// Ignore the photos' EXIF focal lengths: estimate every focal not given by --focal.
    #[arg(long)]
    no_exif_focal: bool,
    /// Input images (PNG, JPEG, PGM or PPM).
    #[arg(required = true)]
    images: Vec<PathBuf>,
    /// Output folder (a scene folder when the network runs).
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the outputs of an earlier dens3r run in OUTPUT (the new ones are staged and
    /// moved in at the end, so images read from it stay intact until then; files of yours
    /// there are never touched).
    #[arg(long)]
    overwrite: bool,
    /// Run the network on the GPU (the default build's `gpu-network` feature, or `cuda`).
    #[arg(long)]
    gpu: bool,
    /// What the network computes in: f32 (the reference), or f16 / bf16 for speed on a GPU;
    /// on the CPU bf16 takes the linear layers' and attention's products in bf16 (faster on CPUs with AVX-512
    /// BF16) and f16 is slower (`dens3r verify --precision` measures their error).
    #[arg(long, default_value_t = dens3r_backbone::Precision::F32)]
    precision: dens3r_backbone::Precision,
}

/// The error for an output folder that already holds a scene, unless `--overwrite`: a scene
/// is never rewritten silently (its images may be this run's inputs). A scene dens3r did not
/// write (no list of its outputs: by hand, another tool) is refused even with `--overwrite`.
pub fn refuse_existing_scene(out: &Path, overwrite: bool) -> Result<()> {
    if overwrite && dens3r_scene::holds_scene(out) && matches!(dens3r_io::output::Manifest::read(out), Ok(None)) {
        bail!(
            "{}: holds a scene dens3r did not write (no {}), so --overwrite does not replace it; write to a new folder, or move its files out first",
            out.display(),
            dens3r_io::output::MANIFEST
        );
    }
    if !overwrite && dens3r_scene::holds_scene(out) {
        bail!(
            "{}: already holds a scene (cameras.json); write to a new folder, or pass --overwrite to replace it",
            out.display()
        );
    }
    if !overwrite && dens3r_io::output::holds_outputs(out) {
        bail!(
            "{}: already holds the outputs of an earlier dens3r run; write to a new folder, or pass --overwrite to replace them",
            out.display()
        );
    }
    Ok(())
}

/// A loaded head and where its outputs go.
struct NamedHead {
    stem: String,
    head: Head,
}

/// What runs: the Dens3R network (wrapped as a feature backbone for heads on its pass), the
/// heads, and the other backbone with the heads' input size when they were trained on one.
struct Networks {
    net: Option<Dens3rBackbone>,
    /// Portrait images go in unrotated (`--keep-portrait`, or the network's config says so).
    keep_portrait: bool,
    /// The extra network passes averaged in (`--tta-scales`, `--tta-mirror` or the config's).
    tta: TestTimePasses,
    heads: Vec<NamedHead>,
    other: Option<(Box<dyn Backbone>, u32)>,
}

impl Networks {
    fn heads_on_net(&self) -> bool {
        !self.heads.is_empty() && self.other.is_none()
    }
}

/// An input image: its unique name, the network input, and the photo where it is read again.
/// One image: frame name, network input, the photo where it is read again, its known focal
/// (pixels of the photo as read) with the source, and its inputs at the extra sizes.
type Input = (String, Prepared, Option<image::RgbImage>, Option<(f64, FocalSource)>, Vec<Prepared>);

pub fn run(a: PredictArgs) -> Result<()> {
    crate::model_args::check_size(a.size)?;
    if a.focal.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
        bail!("--focal must be a positive number of pixels (e.g. 1000 for a 4000-pixel-wide photo at 70 degrees)");
    }
    for p in &a.images {
        if p.is_dir() {
            bail!("{}: is a folder, not an image; give the photos in it (e.g. {}/*.jpg)", p.display(), p.display());
        }
        if !p.is_file() {
            bail!("{}: image not found", p.display());
        }
    }
    refuse_existing_scene(&a.output, a.overwrite)?;
    let nets = load_networks(&a)?;
    let inputs = load_inputs(&a, &nets)?;
    let out = dens3r_scene::begin_output(&a.output)?;
    // A photo (or other file of the user's) where a frame's outputs go is refused now, not
    // after the network ran.
    out.check_free(&planned_outputs(&inputs, &nets))?;
    // Every file goes to the staging folder, moved into OUTPUT at the end.
    let root = out.root().to_path_buf();
    let mut writer = match &nets.net {
        Some(_) => {
            let mut w = SceneWriter::in_folder(&root)?;
            w.set_extra("generator", serde_json::json!("dens3r predict"));
            Some(w)
        }
        None => None,
    };
    create_head_folders(&root, &nets.heads)?;
    let bar = indicatif::ProgressBar::new(inputs.len() as u64).with_style(
        indicatif::ProgressStyle::with_template("predict {bar:30} {pos}/{len} images [{elapsed} < {eta}]")
            .expect("valid template"),
    );
    for input in &inputs {
        predict_one(&a, &nets, writer.as_mut(), &root, input)?;
        bar.inc(1);
    }
    let mut page = None;
    if let Some(w) = writer {
        w.finish()?;
        let title = dens3r_viewer::title_of(&a.output);
        let summary = serde_json::json!({ "photos": inputs.len(), "maps": if a.original_size { "photo size" } else { "network size" } });
        let opts = dens3r_viewer::PageOptions::default();
        dens3r_viewer::scene_views::write_scene_page(&root, "", &title, Some(summary), true, &opts)?;
        page = Some(a.output.join("index.html"));
    }
    out.finish()?;
    bar.finish_and_clear();
    let what = match (&nets.net, nets.heads.len()) {
        (Some(_), 0) => "depth, normals, confidence, intrinsics and pointmaps".to_string(),
        (Some(_), n) => format!("depth, normals, confidence, intrinsics, pointmaps and {n} head(s)"),
        (None, n) => format!("{n} head(s)"),
    };
    println!(
        "predicted {what} for {} images into {} (maps at {} size{})",
        inputs.len(),
        a.output.display(),
        if a.original_size { "original" } else { "network" },
        if nets.net.is_some() { ", normals in the OpenCV camera frame" } else { "" }
    );
    if let Some(p) = page {
        println!("page: {} (open it in a browser, or `dens3r view {}`)", p.display(), a.output.display());
    }
    Ok(())
}

/// The heads, the network (unless only heads on another backbone are asked for; without
/// --weights it is the bundled default model) and the heads' other backbone, each head checked
/// against the backbone it will run on.
fn load_networks(a: &PredictArgs) -> Result<Networks> {
    let heads = load_heads(&a.heads)?;
    let run_net = a.weights.is_some() || a.heads.is_empty() || a.backbone.is_none();
    // A head trained on another backbone needs that backbone named, not the default network.
    if let Some((h, path)) = heads.iter().zip(&a.heads).find(|(h, _)| !h.head.config.backbone.starts_with("dens3r")) {
        if a.weights.is_none() && a.backbone.is_none() {
            bail!(
                "{}: the head needs its backbone ({}): give --backbone (dinov2:MODEL.onnx, pixels)",
                path.display(),
                h.head.config.backbone
            );
        }
    }
    // Heads on another backbone: it runs on each image resized to the heads' training size.
    let other = match a.backbone.as_deref() {
        Some(spec) => {
            let size = heads.iter().map(|h| h.head.config.size).find(|&s| s > 0).unwrap_or(224);
            Some((open_backbone(spec, a.config.as_deref())?, size))
        }
        None => None,
    };
    let heads_on_net = !heads.is_empty() && other.is_none();
    let mut keep_portrait = a.keep_portrait;
    let mut tta = TestTimePasses::default();
    let net = if run_net {
        let (weights, config) = resolve_model(a.weights.as_deref(), a.config.as_deref())?;
        let settings = dens3r_recon::model::model_settings(config.as_deref())?;
        keep_portrait |= settings.keep_portrait;
        let scales = if a.no_tta { Vec::new() } else { a.tta_scales.clone().unwrap_or(settings.tta_scales) };
        tta.sizes = dens3r_recon::model::tta_sizes(&scales, a.size).context("--tta-scales")?;
        tta.mirrored = (a.tta_mirror || settings.tta_mirror) && !a.no_tta_mirror;
        if a.tta_mirror && tta.sizes.is_empty() {
            bail!("--tta-mirror: this model runs no extra pass to mirror; add --tta-scales (e.g. 0.75, or 1 for a mirrored pass at --size)");
        }
        let model = load_network(&weights, config.as_deref(), a.gpu, a.precision)?;
        let hash = if heads_on_net {
            file_hash(&weights).with_context(|| format!("{}: cannot read", weights.display()))?
        } else {
            0
        };
        Some(Dens3rBackbone::new(model, None, hash)?)
    } else {
        None
    };
    let nets = Networks { net, keep_portrait, tta, heads, other };
    let head_backbone: Option<&dyn Backbone> = match (&nets.other, &nets.net) {
        (Some((b, _)), _) => Some(b.as_ref()),
        (None, n) => n.as_ref().map(|n| n as &dyn Backbone),
    };
    if let Some(b) = head_backbone {
        let (id, dims) = (b.id(), b.dims());
        for (h, path) in nets.heads.iter().zip(&a.heads) {
            check_head(path, &h.head, &id, &dims)?;
        }
    }
    Ok(nets)
}

/// Decodes and preprocesses every image before anything is written, so a bad image fails
/// first. The photo itself is kept only where it is read again (original size, another
/// backbone).
fn load_inputs(a: &PredictArgs, nets: &Networks) -> Result<Vec<Input>> {
    let keep_source = a.original_size || nets.other.is_some();
    let keep_portrait = nets.keep_portrait;
    let mut names = HashSet::new();
    a.images
        .iter()
        .map(|p| {
            let bytes = std::fs::read(p).with_context(|| format!("{}: cannot read", p.display()))?;
            let img = decode_oriented(p, &bytes)?;
            let prep = preprocess(&img, a.size, !keep_portrait).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            // (Empty unless the network runs.)
            let extra = nets.tta.prepare(&img, !keep_portrait).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            let name = dens3r_recon::input::unique_name(p, &mut names);
            let focal = match a.focal {
                Some(f) => {
                    dens3r_recon::input::check_focal(f, img.width() as f64, "--focal")
                        .map_err(|e| anyhow::anyhow!("{e} ({})", p.display()))?;
                    Some((f, FocalSource::Given))
                }
                None if a.no_exif_focal => None,
                None => match dens3r_recon::input::exif_focal(&bytes, (img.width(), img.height())) {
                    Ok(f) => f.map(|f| (f, FocalSource::Exif)),
                    Err(w) => {
                        eprintln!("warning: {}: {w}", p.display());
                        None
                    }
                },
            };
            Ok((name, prep, keep_source.then(|| img.to_rgb8()), focal, extra))
        })
        .collect()
}

/// The files predict writes for its frames (relative to OUTPUT), checked free before it runs.
fn planned_outputs(inputs: &[Input], nets: &Networks) -> Vec<String> {
    let mut files = vec!["cameras.json".to_string()];
    if nets.net.is_some() {
        files.extend(dens3r_viewer::PAGE_FILES.iter().map(|f| f.to_string()));
    }
    for (name, ..) in inputs {
        if nets.net.is_some() {
            for f in ["images/{}.png", "depth/{}.npy", "normals/{}.npy", "conf/{}.npy", "pointmaps/{}.ply"] {
                files.push(f.replace("{}", name));
            }
            files.push(format!("viz/{name}_depth.png"));
            files.push(format!("viz/{name}_normal.png"));
        }
        for h in &nets.heads {
            files.push(format!("viz/{name}_{}.png", h.stem));
        }
    }
    files
}

/// `heads/HEAD/` for every head, with its `classes.json` for segmentation heads.
fn create_head_folders(root: &Path, heads: &[NamedHead]) -> Result<()> {
    for h in heads {
        let dir = root.join("heads").join(&h.stem);
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        if let Task::Seg { classes } = &h.head.config.task {
            let map = classes.iter().enumerate().map(|(i, c)| (i as u16, c.clone())).collect();
            dens3r_scene::write_classes(&dir.join("classes.json"), &map)?;
        }
    }
    Ok(())
}

/// Every output of one image: the network's maps as a scene frame with the heads on the same
/// pass, or the heads on the other backbone.
fn predict_one(
    a: &PredictArgs,
    nets: &Networks,
    writer: Option<&mut SceneWriter>,
    root: &Path,
    (name, prep, source, focal, extra): &Input,
) -> Result<()> {
    let res = if a.original_size { Resolution::Original } else { Resolution::Network };
    let device = burn::tensor::Device::flex();
    // The picture every map of this image is written at (overlays are drawn on it).
    let mut picture = None;
    if let (Some(net), Some(writer)) = (&nets.net, writer) {
        // Nothing written here reads the descriptors.
        let want = dens3r_backbone::HeadOutputs { normal: true, desc: false };
        let (pred, features) = if nets.heads_on_net() {
            let (p, v) = predict_mono_features(net.model(), prep, res, want);
            (p, Some(net.maps(&v)))
        } else {
            (predict_mono(net.model(), prep, res, want), None)
        };
        let mut pred = nets.tta.merge(net.model(), pred, res, extra, want);
        if let Some(src) = source.as_ref().filter(|_| a.original_size) {
            pred.rgb = src.clone();
        }
        // A known focal in pixels of the maps written: the photo's at --original-size, else
        // scaled by the resize (cropping keeps it).
        let scale = if a.original_size { 1.0 } else { prep.info.resize_factor() };
        let known = focal.map(|(f, s)| (f * scale, s));
        if write_mono_frame(writer, name, &pred, known)? == FocalSource::Fallback {
            eprintln!(
                "warning: {name}: the pointmap gives no positive focal (untrained weights?); using a {FALLBACK_HFOV_DEG}-degree field of view"
            );
        }
        if let Some(f) = &features {
            for h in &nets.heads {
                // The network frame back to the image's orientation and map size.
                let size = (f.grid.0 * h.head.config.patch, f.grid.1 * h.head.config.patch);
                let out = match infer(&h.head, f, &device) {
                    HeadOutput::Labels(l) => HeadOutput::Labels(to_image_grid(l, 1, size, &prep.info, res).0),
                    HeadOutput::Depth(d) => HeadOutput::Depth(to_image_grid(d, 1, size, &prep.info, res).0),
                };
                write_head(root, h, name, &out, &pred.rgb)?;
            }
        }
        picture = Some(pred.rgb);
    }
    if let (Some((b, long)), Some(src)) = (&nets.other, source) {
        let img = dens3r_heads::data::resize_to_patches(src.clone(), *long, b.patch() as u32);
        let f = b.extract(&img);
        // Heads only: at their input size, or the photo's with --original-size.
        let (iw, ih) = (img.width() as usize, img.height() as usize);
        let picture = picture.unwrap_or_else(|| if a.original_size { src.clone() } else { img });
        let (ow, oh) = (picture.width() as usize, picture.height() as usize);
        for h in &nets.heads {
            let out = match infer(&h.head, &f, &device) {
                HeadOutput::Labels(l) => HeadOutput::Labels(resize_nearest(&l, iw, ih, ow, oh)),
                HeadOutput::Depth(d) => HeadOutput::Depth(resize_nearest(&d, iw, ih, ow, oh)),
            };
            write_head(root, h, name, &out, &picture)?;
        }
    }
    Ok(())
}

/// Reads every head, naming its outputs after its file stem (made unique).
fn load_heads(paths: &[PathBuf]) -> Result<Vec<NamedHead>> {
    let mut stems = HashSet::new();
    paths
        .iter()
        .map(|p| {
            let head = Head::load(p)?;
            let stem = dens3r_recon::input::unique_name(p, &mut stems);
            Ok(NamedHead { stem, head })
        })
        .collect()
}

/// `heads/HEAD/NAME.png` (labels) or `.npy` (depth), and `viz/NAME_HEAD.png`.
fn write_head(root: &Path, h: &NamedHead, name: &str, out: &HeadOutput, rgb: &image::RgbImage) -> Result<()> {
    let viz = root.join("viz").join(format!("{name}_{}.png", h.stem));
    Ok(write_head_output(&root.join("heads").join(&h.stem), &viz, name, out, rgb)?)
}
