//! `dens3r predict`: images -> scene folder (depth, normals, confidence, intrinsics, pointmaps,
//! visualisations), and trained heads (`--head`) on the same backbone pass.

use crate::model_args::{load_network, open_backbone, resolve_model};
use anyhow::{bail, Context, Result};
use clap::Args;
use dens3r_backbone::predict::{predict_mono, predict_mono_features, to_image_grid, MonoPrediction, Resolution};
use dens3r_backbone::preprocess::{open_oriented, preprocess, Prepared};
use dens3r_geom::{focal_from_pointmap, DMat4, FocalMode, Intrinsics, NormalConvention, PinholeCamera, Raster, Vec3};
use dens3r_heads::data::resize_nearest;
use dens3r_heads::features::file_hash;
use dens3r_heads::infer::{check_head, infer, overlay, write_label_png, HeadOutput};
use dens3r_heads::{Backbone, Dens3rBackbone, Head, Task};
use dens3r_mesh::TriMesh;
use dens3r_scene::{Frame, SceneWriter};
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
    /// Long side of the network input (512, or 1024 for more detail).
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// Keep portrait images as they are (upstream DUSt3R / MASt3R) instead of rotating them.
    #[arg(long)]
    keep_portrait: bool,
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
    /// Input images (PNG or JPEG).
    #[arg(required = true)]
    images: Vec<PathBuf>,
    /// Output folder (a scene folder when the network runs).
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the scene folder OUTPUT already holds (the new one is written beside it and
    /// swapped in at the end, so images read from it stay intact until then).
    #[arg(long)]
    overwrite: bool,
    /// Run the network on the GPU (the default build's `gpu-network` feature, or `cuda`).
    #[arg(long)]
    gpu: bool,
}

/// The error for an output folder that already holds a scene, unless `--overwrite`: a scene
/// is never rewritten silently (its images may be this run's inputs).
pub fn refuse_existing_scene(out: &Path, overwrite: bool) -> Result<()> {
    if !overwrite && dens3r_scene::holds_scene(out) {
        bail!(
            "{}: already holds a scene (cameras.json); write to a new folder, or pass --overwrite to replace it",
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

pub fn run(a: PredictArgs) -> Result<()> {
    crate::model_args::check_size(a.size)?;
    for p in &a.images {
        if !p.is_file() {
            bail!("{}: image not found", p.display());
        }
    }
    refuse_existing_scene(&a.output, a.overwrite)?;
    let heads = load_heads(&a.heads)?;
    // The network runs unless only heads on another backbone are asked for; without
    // --weights it is the bundled default model.
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
    // Heads on the network's own pass: it is wrapped as a feature backbone.
    let heads_on_net = !heads.is_empty() && other.is_none();
    let net = if run_net {
        let (weights, config) = resolve_model(a.weights.as_deref(), a.config.as_deref())?;
        let model = load_network(&weights, config.as_deref(), a.gpu)?;
        let hash = if heads_on_net {
            file_hash(&weights).with_context(|| format!("{}: cannot read", weights.display()))?
        } else {
            0
        };
        Some(Dens3rBackbone::new(model, None, hash).map_err(anyhow::Error::msg)?)
    } else {
        None
    };
    let head_backbone: Option<&dyn Backbone> = match (&other, &net) {
        (Some((b, _)), _) => Some(b.as_ref()),
        (None, n) => n.as_ref().map(|n| n as &dyn Backbone),
    };
    if let Some(b) = head_backbone {
        let (id, dims) = (b.id(), b.dims());
        for (h, path) in heads.iter().zip(&a.heads) {
            check_head(path, &h.head, &id, &dims).map_err(anyhow::Error::msg)?;
        }
    }

    // Decode and preprocess everything first: a bad image fails before anything is written.
    // The photo itself is kept only where it is read again (original size, another backbone).
    let keep_source = a.original_size || other.is_some();
    let mut inputs = Vec::new();
    let mut names = HashSet::new();
    for p in &a.images {
        let img = open_oriented(p).map_err(anyhow::Error::msg)?;
        let prep = preprocess(&img, a.size, !a.keep_portrait).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        let name = dens3r_recon::input::unique_name(p, &mut names);
        inputs.push((name, prep, keep_source.then(|| img.to_rgb8())));
    }
    let mut writer = match &net {
        Some(_) => {
            let mut w = SceneWriter::create(&a.output)?;
            w.set_extra("generator", serde_json::json!("dens3r predict"));
            Some(w)
        }
        None => {
            std::fs::create_dir_all(&a.output).with_context(|| format!("{}: cannot create", a.output.display()))?;
            None
        }
    };
    // Every file goes where the writer writes (a staging folder while a scene is replaced).
    let root = writer.as_ref().map_or_else(|| a.output.clone(), |w| w.root().to_path_buf());
    for h in &heads {
        let dir = root.join("heads").join(&h.stem);
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        if let Task::Seg { classes } = &h.head.config.task {
            let map = classes.iter().enumerate().map(|(i, c)| (i as u16, c.clone())).collect();
            dens3r_scene::write_classes(&dir.join("classes.json"), &map)?;
        }
    }
    let bar = indicatif::ProgressBar::new(inputs.len() as u64).with_style(
        indicatif::ProgressStyle::with_template("predict {bar:30} {pos}/{len} images [{elapsed} < {eta}]")
            .expect("valid template"),
    );
    let res = if a.original_size { Resolution::Original } else { Resolution::Network };
    let device = burn::tensor::Device::flex();
    for (name, prep, source) in &inputs {
        // The picture every map of this image is written at (overlays are drawn on it).
        let mut picture = None;
        if let (Some(net), Some(writer)) = (&net, writer.as_mut()) {
            let (mut pred, features) = if heads_on_net {
                let (p, v) = predict_mono_features(net.model(), prep, res);
                (p, Some(net.maps(&v)))
            } else {
                (predict_mono(net.model(), prep, res), None)
            };
            if let Some(src) = source.as_ref().filter(|_| a.original_size) {
                pred.rgb = src.clone();
            }
            write_network_outputs(writer, &root, name, prep, &pred)?;
            if let Some(f) = features {
                for h in &heads {
                    // The network frame back to the image's orientation and map size.
                    let size = (f.grid.0 * h.head.config.patch, f.grid.1 * h.head.config.patch);
                    let out = match infer(&h.head, &f, &device) {
                        HeadOutput::Labels(l) => HeadOutput::Labels(to_image_grid(l, 1, size, &prep.info, res).0),
                        HeadOutput::Depth(d) => HeadOutput::Depth(to_image_grid(d, 1, size, &prep.info, res).0),
                    };
                    write_head_output(&root, h, name, out, &pred.rgb)?;
                }
            }
            picture = Some(pred.rgb);
        }
        if let (Some((b, long)), Some(src)) = (&other, source) {
            let img = dens3r_heads::data::resize_to_patches(src.clone(), *long, b.patch() as u32);
            let f = b.extract(&img);
            // Heads only: at their input size, or the photo's with --original-size.
            let (iw, ih) = (img.width() as usize, img.height() as usize);
            let picture = picture.unwrap_or_else(|| if a.original_size { src.clone() } else { img });
            let (ow, oh) = (picture.width() as usize, picture.height() as usize);
            for h in &heads {
                let out = match infer(&h.head, &f, &device) {
                    HeadOutput::Labels(l) => HeadOutput::Labels(resize_nearest(&l, iw, ih, ow, oh)),
                    HeadOutput::Depth(d) => HeadOutput::Depth(resize_nearest(&d, iw, ih, ow, oh)),
                };
                write_head_output(&root, h, name, out, &picture)?;
            }
        }
        bar.inc(1);
    }
    if let Some(w) = writer {
        w.finish()?;
    }
    bar.finish_and_clear();
    let what = match (&net, heads.len()) {
        (Some(_), 0) => "depth, normals, confidence, intrinsics and pointmaps".to_string(),
        (Some(_), n) => format!("depth, normals, confidence, intrinsics, pointmaps and {n} head(s)"),
        (None, n) => format!("{n} head(s)"),
    };
    println!(
        "predicted {what} for {} images into {} (maps at {} size{})",
        inputs.len(),
        a.output.display(),
        if a.original_size { "original" } else { "network" },
        if net.is_some() { ", normals in the OpenCV camera frame" } else { "" }
    );
    Ok(())
}

/// Reads every head, naming its outputs after its file stem (made unique).
fn load_heads(paths: &[PathBuf]) -> Result<Vec<NamedHead>> {
    let mut stems = HashSet::new();
    paths
        .iter()
        .map(|p| {
            let head = Head::load(p).map_err(anyhow::Error::msg)?;
            let stem = dens3r_recon::input::unique_name(p, &mut stems);
            Ok(NamedHead { stem, head })
        })
        .collect()
}

/// `heads/HEAD/NAME.png` (labels) or `.npy` (depth), and `viz/NAME_HEAD.png`.
fn write_head_output(root: &Path, h: &NamedHead, name: &str, out: HeadOutput, rgb: &image::RgbImage) -> Result<()> {
    let dir = root.join("heads").join(&h.stem);
    let viz = root.join("viz").join(format!("{name}_{}.png", h.stem));
    let (w, hh) = (rgb.width(), rgb.height());
    match out {
        HeadOutput::Labels(l) => {
            write_label_png(&dir.join(format!("{name}.png")), &l, w, hh).map_err(anyhow::Error::msg)?;
            dens3r_scene::write_rgb_png(&viz, &overlay(rgb, &l))?;
        }
        HeadOutput::Depth(d) => {
            dens3r_scene::npy::write_f32(&dir.join(format!("{name}.npy")), &[hh as usize, w as usize], &d)?;
            let r = Raster::from_vec(w as usize, hh as usize, d).expect("sizes follow the image");
            dens3r_scene::write_rgb_png(&viz, &depth_viz(&r))?;
        }
    }
    Ok(())
}

/// The Dens3R maps of one image into the scene folder.
fn write_network_outputs(
    writer: &mut SceneWriter,
    root: &Path,
    name: &str,
    prep: &Prepared,
    pred: &MonoPrediction,
) -> Result<()> {
    let (w, h) = (pred.depth.width(), pred.depth.height());
    let pp = (w as f64 / 2.0, h as f64 / 2.0);
    let estimated = focal_from_pointmap(&pred.points, pp, FocalMode::Weiszfeld).filter(|f| f.is_finite() && *f > 0.0);
    let intrinsics = match estimated {
        Some(f) => Intrinsics { fx: f, fy: f, cx: pp.0, cy: pp.1 },
        None => {
            eprintln!("warning: {name}: the pointmap gives no positive focal (untrained weights?); using a 60-degree field of view");
            Intrinsics::from_hfov(w, h, 60.0)
        }
    };
    let cam = PinholeCamera { intrinsics, width: w, height: h, cam_to_world: DMat4::IDENTITY };
    let mut frame = Frame::new(name, &cam);
    frame.extra.insert("focal_estimated".into(), serde_json::json!(estimated.is_some()));
    frame.extra.insert("source".into(), serde_json::json!(prep.info.original));
    frame.extra.insert("rotated".into(), serde_json::json!(prep.info.rotated));
    writer.add_frame(frame, &pred.rgb)?;
    writer.write_depth(name, &pred.depth)?;
    if let Some(n) = &pred.normals {
        writer.write_normals(name, n)?;
        dens3r_scene::write_rgb_png(&root.join("viz").join(format!("{name}_normal.png")), &normal_viz(n))?;
    }
    if let Some(c) = &pred.conf {
        writer.write_conf(name, c)?;
    }
    dens3r_scene::write_rgb_png(&root.join("viz").join(format!("{name}_depth.png")), &depth_viz(&pred.depth))?;
    let mut cloud = TriMesh::new(pred.points.data().iter().copied().filter(|p| p.is_finite()).collect(), Vec::new());
    let colors: Vec<[u8; 3]> =
        pred.points.data().iter().zip(pred.rgb.pixels()).filter(|(p, _)| p.is_finite()).map(|(_, c)| c.0).collect();
    cloud.colors = Some(colors);
    dens3r_mesh::write_mesh(&root.join("pointmaps").join(format!("{name}.ply")), &cloud)?;
    Ok(())
}

/// The official normal visualisation (spec 3.3) of the Dens3R saved convention:
/// R = (nx+1)/2, G = (ny+1)/2, B = -nz*127+128; a camera-facing wall is (128, 128, 255).
fn normal_viz(n: &Raster<Vec3>) -> image::RgbImage {
    image::RgbImage::from_fn(n.width() as u32, n.height() as u32, |x, y| {
        let s = NormalConvention::Dens3rSaved.from_opencv(*n.get(x as usize, y as usize));
        let c = |v: f32| v.clamp(0.0, 255.0) as u8;
        image::Rgb([c((s.x + 1.0) / 2.0 * 255.0), c((s.y + 1.0) / 2.0 * 255.0), c(-s.z * 127.0 + 128.0)])
    })
}

/// Depth coloured with a Spectral-like ramp between the 2nd and 85th percentiles (spec 3.3).
fn depth_viz(d: &Raster<f32>) -> image::RgbImage {
    let mut v: Vec<f32> = d.data().iter().copied().filter(|x| *x > 0.0 && x.is_finite()).collect();
    v.sort_by(f32::total_cmp);
    let q = |p: f32| v.get(((v.len().max(1) - 1) as f32 * p) as usize).copied().unwrap_or(0.0);
    let (lo, hi) = (q(0.02), q(0.85).max(q(0.02) + 1e-6));
    const RAMP: [[f32; 3]; 5] =
        [[158.0, 1.0, 66.0], [244.0, 109.0, 67.0], [255.0, 255.0, 191.0], [102.0, 194.0, 165.0], [94.0, 79.0, 162.0]];
    image::RgbImage::from_fn(d.width() as u32, d.height() as u32, |x, y| {
        let z = *d.get(x as usize, y as usize);
        if z.is_nan() || z <= 0.0 {
            return image::Rgb([0, 0, 0]);
        }
        let t = ((z - lo) / (hi - lo)).clamp(0.0, 1.0) * 4.0;
        let (i, f) = ((t.floor() as usize).min(3), t - t.floor().min(3.0));
        image::Rgb(std::array::from_fn(|k| (RAMP[i][k] + (RAMP[i + 1][k] - RAMP[i][k]) * f) as u8))
    })
}
