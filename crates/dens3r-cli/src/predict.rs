//! `dens3r predict`: images -> scene folder (depth, normals, confidence, intrinsics, pointmaps,
//! visualisations).

use anyhow::{bail, Result};
use clap::Args;
use dens3r_backbone::predict::{predict_mono, Resolution};
use dens3r_backbone::preprocess::{open_oriented, preprocess};
use dens3r_geom::{focal_from_pointmap, DMat4, FocalMode, Intrinsics, NormalConvention, PinholeCamera, Raster, Vec3};
use dens3r_mesh::TriMesh;
use dens3r_scene::{Frame, SceneWriter};
use std::collections::HashSet;
use std::path::PathBuf;

#[derive(Args)]
pub struct PredictArgs {
    #[command(flatten)]
    model: crate::model_args::ModelArgs,
    /// Write every map at the original image size (the official `rescale_to_orig`: edge
    /// padding, nearest neighbour) with the original pixels as colours, so depth, normals and
    /// intrinsics line up with the input photos (COLMAP, nerfstudio). Default: network size.
    #[arg(long)]
    original_size: bool,
    /// Input images (PNG or JPEG).
    #[arg(required = true)]
    images: Vec<PathBuf>,
    /// Output scene folder.
    #[arg(short, long)]
    output: PathBuf,
}

pub fn run(a: PredictArgs) -> Result<()> {
    for p in &a.images {
        if !p.is_file() {
            bail!("{}: image not found", p.display());
        }
    }
    let model = a.model.load()?;
    // Decode and preprocess everything first: a bad image fails before anything is written.
    let mut inputs = Vec::new();
    let mut names = HashSet::new();
    for p in &a.images {
        let img = open_oriented(p).map_err(anyhow::Error::msg)?;
        let prep = preprocess(&img, a.model.size, !a.model.keep_portrait)
            .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        let name = dens3r_recon::input::unique_name(p, &mut names);
        let source = a.original_size.then(|| img.to_rgb8());
        inputs.push((name, prep, source));
    }
    let mut writer = SceneWriter::create(&a.output)?;
    writer.set_extra("generator", serde_json::json!("dens3r predict"));
    let bar = indicatif::ProgressBar::new(inputs.len() as u64).with_style(
        indicatif::ProgressStyle::with_template("predict {bar:30} {pos}/{len} images [{elapsed} < {eta}]")
            .expect("valid template"),
    );
    let res = if a.original_size { Resolution::Original } else { Resolution::Network };
    for (name, prep, source) in &inputs {
        let mut pred = predict_mono(&model, prep, res);
        if let Some(src) = source {
            pred.rgb = src.clone();
        }
        let (w, h) = (pred.depth.width(), pred.depth.height());
        let pp = (w as f64 / 2.0, h as f64 / 2.0);
        let estimated =
            focal_from_pointmap(&pred.points, pp, FocalMode::Weiszfeld).filter(|f| f.is_finite() && *f > 0.0);
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
            dens3r_scene::write_rgb_png(&a.output.join("viz").join(format!("{name}_normal.png")), &normal_viz(n))?;
        }
        if let Some(c) = &pred.conf {
            writer.write_conf(name, c)?;
        }
        dens3r_scene::write_rgb_png(&a.output.join("viz").join(format!("{name}_depth.png")), &depth_viz(&pred.depth))?;
        let mut cloud =
            TriMesh::new(pred.points.data().iter().copied().filter(|p| p.is_finite()).collect(), Vec::new());
        let colors: Vec<[u8; 3]> =
            pred.points.data().iter().zip(pred.rgb.pixels()).filter(|(p, _)| p.is_finite()).map(|(_, c)| c.0).collect();
        cloud.colors = Some(colors);
        dens3r_mesh::write_mesh(&a.output.join("pointmaps").join(format!("{name}.ply")), &cloud)?;
        bar.inc(1);
    }
    writer.finish()?;
    bar.finish_and_clear();
    println!(
        "predicted {} images into {} (network size {}, maps at {} size, normals in the OpenCV camera frame)",
        inputs.len(),
        a.output.display(),
        a.model.size,
        if a.original_size { "original" } else { "network" }
    );
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
