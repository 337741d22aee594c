//! `dens3r bench scale`: `reconstruct` on room walkthroughs of 25 to 300 rendered views, each
//! run a child process: wall time per stage (from its `summary.json`), peak RSS, pairs, camera
//! error against the truth, and the pair graph's choice against the truth's co-visibility
//! beside sliding / log windows of as many pairs; COLMAP's time beside ours where it is run.
//! Depth and normals come from the truth with a network's errors (`reconstruct --oracle`) so
//! that hundreds of views take minutes, or from the bundled model (`--model`).

use crate::bench_sfm::{measured, read_colmap_text, run_colmap, scene_cameras, score};
use anyhow::{Context, Result};
use clap::Args;
use dens3r_align::{make_pairs, PairGraph};
use dens3r_scene::Scene;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

#[derive(Args)]
pub struct ScaleBenchArgs {
    /// View counts, comma-separated.
    #[arg(long, default_value = "25,50,100,200,300", value_delimiter = ',')]
    views: Vec<usize>,
    /// Depth and normals from the bundled model instead of the oracle (slow: ~1 s a photo).
    #[arg(long)]
    model: bool,
    /// Give the photos shuffled file names (windows over names then find no neighbours).
    #[arg(long)]
    shuffle: bool,
    /// Run COLMAP (exhaustive matching) up to this many views (0: never).
    #[arg(long, default_value_t = 0)]
    colmap_up_to: usize,
    /// COLMAP's executable (scripts/bench-setup.sh installs Debian's).
    #[arg(long, default_value = "colmap")]
    colmap: PathBuf,
    /// Extra arguments for `reconstruct`, split on spaces.
    #[arg(long, default_value = "")]
    reconstruct_args: String,
    /// Working folder.
    #[arg(long, default_value = ".cache/bench-scale")]
    workdir: PathBuf,
    /// Write the results as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Share of a grid of view `i`'s pixels that view `j` sees (inside its image, in front,
/// depth within 3%): the truth's co-visibility.
fn covisibility(scene: &Scene) -> Result<Vec<Vec<f64>>> {
    let frames = scene.frames();
    let cams: Vec<_> = frames.iter().map(|f| f.camera()).collect();
    let to_cam: Vec<glam::DMat4> = cams.iter().map(|c| c.world_to_cam()).collect();
    let depths: Vec<_> =
        frames.iter().map(|f| scene.depth(f)?.context("truth without depth")).collect::<Result<Vec<_>>>()?;
    let n = frames.len();
    let mut out = vec![vec![0.0; n]; n];
    for i in 0..n {
        let (w, h) = (depths[i].width(), depths[i].height());
        let samples: Vec<glam::DVec3> = (0..12)
            .flat_map(|gy| (0..16).map(move |gx| ((gx * 2 + 1) * w / 32, (gy * 2 + 1) * h / 24)))
            .filter_map(|(x, y)| {
                let z = *depths[i].get(x, y) as f64;
                (z.is_finite() && z > 0.0).then(|| {
                    cams[i].cam_to_world.transform_point3(cams[i].intrinsics.unproject(x as f64, y as f64) * z)
                })
            })
            .collect();
        for j in (0..n).filter(|&j| j != i) {
            let seen = samples
                .iter()
                .filter(|p| {
                    let c = to_cam[j].transform_point3(**p);
                    let (u, v) = cams[j].intrinsics.project(c);
                    let (u, v) = (u.round(), v.round());
                    c.z > 0.0 && u >= 0.0 && v >= 0.0 && (u as usize) < w && (v as usize) < h && {
                        let zj = *depths[j].get(u as usize, v as usize) as f64;
                        (zj - c.z).abs() < 0.03 * c.z
                    }
                })
                .count();
            out[i][j] = seen as f64 / samples.len().max(1) as f64;
        }
    }
    Ok(out)
}

/// Precision (picked pairs truly co-visible) and recall (co-visible pairs picked) of `pairs`
/// (truth frame indices), co-visible meaning 10% either way.
fn pair_quality(pairs: &[(usize, usize)], covis: &[Vec<f64>]) -> (f64, f64) {
    let n = covis.len();
    let covisible = |i: usize, j: usize| covis[i][j].max(covis[j][i]) >= 0.1;
    let truth = (0..n).flat_map(|i| (i + 1..n).map(move |j| (i, j))).filter(|&(i, j)| covisible(i, j)).count();
    let good = pairs.iter().filter(|&&(i, j)| covisible(i, j)).count();
    (good as f64 / pairs.len().max(1) as f64, good as f64 / truth.max(1) as f64)
}

/// A rendered walkthrough and the photos a run sees.
struct Set {
    dir: PathBuf,
    truth: Scene,
    photos: PathBuf,
    /// Photo stem -> truth frame name.
    alias: HashMap<String, String>,
}

/// Renders the `n`-view walkthrough and lays out its photos (names shuffled if asked) and,
/// for the oracle, the truth under the photos' names.
fn prepare(exe: &Path, a: &ScaleBenchArgs, n: usize) -> Result<Set> {
    let dir = a.workdir.join(format!("room-{n}{}", if a.shuffle { "-shuffled" } else { "" }));
    let truth_dir = dir.join("truth");
    std::fs::create_dir_all(&dir)?;
    let seed = (1000 + n).to_string();
    let mut render = Command::new(exe);
    render.args(["render", "--width", "512", "--height", "384", "--overwrite", "-o"]).arg(&truth_dir);
    render.args(["--procedural", "room", "--views", &n.to_string(), "--seed", &seed]);
    measured(&mut render, "render", &dir.join("render.log"))?;
    let truth = Scene::open(&truth_dir)?;
    let photos = dir.join("photos");
    let _ = std::fs::remove_dir_all(&photos);
    std::fs::create_dir_all(&photos)?;
    let mut alias: HashMap<String, String> = HashMap::new();
    for (k, f) in truth.frames().iter().enumerate() {
        let name = if a.shuffle { format!("p{:04}", (k * 7919 + 13) % 10007) } else { f.name.clone() };
        std::fs::copy(truth_dir.join(&f.image), photos.join(format!("{name}.png")))?;
        alias.insert(name, f.name.clone());
    }
    if !a.model {
        // The oracle finds frames by the photos' stems.
        let oracle = dir.join("oracle");
        let _ = std::fs::remove_dir_all(&oracle);
        copy_scene_renamed(&truth_dir, &oracle, &alias)?;
    }
    Ok(Set { dir, truth, photos, alias })
}

/// Precision / recall of the run's pairs (`summary.json`'s graph list) and of sliding and log
/// windows over the file order with as many pairs; the window.
fn graph_quality(set: &Set, summary: &Value) -> Result<([(f64, f64); 3], usize)> {
    let n = set.truth.frames().len();
    let covis = covisibility(&set.truth)?;
    let index: HashMap<String, usize> =
        set.truth.frames().iter().enumerate().map(|(k, f)| (f.name.clone(), k)).collect();
    let photo_order: Vec<usize> = {
        let mut stems: Vec<&String> = set.alias.keys().collect();
        stems.sort();
        stems.iter().map(|s| index[&set.alias[*s]]).collect()
    };
    let picked: Vec<(usize, usize)> = summary["graph"]["list"]
        .as_array()
        .map(|l| {
            l.iter()
                .filter_map(|p| {
                    let f = |k: usize| p[k].as_str().and_then(|s| set.alias.get(s)).map(|s| index[s]);
                    Some((f(0)?, f(1)?))
                })
                .collect()
        })
        .unwrap_or_default();
    let k = picked.len().div_ceil(n).max(1);
    let by_order = |g: PairGraph| -> Vec<(usize, usize)> {
        make_pairs(n, g, false).into_iter().map(|(i, j)| (photo_order[i], photo_order[j])).collect()
    };
    Ok((
        [
            pair_quality(&picked, &covis),
            pair_quality(&by_order(PairGraph::SlidingWindow { k, cyclic: false }), &covis),
            pair_quality(&by_order(PairGraph::LogWindow { k, cyclic: false }), &covis),
        ],
        k,
    ))
}

/// Truth cameras renamed to the photos' stems are compared by truth name.
fn by_truth_name<V>(alias: &HashMap<String, String>, cams: HashMap<String, V>) -> HashMap<String, V> {
    cams.into_iter().map(|(k, v)| (alias.get(&k).cloned().unwrap_or(k), v)).collect()
}

pub fn run(a: ScaleBenchArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    std::fs::create_dir_all(&a.workdir)?;
    let mut results = Vec::new();
    println!("| views | pairs | registered | rotation (deg, median) | retrieval | keypoints | cameras | network | write | fuse | wall (s) | s / view | peak RSS (MB) | graph precision / recall | swin same pairs | logwin same pairs | COLMAP wall (s) |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for &n in &a.views {
        let set = prepare(&exe, &a, n)?;
        let truth = scene_cameras(set.truth.root())?;
        let out = set.dir.join("ours");
        let _ = std::fs::remove_dir_all(&out);
        let mut rec = Command::new(&exe);
        rec.args(["reconstruct", "--no-cache", "-o"]).arg(&out).arg(&set.photos);
        if !a.model {
            rec.arg("--oracle").arg(set.dir.join("oracle"));
        }
        rec.args(a.reconstruct_args.split_whitespace());
        let m = measured(&mut rec, "dens3r reconstruct", &set.dir.join("ours.log"))?;
        let summary: Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json"))?)?;
        let est = by_truth_name(&set.alias, scene_cameras(&out.join("scene"))?);
        let (_, reproj) = read_colmap_text(&out.join("colmap"))?;
        let ours = score(&truth, &est, reproj, &m);
        let ([q, qs, ql], k) = graph_quality(&set, &summary)?;
        let colmap = if a.colmap_up_to >= n {
            let (cams, reproj, m) = run_colmap(&a.colmap, &set.photos, &set.dir.join("colmap"))?;
            score(&truth, &by_truth_name(&set.alias, cams), reproj, &m)
        } else {
            Value::Null
        };
        let sec = &summary["seconds"];
        let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
        println!(
            "| {n} | {} | {}/{n} | {:.3} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {:.0} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {} |",
            summary["graph"]["pairs"],
            ours["registered"],
            f(&ours["rotation_deg"]),
            f(&sec["retrieval"]),
            f(&sec["keypoints"]),
            f(&sec["cameras"]),
            f(&sec["network"]),
            f(&sec["write"]),
            f(&sec["fuse"]),
            m.seconds,
            m.seconds / n as f64,
            m.rss_mb,
            q.0,
            q.1,
            qs.0,
            qs.1,
            ql.0,
            ql.1,
            if colmap.is_null() { "-".to_string() } else { format!("{:.1} ({}/{n}, {:.3} deg)", f(&colmap["seconds"]), colmap["registered"], f(&colmap["rotation_deg"])) }
        );
        results.push(json!({
            "views": n, "shuffled": a.shuffle, "model": if a.model { "dens3r-s" } else { "oracle" },
            "ours": ours, "summary": summary, "colmap": colmap,
            "graph_quality": { "precision": q.0, "recall": q.1, "swin": [qs.0, qs.1], "logwin": [ql.0, ql.1], "window": k },
        }));
        if let Some(path) = &a.json {
            std::fs::write(path, serde_json::to_string_pretty(&results)?)?;
        }
    }
    Ok(())
}

/// A copy of the scene folder `src` at `dst` whose frames (and their layer files) are renamed
/// from truth names to photo stems (`alias`: photo stem -> truth frame), for the oracle.
fn copy_scene_renamed(src: &Path, dst: &Path, alias: &HashMap<String, String>) -> Result<()> {
    let back: HashMap<&String, &String> = alias.iter().map(|(p, t)| (t, p)).collect();
    let mut cams: Value = serde_json::from_str(&std::fs::read_to_string(src.join("cameras.json"))?)?;
    for f in cams["frames"].as_array_mut().context("cameras.json without frames")? {
        let name = f["name"].as_str().context("frame without name")?.to_string();
        let new = back.get(&name).map_or(name.clone(), |s| (*s).clone());
        for layer in ["depth", "normals"] {
            let from = src.join(layer).join(format!("{name}.npy"));
            if from.is_file() {
                std::fs::create_dir_all(dst.join(layer))?;
                std::fs::copy(&from, dst.join(layer).join(format!("{new}.npy")))?;
            }
        }
        let image = f["image"].as_str().context("frame without image")?.to_string();
        let ext = Path::new(&image).extension().map_or("png".into(), |e| e.to_string_lossy().into_owned());
        std::fs::create_dir_all(dst.join("images"))?;
        std::fs::copy(src.join(&image), dst.join("images").join(format!("{new}.{ext}")))?;
        f["name"] = json!(new);
        f["image"] = json!(format!("images/{new}.{ext}"));
    }
    std::fs::write(dst.join("cameras.json"), serde_json::to_string_pretty(&cams)?)?;
    Ok(())
}
