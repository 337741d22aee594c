//! `dens3r eval depth|normals|mesh`.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use dens3r_geom::metrics::{depth_metrics, normal_metrics, DepthAlign, DepthMetrics, NormalMetrics};
use dens3r_geom::normals::normals_from_pointmap_robust;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{NormalConvention, Raster};
use dens3r_mesh::{mesh_metrics, MeshMetricsOptions};
use dens3r_scene::{Frame, Scene};
use serde_json::json;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum EvalCommand {
    /// Depth errors of scene PRED against scene GT (frames matched by name).
    Depth(DepthArgs),
    /// Normal angular errors of scene PRED against scene GT (frames matched by name).
    Normals(NormalArgs),
    /// Chamfer-L1, F-score and normal consistency of mesh PRED against mesh GT.
    Mesh(MeshArgs),
}

#[derive(Clone, Copy, ValueEnum)]
pub enum Align {
    /// Compare as is (metric depth).
    None,
    /// Scale by median(gt) / median(pred), per frame.
    Median,
    /// Least-squares scale and shift, per frame.
    ScaleShift,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum Convention {
    Opencv,
    Dens3rRaw,
    Dens3rSaved,
    Opengl,
}

#[derive(Args)]
pub struct Common {
    /// Predicted scene folder.
    pred: PathBuf,
    /// Ground-truth scene folder (its masks, if any, restrict the pixels).
    gt: PathBuf,
    /// Print one line per frame too.
    #[arg(long)]
    per_frame: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct DepthArgs {
    #[command(flatten)]
    common: Common,
    /// How to align the prediction before scoring.
    #[arg(long, value_enum, default_value_t = Align::None)]
    align: Align,
}

#[derive(Args)]
pub struct NormalArgs {
    #[command(flatten)]
    common: Common,
    /// Convention of PRED's normal files (GT is always OpenCV).
    #[arg(long, value_enum, default_value_t = Convention::Opencv)]
    pred_convention: Convention,
    /// Derive PRED's normals from its depth and cameras instead of reading normals/.
    #[arg(long)]
    from_depth: bool,
}

#[derive(Args)]
pub struct MeshArgs {
    /// Predicted mesh (.ply, .obj, .off).
    pred: PathBuf,
    /// Ground-truth mesh.
    gt: PathBuf,
    /// Points sampled on each mesh.
    #[arg(long, default_value_t = 100_000)]
    samples: usize,
    /// F-score thresholds in mesh units (repeatable).
    #[arg(long = "threshold", default_values_t = [0.01, 0.02])]
    thresholds: Vec<f64>,
    /// Sampling seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(c: EvalCommand) -> Result<()> {
    match c {
        EvalCommand::Depth(a) => depth(a),
        EvalCommand::Normals(a) => normals(a),
        EvalCommand::Mesh(a) => mesh(a),
    }
}

/// A predicted and a ground-truth scene with their frames matched by name.
struct Paired {
    pred: Scene,
    gt: Scene,
    frames: Vec<(Frame, Frame)>,
}

/// Frames present in both scenes, with matching sizes.
fn paired(c: &Common) -> Result<Paired> {
    let (p, g) = (Scene::open(&c.pred)?, Scene::open(&c.gt)?);
    let mut pairs = Vec::new();
    for gf in g.frames() {
        if let Some(pf) = p.frame(&gf.name) {
            if (pf.width, pf.height) != (gf.width, gf.height) {
                bail!(
                    "frame '{}' is {}x{} in {} but {}x{} in {}: resample one of them first",
                    gf.name,
                    pf.width,
                    pf.height,
                    c.pred.display(),
                    gf.width,
                    gf.height,
                    c.gt.display()
                );
            }
            pairs.push((pf.clone(), gf.clone()));
        }
    }
    if pairs.is_empty() {
        bail!("{} and {} share no frame names: nothing to compare", c.pred.display(), c.gt.display());
    }
    Ok(Paired { pred: p, gt: g, frames: pairs })
}

fn need<T>(v: Option<T>, scene: &Scene, f: &Frame, what: &str) -> Result<T> {
    v.with_context(|| {
        format!("{}: frame '{}' has no {what} file ({what}/{}.npy)", scene.root().display(), f.name, f.name)
    })
}

fn depth(a: DepthArgs) -> Result<()> {
    let Paired { pred: ps, gt: gs, frames: pairs } = paired(&a.common)?;
    let align = match a.align {
        Align::None => DepthAlign::None,
        Align::Median => DepthAlign::MedianScale,
        Align::ScaleShift => DepthAlign::ScaleShift,
    };
    let mut rows = Vec::new();
    for (pf, gf) in &pairs {
        let pd = need(ps.depth(pf)?, &ps, pf, "depth")?;
        let gd = need(gs.depth(gf)?, &gs, gf, "depth")?;
        let m =
            depth_metrics(&pd, &gd, gs.mask(gf)?.as_ref(), align).with_context(|| format!("frame '{}'", gf.name))?;
        rows.push((gf.name.clone(), m));
    }
    let mean = |f: &dyn Fn(&DepthMetrics) -> f64| rows.iter().map(|r| f(&r.1)).sum::<f64>() / rows.len() as f64;
    let summary =
        [mean(&|m| m.abs_rel), mean(&|m| m.rmse), mean(&|m| m.delta[0]), mean(&|m| m.delta[1]), mean(&|m| m.delta[2])];
    if a.common.json {
        let frames: Vec<_> = rows.iter().map(|(n, m)| json!({"name": n, "abs_rel": m.abs_rel, "rmse": m.rmse, "delta": m.delta, "scale": m.scale, "shift": m.shift, "pixels": m.count})).collect();
        let s = json!({"frames": rows.len(), "abs_rel": summary[0], "rmse": summary[1], "delta1": summary[2], "delta2": summary[3], "delta3": summary[4], "per_frame": frames});
        println!("{}", serde_json::to_string_pretty(&s)?);
        return Ok(());
    }
    println!("{:<12} {:>9} {:>9} {:>8} {:>8} {:>8}", "frame", "AbsRel", "RMSE", "d<1.25", "d<1.25^2", "d<1.25^3");
    if a.common.per_frame {
        for (n, m) in &rows {
            println!(
                "{:<12} {:>9.5} {:>9.5} {:>8.4} {:>8.4} {:>8.4}",
                n, m.abs_rel, m.rmse, m.delta[0], m.delta[1], m.delta[2]
            );
        }
    }
    let label = format!("mean of {}", rows.len());
    println!(
        "{:<12} {:>9.5} {:>9.5} {:>8.4} {:>8.4} {:>8.4}",
        label, summary[0], summary[1], summary[2], summary[3], summary[4]
    );
    Ok(())
}

fn normals(a: NormalArgs) -> Result<()> {
    let Paired { pred: ps, gt: gs, frames: pairs } = paired(&a.common)?;
    let conv = match a.pred_convention {
        Convention::Opencv => NormalConvention::OpenCv,
        Convention::Dens3rRaw => NormalConvention::Dens3rRaw,
        Convention::Dens3rSaved => NormalConvention::Dens3rSaved,
        Convention::Opengl => NormalConvention::OpenGl,
    };
    let mut rows = Vec::new();
    for (pf, gf) in &pairs {
        let pred: Raster<glam::Vec3> = if a.from_depth {
            let d = need(ps.depth(pf)?, &ps, pf, "depth")?;
            normals_from_pointmap_robust(&depth_to_pointmap(&d, &pf.camera().intrinsics), 0.05)
        } else {
            need(ps.normals(pf)?, &ps, pf, "normals")?.map(|n| conv.to_opencv(*n))
        };
        let gt = need(gs.normals(gf)?, &gs, gf, "normals")?;
        let m = normal_metrics(&pred, &gt, gs.mask(gf)?.as_ref()).with_context(|| format!("frame '{}'", gf.name))?;
        rows.push((gf.name.clone(), m));
    }
    let mean = |f: &dyn Fn(&NormalMetrics) -> f64| rows.iter().map(|r| f(&r.1)).sum::<f64>() / rows.len() as f64;
    let s = [
        mean(&|m| m.mean),
        mean(&|m| m.median),
        mean(&|m| m.rmse),
        mean(&|m| m.within[0]),
        mean(&|m| m.within[1]),
        mean(&|m| m.within[2]),
    ];
    if a.common.json {
        let frames: Vec<_> = rows.iter().map(|(n, m)| json!({"name": n, "mean": m.mean, "median": m.median, "rmse": m.rmse, "within_11_25": m.within[0], "within_22_5": m.within[1], "within_30": m.within[2], "pixels": m.count})).collect();
        let j = json!({"frames": rows.len(), "mean": s[0], "median": s[1], "rmse": s[2], "within_11_25": s[3], "within_22_5": s[4], "within_30": s[5], "per_frame": frames});
        println!("{}", serde_json::to_string_pretty(&j)?);
        return Ok(());
    }
    println!("{:<12} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}", "frame", "mean", "median", "rmse", "<11.25", "<22.5", "<30");
    if a.common.per_frame {
        for (n, m) in &rows {
            println!(
                "{:<12} {:>8.3} {:>8.3} {:>8.3} {:>8.4} {:>8.4} {:>8.4}",
                n, m.mean, m.median, m.rmse, m.within[0], m.within[1], m.within[2]
            );
        }
    }
    let label = format!("mean of {}", rows.len());
    println!("{:<12} {:>8.3} {:>8.3} {:>8.3} {:>8.4} {:>8.4} {:>8.4}", label, s[0], s[1], s[2], s[3], s[4], s[5]);
    println!("(angles in degrees; fractions of pixels under each threshold)");
    Ok(())
}

fn mesh(a: MeshArgs) -> Result<()> {
    if a.thresholds.iter().any(|t| t.is_nan() || *t <= 0.0) {
        bail!("--threshold values must be positive");
    }
    let pred = dens3r_mesh::read_mesh(&a.pred)?;
    let gt = dens3r_mesh::read_mesh(&a.gt)?;
    let opts = MeshMetricsOptions { samples: a.samples, thresholds: a.thresholds, seed: a.seed };
    let m = mesh_metrics(&pred, &gt, &opts).map_err(anyhow::Error::msg)?;
    if a.json {
        let f: Vec<_> = m
            .fscores
            .iter()
            .map(
                |f| json!({"threshold": f.threshold, "precision": f.precision, "recall": f.recall, "fscore": f.fscore}),
            )
            .collect();
        let j = json!({"chamfer_l1": m.chamfer_l1, "accuracy": m.accuracy, "completeness": m.completeness, "normal_consistency": m.normal_consistency, "fscores": f});
        println!("{}", serde_json::to_string_pretty(&j)?);
        return Ok(());
    }
    println!(
        "chamfer-L1          {:.6}  (accuracy {:.6}, completeness {:.6})",
        m.chamfer_l1, m.accuracy, m.completeness
    );
    for f in &m.fscores {
        println!("F-score@{:<11} {:.4}  (precision {:.4}, recall {:.4})", f.threshold, f.fscore, f.precision, f.recall);
    }
    println!("normal consistency  {:.4}", m.normal_consistency);
    Ok(())
}
