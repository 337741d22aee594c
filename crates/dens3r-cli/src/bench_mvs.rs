//! `dens3r bench mvs`: the dense stage on rendered textured scenes with their true meshes, side
//! by side in one run: today's network-only path (`reconstruct`'s fused network depth), MVS
//! without the prior, MVS with it (both on `reconstruct`'s own SfM cameras), and the truth's
//! depth through the same TSDF (the ceiling). Per side: mesh accuracy / completeness / F-score
//! at 0.02 and 0.05 of the scene's size (the true mesh's largest bounding-box side; `eval mesh`,
//! reconstructions placed by their cameras), per-view depth
//! error against the truth (AbsRel, share within 1% and 2%), seconds per depth map, peak RSS.

use crate::bench_sfm::{measured, Measured};
use anyhow::{bail, Context, Result};
use clap::Args;
use dens3r_scene::Scene;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;

#[derive(Args)]
pub struct MvsBenchArgs {
    /// Working folder (rendered sets, every side's outputs).
    #[arg(long, default_value = ".cache/bench-mvs")]
    workdir: PathBuf,
    /// Only the sets whose names contain this (dragon-24, armadillo-24, room-30).
    #[arg(long)]
    only: Option<String>,
    /// Extra arguments for every `mvs` run, split on spaces (e.g. "--mvs-size 800").
    #[arg(long, default_value = "")]
    mvs_args: String,
    /// Skip the sides whose names contain this (network, mvs-no-prior, mvs-prior, ceiling).
    #[arg(long)]
    skip: Option<String>,
    /// Write the results as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// The rendered sets: name and `render` arguments (fixed before any result was seen; the
/// meshes and photographs differ from those `bench sfm` uses for its orbits).
fn sets(data: &Path) -> Vec<(String, Vec<String>)> {
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<String>>();
    let mesh = |m: &str| data.join("meshes").join(m).display().to_string();
    let tex = |t: &str| data.join("textures").join(t).display().to_string();
    vec![
        (
            "dragon-24".into(),
            [
                s(&["--mesh", &mesh("ChineseDragon-10kv.off"), "--texture", &tex("chelsea.png")]),
                s(&["--path", "orbit", "--views", "24", "--seed", "11"]),
            ]
            .concat(),
        ),
        (
            "armadillo-24".into(),
            [
                s(&["--mesh", &mesh("armadillo.off"), "--texture", &tex("gravel.png")]),
                s(&["--path", "orbit", "--views", "24", "--seed", "12"]),
            ]
            .concat(),
        ),
        ("room-30".into(), s(&["--procedural", "room", "--views", "30", "--seed", "13"])),
    ]
}

/// The fractions of the scene's size F-scores are taken at.
const THRESHOLDS: [f64; 2] = [0.02, 0.05];

/// The scene's size: the true mesh's largest bounding-box side.
fn scene_size(gt: &Path) -> Result<f64> {
    let mesh = dens3r_mesh::read_mesh(gt)?;
    let (lo, hi) = mesh.bounds().context("the true mesh is empty")?;
    Ok((hi - lo).max_element() as f64)
}

/// `eval mesh PRED GT --json` at [`THRESHOLDS`] x `size` (placed by the cameras of `placed` =
/// (pred scene, truth scene)); its F-scores are re-keyed by the fractions.
fn eval_mesh(
    exe: &Path,
    pred: &Path,
    gt: &Path,
    size: f64,
    placed: Option<(&Path, &Path)>,
    log: &Path,
) -> Result<Value> {
    let mut c = Command::new(exe);
    c.args(["eval", "mesh", "--json"]).arg(pred).arg(gt);
    for t in THRESHOLDS {
        c.arg("--threshold").arg((t * size).to_string());
    }
    if let Some((p, g)) = placed {
        c.arg("--align-cameras").arg(p).arg(g);
    }
    let out = c.output().context("cannot start dens3r eval mesh")?;
    std::fs::write(log, [&out.stdout[..], &out.stderr[..]].concat())?;
    if !out.status.success() {
        bail!("eval mesh {} failed (its output: {})", pred.display(), log.display());
    }
    let mut v: Value = serde_json::from_slice(&out.stdout)?;
    if let Some(fs) = v["fscores"].as_array_mut() {
        for f in fs {
            let t = f["threshold"].as_f64().unwrap_or(f64::NAN) / size;
            f["threshold"] = json!((t * 1e6).round() / 1e6);
        }
    }
    for k in ["accuracy", "completeness", "chamfer_l1"] {
        if let Some(x) = v[k].as_f64() {
            v[k] = json!(x / size);
        }
    }
    v["scene_size"] = json!(size);
    Ok(v)
}

/// Per-view depth error of `pred` (a scene folder in the reconstruction's frame, scaled by
/// `scale` into the truth's) against `truth`, over the pixels both have: AbsRel, and the
/// shares within 1% and 2%; also the share of truth pixels `pred` has depth for.
fn depth_scores(pred: &Path, truth: &Path, scale: f64) -> Result<Value> {
    let p = Scene::open(pred)?;
    let t = Scene::open(truth)?;
    let (mut n, mut abs_rel, mut w1, mut w2, mut truth_px) = (0usize, 0.0f64, 0usize, 0usize, 0usize);
    for f in p.frames() {
        let Some(tf) = t.frame(&f.name) else { continue };
        let (Some(dp), Some(dt)) = (p.depth(f)?, t.depth(tf)?) else { continue };
        // The maps may be at another size than the truth (a working size): nearest pixel.
        let (sx, sy) = (dt.width() as f64 / dp.width() as f64, dt.height() as f64 / dp.height() as f64);
        truth_px += dt.data().iter().filter(|d| **d > 0.0).count();
        for y in 0..dp.height() {
            for x in 0..dp.width() {
                let d = *dp.get(x, y) as f64 * scale;
                let (u, v) = (
                    (((x as f64 + 0.5) * sx - 0.5).round() as usize).min(dt.width() - 1),
                    (((y as f64 + 0.5) * sy - 0.5).round() as usize).min(dt.height() - 1),
                );
                let g = *dt.get(u, v) as f64;
                if !(d > 0.0 && d.is_finite() && g > 0.0) {
                    continue;
                }
                let r = (d - g).abs() / g;
                n += 1;
                abs_rel += r;
                w1 += (r <= 0.01) as usize;
                w2 += (r <= 0.02) as usize;
            }
        }
    }
    let area = |k: usize| k as f64 / n.max(1) as f64;
    Ok(json!({
        "abs_rel": abs_rel / n.max(1) as f64, "within_1pct": area(w1), "within_2pct": area(w2),
        "pixels": n, "coverage": n as f64 / truth_px.max(1) as f64,
    }))
}

/// The scale `eval mesh` placed a reconstruction by.
fn placed_scale(v: &Value) -> f64 {
    v["placed_by_cameras"]["scale"].as_f64().unwrap_or(1.0)
}

fn fscore(v: &Value, t: f64) -> f64 {
    v["fscores"]
        .as_array()
        .and_then(|a| a.iter().find(|f| (f["threshold"].as_f64().unwrap_or(-1.0) - t).abs() < 1e-9))
        .and_then(|f| f["fscore"].as_f64())
        .unwrap_or(f64::NAN)
}

fn side(mesh: Value, depth: Value, seconds_per_map: f64, m: &Measured) -> Value {
    json!({"mesh": mesh, "depth": depth, "seconds_per_map": seconds_per_map, "seconds": m.seconds, "peak_rss_mb": m.rss_mb})
}

fn mvs_side(exe: &Path, dir: &Path, truth: &Path, size: f64, name: &str, extra: &[&str], user: &str) -> Result<Value> {
    let out = dir.join(name);
    let _ = std::fs::remove_dir_all(&out);
    let mut c = Command::new(exe);
    c.arg("mvs").arg(dir.join("network/scene")).arg("-o").arg(&out).args(extra).args(user.split_whitespace());
    let m = measured(&mut c, &format!("dens3r mvs ({name})"), &dir.join(format!("{name}.log")))?;
    let mesh = eval_mesh(
        exe,
        &out.join("mesh.ply"),
        &truth.join("gt_mesh.ply"),
        size,
        Some((&out, truth)),
        &dir.join(format!("{name}-eval.log")),
    )?;
    let summary: Value = serde_json::from_str(&std::fs::read_to_string(out.join("mvs.json"))?)?;
    let depth = depth_scores(&out, truth, placed_scale(&mesh))?;
    Ok(side(mesh, depth, summary["seconds_per_view"].as_f64().unwrap_or(f64::NAN), &m))
}

pub fn run(a: MvsBenchArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    let data = PathBuf::from(std::env::var("DENS3R_DATA").unwrap_or_else(|_| ".cache/data".into()));
    if !data.join("meshes/armadillo.off").is_file() || !data.join("textures/chelsea.png").is_file() {
        bail!("{}: no scanned meshes or photographs: run scripts/fetch-data.sh first", data.display());
    }
    std::fs::create_dir_all(&a.workdir)?;
    let skip = |s: &str| a.skip.as_ref().is_some_and(|k| s.contains(k.as_str()));
    let mut results = Vec::new();
    for (name, render_args) in sets(&data).iter().filter(|(n, _)| a.only.as_ref().is_none_or(|o| n.contains(o))) {
        let dir = a.workdir.join(name);
        let truth = dir.join("truth");
        std::fs::create_dir_all(&dir)?;
        if !truth.join("cameras.json").is_file() {
            let mut render = Command::new(&exe);
            render.args(["render", "--overwrite", "-o"]).arg(&truth).args(render_args);
            measured(&mut render, "render", &dir.join("render.log"))?;
        }
        let gt = truth.join("gt_mesh.ply");
        let size = scene_size(&gt)?;
        let mut row = json!({"set": name, "scene_size": size});
        // Today's path: SfM cameras, the network's depth fused (reconstruct's own mesh
        // settings; its voxel from summary.json).
        let net = dir.join("network");
        let mut m = Measured { seconds: f64::NAN, rss_mb: f64::NAN };
        if !net.join("summary.json").is_file() || !skip("network") {
            let _ = std::fs::remove_dir_all(&net);
            let mut rec = Command::new(&exe);
            rec.args(["reconstruct", "--no-cache", "--dense", "network", "-o"]).arg(&net).arg(truth.join("images"));
            m = measured(&mut rec, "dens3r reconstruct", &dir.join("network.log"))?;
        }
        let summary: Value = serde_json::from_str(&std::fs::read_to_string(net.join("summary.json"))?)?;
        let voxel = summary["mesh"]["voxel"].as_f64().context("reconstruct's summary.json has no mesh voxel")?;
        let min_conf = summary["mesh"]["min_conf"].as_f64().unwrap_or(0.0);
        let mut fuse = Command::new(&exe);
        fuse.arg("fuse").arg(net.join("scene")).arg("-o").arg(dir.join("network.ply"));
        fuse.args(["--voxel", &voxel.to_string(), "--conf-weight", "--min-conf", &min_conf.to_string()]);
        fuse.args(["--max-depth", "1e9", "--min-depth", "0"]);
        measured(&mut fuse, "dens3r fuse (network)", &dir.join("network-fuse.log"))?;
        let placed = Some((net.join("scene"), truth.clone()));
        let placed = placed.as_ref().map(|(a, b)| (a.as_path(), b.as_path()));
        let mesh = eval_mesh(&exe, &dir.join("network.ply"), &gt, size, placed, &dir.join("network-eval.log"))?;
        let depth = depth_scores(&net.join("scene"), &truth, placed_scale(&mesh))?;
        row["network"] = side(mesh, depth, f64::NAN, &m);
        if !skip("mvs-no-prior") {
            row["mvs-no-prior"] = mvs_side(&exe, &dir, &truth, size, "mvs-no-prior", &["--no-prior"], &a.mvs_args)?;
        }
        if !skip("mvs-prior") {
            row["mvs-prior"] = mvs_side(&exe, &dir, &truth, size, "mvs-prior", &[], &a.mvs_args)?;
        }
        if !skip("ceiling") {
            // The truth's depth through the same TSDF at the MVS mesh's voxel in truth units.
            let voxel = ["mvs-prior", "mvs-no-prior"]
                .iter()
                .find_map(|s| {
                    let v: Value =
                        serde_json::from_str(&std::fs::read_to_string(dir.join(s).join("mvs.json")).ok()?).ok()?;
                    Some(v["voxel"].as_f64()? * placed_scale(&row[*s]["mesh"]))
                })
                .unwrap_or(0.01);
            let mut fuse = Command::new(&exe);
            fuse.arg("fuse").arg(&truth).arg("-o").arg(dir.join("ceiling.ply")).args(["--voxel", &voxel.to_string()]);
            fuse.args(["--normal-weight", "--max-depth", "1e9", "--min-depth", "0"]);
            let m = measured(&mut fuse, "dens3r fuse (truth)", &dir.join("ceiling.log"))?;
            let mesh = eval_mesh(&exe, &dir.join("ceiling.ply"), &gt, size, None, &dir.join("ceiling-eval.log"))?;
            row["ceiling"] = side(mesh, Value::Null, f64::NAN, &m);
        }
        print_rows(&row);
        results.push(row);
    }
    if let Some(path) = &a.json {
        std::fs::write(path, serde_json::to_string_pretty(&results)?)?;
    }
    Ok(())
}

fn print_rows(row: &Value) {
    let name = row["set"].as_str().unwrap_or("?");
    println!("| set | side | F@0.02 | F@0.05 | accuracy (x size) | completeness (x size) | depth AbsRel | within 1% | within 2% | s / map | wall (s) | peak RSS (MB) |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    let ceiling = fscore(&row["ceiling"]["mesh"], 0.02);
    for s in ["network", "mvs-no-prior", "mvs-prior", "ceiling"] {
        let v = &row[s];
        if v.is_null() {
            continue;
        }
        let f = |p: &str| v.pointer(p).and_then(Value::as_f64).unwrap_or(f64::NAN);
        println!(
            "| {name} | {s} | {:.3} | {:.3} | {:.4} | {:.4} | {:.4} | {:.1}% | {:.1}% | {:.1} | {:.1} | {:.0} |",
            fscore(&v["mesh"], 0.02),
            fscore(&v["mesh"], 0.05),
            f("/mesh/accuracy"),
            f("/mesh/completeness"),
            f("/depth/abs_rel"),
            100.0 * f("/depth/within_1pct"),
            100.0 * f("/depth/within_2pct"),
            f("/seconds_per_map"),
            f("/seconds"),
            f("/peak_rss_mb"),
        );
    }
    for s in ["network", "mvs-no-prior", "mvs-prior"] {
        let f = fscore(&row[s]["mesh"], 0.02);
        if f.is_finite() && ceiling.is_finite() {
            println!("{name}: {s} F@0.02 = {:.2} x the ceiling's (goal for MVS >= 0.9)", f / ceiling);
        }
    }
}
