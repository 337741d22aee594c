//! `dens3r eval depth|disparity|normals|mesh|cameras|baselines` (and `head`, in `eval_head`).

use anyhow::{bail, Result};
use clap::{Args, Subcommand, ValueEnum};
use dens3r_geom::metrics::{cameras::median as cam_median, DepthAlign, DepthMetrics, NormalMetrics};
use dens3r_geom::NormalConvention;
use dens3r_mesh::{mesh_metrics, MeshMetricsOptions};
use dens3r_scene::eval::{self, NormalSource};
use dens3r_scene::Scene;
use serde_json::json;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum EvalCommand {
    /// Depth errors of scene PRED against scene GT (frames matched by name).
    Depth(DepthArgs),
    /// Predicted depth against a disparity map whose calibration is unknown (e.g. OpenCV's
    /// Middlebury Aloe): inverse depth aligned to the disparity by least-squares scale and
    /// shift, beside the best constant and the best plane fitted to the disparity itself.
    Disparity(DisparityArgs),
    /// Normal angular errors of scene PRED against scene GT (frames matched by name).
    Normals(NormalArgs),
    /// Chamfer-L1, F-score and normal consistency of mesh PRED against mesh GT.
    Mesh(MeshArgs),
    /// Pose errors of scene PRED's cameras against scene GT's (frames matched by name; image
    /// sizes may differ): relative rotation and translation direction over every pair of
    /// views, and focal error relative to the image width.
    Cameras(CameraArgs),
    /// Scores of two image-blind baselines fitted to scene GT itself: the median depth with
    /// camera-facing normals, and the best-fit plane (what a predictor must beat).
    Baselines(BaselineArgs),
    /// Scores of a trained head (`train-head`'s OUTPUT.json) on folders it never saw:
    /// segmentation mIoU and per-class IoU, or depth AbsRel and delta1 beside the image-blind
    /// constant.
    Head(crate::eval_head::HeadArgs),
}

#[derive(Args)]
pub struct CameraArgs {
    /// Predicted scene folder (e.g. `reconstruct`'s OUT/scene).
    pred: PathBuf,
    /// Ground-truth scene folder.
    gt: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct BaselineArgs {
    /// Ground-truth scene folder (depth; normals scored when present; masks restrict).
    gt: PathBuf,
    /// Alignment applied to the plane's depth before scoring (the constant is the median
    /// already, which every alignment leaves as it is).
    #[arg(long, value_enum, default_value_t = Align::Median)]
    align: Align,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
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
    /// Predicted scene folder (for depth also a folder of NAME.npy maps, as `predict --head`
    /// writes with --original-size).
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
pub struct DisparityArgs {
    /// Predicted depth map, a height x width float .npy (`predict --original-size` writes
    /// OUT/depth/NAME.npy).
    pred: PathBuf,
    /// Ground-truth disparity of the same size: a grey PNG (8 or 16 bit, the value is the
    /// disparity, 0 unknown: Middlebury 2006's convention), a float .npy, or a .pfm
    /// (Middlebury 2014, Scene Flow; infinity unknown).
    gt: PathBuf,
    /// Divide the disparity file's values by this (KITTI's 16-bit PNGs: 256), so RMSE and MAE
    /// are in pixels.
    #[arg(long, default_value_t = 1.0)]
    scale: f32,
    /// A PNG whose non-zero pixels are the ones scored.
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
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
    /// Place PRED (a reconstruction, known up to scale) into GT's frame first: the similarity
    /// that best takes the cameras of scene folder PRED_SCENE onto those of GT_SCENE (matched
    /// by frame name), e.g. `reconstruct`'s OUT/scene and the render that made its photos.
    #[arg(long, num_args = 2, value_names = ["PRED_SCENE", "GT_SCENE"])]
    align_cameras: Option<Vec<PathBuf>>,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(c: EvalCommand) -> Result<()> {
    match c {
        EvalCommand::Depth(a) => depth(a),
        EvalCommand::Disparity(a) => disparity(a),
        EvalCommand::Normals(a) => normals(a),
        EvalCommand::Mesh(a) => mesh(a),
        EvalCommand::Cameras(a) => cameras(a),
        EvalCommand::Baselines(a) => baselines(a),
        EvalCommand::Head(a) => crate::eval_head::run(a),
    }
}

pub fn depth_align(a: Align) -> DepthAlign {
    match a {
        Align::None => DepthAlign::None,
        Align::Median => DepthAlign::MedianScale,
        Align::ScaleShift => DepthAlign::ScaleShift,
    }
}

fn cameras(a: CameraArgs) -> Result<()> {
    let (views, missing, m) = eval::camera_scores(&a.pred, &a.gt)?;
    warn_missing(&missing, views + missing.len(), "cameras", &a.pred);
    let under = |t: f64| m.rotation_deg.iter().filter(|&&e| e < t).count() as f64 / m.rotation_deg.len() as f64;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let j = json!({
        "views": views, "views_total": views + missing.len(), "missing": missing, "pairs": m.rotation_deg.len(),
        "rotation_median_deg": cam_median(&m.rotation_deg), "rotation_mean_deg": mean(&m.rotation_deg),
        "rotation_under_5": under(5.0), "rotation_under_15": under(15.0),
        "translation_median_deg": cam_median(&m.translation_deg),
        "focal_median_rel": cam_median(&m.focal_rel), "focal_max_rel": m.focal_rel.iter().cloned().fold(0.0, f64::max),
    });
    to_page(&a.pred, "cameras", &a.gt, &j)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&j)?);
        return Ok(());
    }
    println!(
        "{} views{}, {} pairs: relative rotation error median {:.3} deg, mean {:.3} deg, {:.1}% under 5 deg, {:.1}% under 15 deg",
        views,
        if missing.is_empty() { String::new() } else { format!(" of {} (the others have no camera)", views + missing.len()) },
        m.rotation_deg.len(),
        cam_median(&m.rotation_deg),
        mean(&m.rotation_deg),
        100.0 * under(5.0),
        100.0 * under(15.0)
    );
    // Pairs whose true cameras share a centre have no direction to score (issue 77, 10: this
    // printed "NaN deg").
    let translation = if m.translation_deg.is_empty() {
        "not scored (the truth's camera centres coincide)".to_string()
    } else {
        format!("{:.3} deg", cam_median(&m.translation_deg))
    };
    println!(
        "translation direction error median {translation}; focal error median {:.2}%, max {:.2}%",
        100.0 * cam_median(&m.focal_rel),
        100.0 * j["focal_max_rel"].as_f64().unwrap_or(f64::NAN)
    );
    Ok(())
}

fn baselines(a: BaselineArgs) -> Result<()> {
    let gs = Scene::open(&a.gt)?;
    // Per baseline: depth metrics and normal metrics of every frame.
    let rows = eval::baseline_scores(&gs, depth_align(a.align))?;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let names = ["constant", "plane"];
    let table: Vec<_> = rows
        .iter()
        .zip(names)
        .map(|((d, n), name)| {
            let dm = |f: fn(&DepthMetrics) -> f64| mean(&d.iter().map(f).collect::<Vec<_>>());
            let nm = |f: fn(&NormalMetrics) -> f64| (!n.is_empty()).then(|| mean(&n.iter().map(f).collect::<Vec<_>>()));
            json!({"baseline": name, "frames": d.len(), "abs_rel": dm(|m| m.abs_rel), "rmse": dm(|m| m.rmse),
                "delta1": dm(|m| m.delta[0]), "normal_mean": nm(|m| m.mean), "normal_median": nm(|m| m.median),
                "within_11_25": nm(|m| m.within[0])})
        })
        .collect();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&table)?);
        return Ok(());
    }
    println!(
        "{:<10} {:>9} {:>9} {:>8} {:>12} {:>12} {:>8}",
        "baseline", "AbsRel", "RMSE", "d<1.25", "normal mean", "median", "<11.25"
    );
    for r in &table {
        let f = |k: &str| r[k].as_f64().map_or("-".to_string(), |v| format!("{v:.4}"));
        println!(
            "{:<10} {:>9} {:>9} {:>8} {:>12} {:>12} {:>8}",
            r["baseline"].as_str().unwrap_or(""),
            f("abs_rel"),
            f("rmse"),
            f("delta1"),
            f("normal_mean"),
            f("normal_median"),
            f("within_11_25")
        );
    }
    println!("(mean over {} frames; normal angles in degrees)", rows[0].0.len());
    Ok(())
}

/// The frames that could be scored. One that cannot (no pixel valid in both maps: NaN,
/// infinite or zero values, or an empty mask) is skipped with a warning naming it and both
/// folders; only a run where no frame can be scored fails.
fn keep_scored<M, E: std::fmt::Display>(
    scored: Vec<(String, Result<M, E>)>,
    what: &str,
    c: &Common,
) -> Result<Vec<(String, M)>> {
    let total = scored.len();
    let mut rows = Vec::new();
    let mut skipped = Vec::new();
    for (name, m) in scored {
        match m {
            Ok(m) => rows.push((name, m)),
            Err(e) => skipped.push(format!(
                "warning: frame '{name}' skipped ({what} of {} against {}): {e}",
                c.pred.display(),
                c.gt.display()
            )),
        }
    }
    if rows.is_empty() {
        bail!(
            "{} against {}: none of the {total} frames has a pixel valid in both {what} maps (NaN, infinite or zero values, or empty masks)",
            c.pred.display(),
            c.gt.display()
        );
    }
    if rows.len() < total {
        skipped.iter().for_each(|w| eprintln!("{w}"));
        eprintln!(
            "warning: {} of {total} frames skipped; the means are over the other {}",
            total - rows.len(),
            rows.len()
        );
    }
    Ok(rows)
}

/// Warns, naming them, about ground-truth frames the prediction has nothing for: the scores
/// are over the others (`total` frames in all).
fn warn_missing(missing: &[String], total: usize, what: &str, pred: &std::path::Path) {
    if missing.is_empty() {
        return;
    }
    let names = missing.iter().take(8).cloned().collect::<Vec<_>>().join(", ");
    let more = if missing.len() > 8 { format!(" and {} more", missing.len() - 8) } else { String::new() };
    eprintln!(
        "warning: {}: no {what} for {} of the ground truth's {total} frames ({names}{more}); scored over the other {}",
        pred.display(),
        missing.len(),
        total - missing.len()
    );
}

/// Adds these scores to the page that shows `pred` (an output folder's `index.html`), where
/// there is one; says so on stderr (stdout may be `--json`).
fn to_page(pred: &std::path::Path, kind: &str, truth: &std::path::Path, scores: &serde_json::Value) -> Result<()> {
    let mut s = scores.clone();
    if let Some(o) = s.as_object_mut() {
        o.retain(|_, v| *v != json!([]));
    }
    s["truth"] = json!(truth.display().to_string());
    if let Some(page) = dens3r_viewer::add_scores(pred, kind, s)? {
        eprintln!("scores added to {}", page.display());
    }
    Ok(())
}

fn depth(a: DepthArgs) -> Result<()> {
    let align = depth_align(a.align);
    // A scene folder, or a folder of depth .npy files named by frame.
    let (pred, gt, missing) = if a.common.pred.join("cameras.json").is_file() {
        let p = eval::pair(&a.common.pred, &a.common.gt)?;
        (eval::pred_depths(&p)?, p.gt, p.missing)
    } else {
        let gt = Scene::open(&a.common.gt)?;
        let (pred, missing) = eval::npy_depths(&a.common.pred, &gt)?;
        (pred, gt, missing)
    };
    let total = pred.len() + missing.len();
    warn_missing(&missing, total, "depth", &a.common.pred);
    let scored = eval::depth_scores(&pred, &gt, align)?;
    let rows = keep_scored(scored, "depth", &a.common)?;
    let mean = |f: &dyn Fn(&DepthMetrics) -> f64| rows.iter().map(|r| f(&r.1)).sum::<f64>() / rows.len() as f64;
    let summary =
        [mean(&|m| m.abs_rel), mean(&|m| m.rmse), mean(&|m| m.delta[0]), mean(&|m| m.delta[1]), mean(&|m| m.delta[2])];
    // The share of the ground truth's valid pixels scored, over every frame (unscored ones 0).
    let coverage = rows.iter().map(|r| r.1.coverage).sum::<f64>() / total.max(1) as f64;
    for (n, m) in rows.iter().filter(|r| r.1.coverage < 0.999) {
        eprintln!(
            "warning: frame '{n}': the prediction is invalid (NaN, infinite or zero) at {:.1}% of the ground truth's valid pixels; scored on the rest",
            100.0 * (1.0 - m.coverage)
        );
    }
    if a.common.json {
        let frames: Vec<_> = rows.iter().map(|(n, m)| json!({"name": n, "abs_rel": m.abs_rel, "rmse": m.rmse, "delta": m.delta, "scale": m.scale, "shift": m.shift, "pixels": m.count, "coverage": m.coverage})).collect();
        let s = json!({"frames": rows.len(), "frames_total": total, "missing": missing, "coverage": coverage, "abs_rel": summary[0], "rmse": summary[1], "delta1": summary[2], "delta2": summary[3], "delta3": summary[4], "per_frame": frames});
        println!("{}", serde_json::to_string_pretty(&s)?);
    }
    let s = json!({"frames": rows.len(), "align": a.align.to_possible_value().map(|v| v.get_name().to_string()), "abs_rel": summary[0], "rmse": summary[1], "delta1": summary[2]});
    to_page(&a.common.pred, "depth", &a.common.gt, &s)?;
    if a.common.json {
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
    let label = if rows.len() < total { format!("mean of {}/{total}", rows.len()) } else { format!("mean of {total}") };
    println!(
        "{:<12} {:>9.5} {:>9.5} {:>8.4} {:>8.4} {:>8.4}",
        label, summary[0], summary[1], summary[2], summary[3], summary[4]
    );
    println!("(coverage: {:.1}% of the ground truth's valid pixels scored)", 100.0 * coverage);
    Ok(())
}

fn disparity(a: DisparityArgs) -> Result<()> {
    let s = eval::disparity_file_scores(&a.pred, &a.gt, a.scale, a.mask.as_deref())?;
    let rows = [("prediction", s.prediction), ("constant", s.constant), ("plane", s.plane)];
    if a.json {
        let row =
            |m: &dens3r_geom::metrics::DisparityMetrics| json!({"rel_rmse": m.rel_rmse, "rmse": m.rmse, "mae": m.mae});
        let j = json!({"pixels": s.prediction.count, "scale": s.scale, "shift": s.shift,
            "prediction": row(&s.prediction), "constant": row(&s.constant), "plane": row(&s.plane)});
        println!("{}", serde_json::to_string_pretty(&j)?);
        return Ok(());
    }
    println!("{:<12} {:>9} {:>9} {:>9}", "predictor", "rel RMSE", "RMSE", "MAE");
    for (name, m) in rows {
        println!("{:<12} {:>9.4} {:>9.3} {:>9.3}", name, m.rel_rmse, m.rmse, m.mae);
    }
    println!(
        "({} pixels; inverse depth scaled and shifted onto the disparity; RMSE and MAE in the disparity's units; \
         rel RMSE = RMSE / the disparity's standard deviation, 1 for the best constant)",
        s.prediction.count
    );
    Ok(())
}

fn normals(a: NormalArgs) -> Result<()> {
    let source = match (a.from_depth, a.pred_convention) {
        (true, _) => NormalSource::FromDepth,
        (false, Convention::Opencv) => NormalSource::Layer(NormalConvention::OpenCv),
        (false, Convention::Dens3rRaw) => NormalSource::Layer(NormalConvention::Dens3rRaw),
        (false, Convention::Dens3rSaved) => NormalSource::Layer(NormalConvention::Dens3rSaved),
        (false, Convention::Opengl) => NormalSource::Layer(NormalConvention::OpenGl),
    };
    let paired = eval::pair(&a.common.pred, &a.common.gt)?;
    let total = paired.frames.len() + paired.missing.len();
    warn_missing(&paired.missing, total, "normals", &a.common.pred);
    let rows = eval::normal_scores(&paired, source)?;
    let rows = keep_scored(rows, "normals", &a.common)?;
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
    }
    let j =
        json!({"frames": rows.len(), "mean_deg": s[0], "median_deg": s[1], "within_11_25": s[3], "within_30": s[5]});
    to_page(&a.common.pred, "normals", &a.common.gt, &j)?;
    if a.common.json {
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

/// Most points sampled per mesh by `eval mesh`.
const MAX_MESH_SAMPLES: usize = 20_000_000;

fn mesh(a: MeshArgs) -> Result<()> {
    if a.thresholds.iter().any(|t| t.is_nan() || *t <= 0.0) {
        bail!("--threshold values must be positive");
    }
    // Each sample keeps a point, a normal and a distance per mesh (about 60 bytes).
    if !(1..=MAX_MESH_SAMPLES).contains(&a.samples) {
        bail!("--samples {}: expected 1..={MAX_MESH_SAMPLES} (1e5 is the usual; 1e7 needs about 1.2 GB)", a.samples);
    }
    let mut pred = dens3r_mesh::read_mesh(&a.pred)?;
    let gt = dens3r_mesh::read_mesh(&a.gt)?;
    let mut placed = None;
    if let Some([ps, gs]) = a.align_cameras.as_deref() {
        let (sim, n) = eval::camera_similarity(ps, gs)?;
        for v in &mut pred.positions {
            *v = sim.apply(v.as_dvec3()).as_vec3();
        }
        if let Some(ns) = &mut pred.normals {
            let r = sim.rotation.as_mat3();
            ns.iter_mut().for_each(|n| *n = r * *n);
        }
        placed = Some((sim.scale, n));
    }
    let opts = MeshMetricsOptions { samples: a.samples, thresholds: a.thresholds, seed: a.seed };
    let m = mesh_metrics(&pred, &gt, &opts).map_err(anyhow::Error::msg)?;
    let mut shown = json!({"chamfer_l1": m.chamfer_l1, "normal_consistency": m.normal_consistency});
    for f in &m.fscores {
        shown[format!("fscore_at_{}", f.threshold)] = json!(f.fscore);
    }
    to_page(&a.pred, "mesh", &a.gt, &shown)?;
    if a.json {
        let f: Vec<_> = m
            .fscores
            .iter()
            .map(
                |f| json!({"threshold": f.threshold, "precision": f.precision, "recall": f.recall, "fscore": f.fscore}),
            )
            .collect();
        let mut j = json!({"chamfer_l1": m.chamfer_l1, "accuracy": m.accuracy, "completeness": m.completeness, "normal_consistency": m.normal_consistency, "fscores": f});
        if let Some((scale, n)) = placed {
            j["placed_by_cameras"] = json!({"cameras": n, "scale": scale});
        }
        println!("{}", serde_json::to_string_pretty(&j)?);
        return Ok(());
    }
    if let Some((scale, n)) = placed {
        println!("placed by {n} cameras: scale {scale:.4}");
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
