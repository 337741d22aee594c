//! `dens3r bench sfm`: `reconstruct`'s cameras beside COLMAP's on rendered sets with known
//! cameras (room walkthroughs, orbits of scanned meshes with photographed textures), each side
//! a child process timed whole with its peak RSS: registered views, median relative rotation
//! and baseline-direction errors over all view pairs, focal error, mean reprojection error
//! (both from their COLMAP models' points), wall time.

use anyhow::{bail, Context, Result};
use clap::Args;
use dens3r_geom::metrics::cameras::{camera_metrics, median};
use dens3r_geom::{Intrinsics, PinholeCamera};
use dens3r_scene::Scene;
use glam::{DMat3, DMat4, DQuat, DVec3};
use serde_json::json;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Args)]
pub struct SfmBenchArgs {
    /// Working folder (rendered sets, both sides' outputs).
    #[arg(long, default_value = ".cache/bench-sfm")]
    workdir: PathBuf,
    /// Only the first N sets.
    #[arg(long)]
    sets: Option<usize>,
    /// Only the sets whose names contain this (room-30-a, room-30-b, room-60, bunny-24,
    /// armadillo-12).
    #[arg(long)]
    only: Option<String>,
    /// COLMAP's executable (scripts/bench-setup.sh installs Debian's).
    #[arg(long, default_value = "colmap")]
    colmap: PathBuf,
    /// Skip COLMAP.
    #[arg(long)]
    no_colmap: bool,
    /// Extra arguments for `reconstruct` (e.g. "--align dense"), split on spaces.
    #[arg(long, default_value = "")]
    reconstruct_args: String,
    /// Write the results as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// A rendered set: its name and the `render` arguments (seeds fixed before any result was seen).
fn sets(data: &Path) -> Vec<(String, Vec<String>)> {
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<String>>();
    let mesh = |m: &str| data.join("meshes").join(m).display().to_string();
    let tex = |t: &str| data.join("textures").join(t).display().to_string();
    vec![
        ("room-30-a".into(), s(&["--procedural", "room", "--views", "30", "--seed", "1"])),
        ("room-30-b".into(), s(&["--procedural", "room", "--views", "30", "--seed", "2"])),
        ("room-60".into(), s(&["--procedural", "room", "--views", "60", "--seed", "3"])),
        (
            "bunny-24".into(),
            [
                s(&["--mesh", &mesh("bunny00.off"), "--texture", &tex("astronaut.png")]),
                s(&["--path", "orbit", "--views", "24", "--seed", "4"]),
            ]
            .concat(),
        ),
        (
            "armadillo-12".into(),
            [
                s(&["--mesh", &mesh("armadillo.off"), "--texture", &tex("coffee.png")]),
                s(&["--path", "orbit", "--views", "12", "--seed", "5"]),
            ]
            .concat(),
        ),
    ]
}

/// Wall seconds and peak RSS (MB) of a finished child.
pub(crate) struct Measured {
    pub seconds: f64,
    pub rss_mb: f64,
}

/// Runs `cmd` to completion, its output to `log`; fails naming `what` when it fails.
pub(crate) fn measured(cmd: &mut Command, what: &str, log: &Path) -> Result<Measured> {
    let file = std::fs::File::create(log).with_context(|| format!("{}: cannot create", log.display()))?;
    cmd.stdout(file.try_clone()?).stderr(file);
    let t = Instant::now();
    let mut child = cmd.spawn().with_context(|| format!("cannot start {what}"))?;
    let (ok, rss_mb) = wait_rss(&mut child)?;
    if !ok {
        bail!("{what} failed (its output: {})", log.display());
    }
    Ok(Measured { seconds: t.elapsed().as_secs_f64(), rss_mb })
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn wait_rss(child: &mut std::process::Child) -> Result<(bool, f64)> {
    let mut status = 0;
    // SAFETY: wait4 on our own child's pid, with valid pointers to locals.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let pid = unsafe { libc::wait4(child.id() as libc::pid_t, &mut status, 0, &mut usage) };
    if pid < 0 {
        bail!("waiting for a child: {}", std::io::Error::last_os_error());
    }
    Ok((libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0, usage.ru_maxrss as f64 / 1024.0))
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn wait_rss(child: &mut std::process::Child) -> Result<(bool, f64)> {
    Ok((child.wait()?.success(), f64::NAN))
}

/// A COLMAP text model's cameras by image name, and its points' mean reprojection error.
pub(crate) fn read_colmap_text(dir: &Path) -> Result<(HashMap<String, PinholeCamera>, f64)> {
    let read = |f: &str| {
        std::fs::read_to_string(dir.join(f)).with_context(|| format!("{}: cannot read", dir.join(f).display()))
    };
    let rows = |text: String| -> Vec<Vec<String>> {
        text.lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .map(|l| l.split_whitespace().map(String::from).collect())
            .collect()
    };
    let num = |s: &str| s.parse::<f64>().unwrap_or(f64::NAN);
    let mut intr: HashMap<String, (Intrinsics, usize, usize)> = HashMap::new();
    for r in rows(read("cameras.txt")?) {
        let (w, h) = (num(&r[2]) as usize, num(&r[3]) as usize);
        let p: Vec<f64> = r[4..].iter().map(|v| num(v)).collect();
        // SIMPLE_* models: f cx cy ...; PINHOLE / OPENCV / RADIAL with two focals: fx fy cx cy.
        let k = match r[1].as_str() {
            "PINHOLE" | "OPENCV" | "FULL_OPENCV" => Intrinsics { fx: p[0], fy: p[1], cx: p[2] - 0.5, cy: p[3] - 0.5 },
            _ => Intrinsics { fx: p[0], fy: p[0], cx: p[1] - 0.5, cy: p[2] - 0.5 },
        };
        intr.insert(r[0].clone(), (k, w, h));
    }
    let mut cams = HashMap::new();
    // images.txt: two lines per image, the pose first.
    for r in rows(read("images.txt")?).into_iter().filter(|r| r.len() == 10) {
        let q = DQuat::from_xyzw(num(&r[2]), num(&r[3]), num(&r[4]), num(&r[1])).normalize();
        let (rot, t) = (DMat3::from_quat(q), DVec3::new(num(&r[5]), num(&r[6]), num(&r[7])));
        let Some(&(k, w, h)) = intr.get(&r[8]) else { continue };
        let mut m = DMat4::from_mat3(rot.transpose());
        m.w_axis = (-(rot.transpose() * t)).extend(1.0);
        cams.insert(stem(&r[9]), PinholeCamera { intrinsics: k, width: w, height: h, cam_to_world: m });
    }
    let errors: Vec<f64> = rows(read("points3D.txt")?).iter().filter(|r| r.len() > 7).map(|r| num(&r[7])).collect();
    Ok((cams, errors.iter().sum::<f64>() / errors.len().max(1) as f64))
}

pub(crate) fn stem(name: &str) -> String {
    Path::new(name).file_stem().map_or(name.to_string(), |s| s.to_string_lossy().into_owned())
}

/// One side's scores on a set.
pub(crate) fn score(
    truth: &HashMap<String, PinholeCamera>,
    est: &HashMap<String, PinholeCamera>,
    reproj: f64,
    m: &Measured,
) -> serde_json::Value {
    let mut names: Vec<&String> = truth.keys().filter(|n| est.contains_key(*n)).collect();
    names.sort();
    let e: Vec<PinholeCamera> = names.iter().map(|n| est[*n]).collect();
    let t: Vec<PinholeCamera> = names.iter().map(|n| truth[*n]).collect();
    let cm = camera_metrics(&e, &t);
    json!({
        "registered": names.len(), "views": truth.len(),
        "rotation_deg": median(&cm.rotation_deg), "translation_deg": median(&cm.translation_deg),
        "focal_rel": median(&cm.focal_rel), "reprojection_px": reproj,
        "seconds": m.seconds, "peak_rss_mb": m.rss_mb,
    })
}

/// The truth's cameras by frame name.
pub(crate) fn scene_cameras(dir: &Path) -> Result<HashMap<String, PinholeCamera>> {
    let scene = Scene::open(dir)?;
    Ok(scene.frames().iter().map(|f| (stem(&f.name), f.camera())).collect())
}

/// COLMAP's whole pipeline on `images` (one shared camera, CPU SIFT, exhaustive matching,
/// the incremental mapper), its largest model as text.
pub(crate) fn run_colmap(
    colmap: &Path,
    images: &Path,
    out: &Path,
) -> Result<(HashMap<String, PinholeCamera>, f64, Measured)> {
    let _ = std::fs::remove_dir_all(out);
    std::fs::create_dir_all(out.join("sparse"))?;
    let db = out.join("database.db");
    let (dbs, ims, sp) =
        (db.display().to_string(), images.display().to_string(), out.join("sparse").display().to_string());
    let steps: Vec<Vec<&str>> = vec![
        vec![
            "feature_extractor",
            "--database_path",
            &dbs,
            "--image_path",
            &ims,
            "--ImageReader.single_camera",
            "1",
            "--SiftExtraction.use_gpu",
            "0",
        ],
        vec!["exhaustive_matcher", "--database_path", &dbs, "--SiftMatching.use_gpu", "0"],
        vec!["mapper", "--database_path", &dbs, "--image_path", &ims, "--output_path", &sp],
    ];
    let mut total = Measured { seconds: 0.0, rss_mb: 0.0 };
    for (k, args) in steps.iter().enumerate() {
        let log = out.join(format!("step{k}.log"));
        let m = match measured(Command::new(colmap).args(args), &format!("colmap {}", args[0]), &log) {
            Ok(m) => m,
            // The mapper gives up where it finds no initial pair: nothing registered.
            Err(e) if args[0] == "mapper" => {
                eprintln!("{e}");
                return Ok((HashMap::new(), f64::NAN, total));
            }
            Err(e) => return Err(e),
        };
        total.seconds += m.seconds;
        total.rss_mb = total.rss_mb.max(m.rss_mb);
    }
    // The model with most images.
    let mut best: Option<(usize, PathBuf)> = None;
    for entry in std::fs::read_dir(out.join("sparse"))? {
        let dir = entry?.path();
        let txt = dir.join("txt");
        std::fs::create_dir_all(&txt)?;
        let (ds, ts) = (dir.display().to_string(), txt.display().to_string());
        let args = ["model_converter", "--input_path", &ds, "--output_path", &ts, "--output_type", "TXT"];
        measured(Command::new(colmap).args(args), "colmap model_converter", &out.join("convert.log"))?;
        let count = read_colmap_text(&txt).map_or(0, |(c, _)| c.len());
        if best.as_ref().is_none_or(|b| count > b.0) {
            best = Some((count, txt));
        }
    }
    let Some((_, txt)) = best else { return Ok((HashMap::new(), f64::NAN, total)) };
    let (cams, reproj) = read_colmap_text(&txt)?;
    Ok((cams, reproj, total))
}

pub fn run(a: SfmBenchArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    let data = PathBuf::from(std::env::var("DENS3R_DATA").unwrap_or_else(|_| ".cache/data".into()));
    if !data.join("meshes/bunny00.off").is_file() || !data.join("textures/astronaut.png").is_file() {
        bail!("{}: no scanned meshes or photographs: run scripts/fetch-data.sh first", data.display());
    }
    let colmap_ok = !a.no_colmap && Command::new(&a.colmap).arg("help").output().is_ok_and(|o| o.status.success());
    if !a.no_colmap && !colmap_ok {
        bail!(
            "{}: COLMAP not found: run scripts/bench-setup.sh (Debian's colmap), or pass --no-colmap",
            a.colmap.display()
        );
    }
    std::fs::create_dir_all(&a.workdir)?;
    let mut results = Vec::new();
    let list = sets(&data);
    let chosen =
        list.iter().take(a.sets.unwrap_or(list.len())).filter(|(n, _)| a.only.as_ref().is_none_or(|o| n.contains(o)));
    for (name, render_args) in chosen {
        let dir = a.workdir.join(name);
        let truth_dir = dir.join("truth");
        std::fs::create_dir_all(&dir)?;
        let mut render = Command::new(&exe);
        render
            .args(["render", "--width", "512", "--height", "384", "--overwrite", "-o"])
            .arg(&truth_dir)
            .args(render_args);
        measured(&mut render, "render", &dir.join("render.log"))?;
        let truth = scene_cameras(&truth_dir)?;
        let images = truth_dir.join("images");
        // The bench's own folders from an earlier run go first.
        let ours_dir = dir.join("ours");
        let _ = std::fs::remove_dir_all(&ours_dir);
        let mut rec = Command::new(&exe);
        rec.args(["reconstruct", "--no-mesh", "--no-cache", "-o"]).arg(&ours_dir).arg(&images);
        rec.args(a.reconstruct_args.split_whitespace());
        let m = measured(&mut rec, "dens3r reconstruct", &dir.join("ours.log"))?;
        let (_, ours_reproj) = read_colmap_text(&ours_dir.join("colmap"))?;
        let ours = score(&truth, &scene_cameras(&ours_dir.join("scene"))?, ours_reproj, &m);
        let colmap = if colmap_ok {
            let (cams, reproj, m) = run_colmap(&a.colmap, &images, &dir.join("colmap"))?;
            score(&truth, &cams, reproj, &m)
        } else {
            serde_json::Value::Null
        };
        print_row(name, &ours, &colmap);
        results.push(json!({ "set": name, "ours": ours, "colmap": colmap }));
    }
    if let Some(path) = &a.json {
        std::fs::write(path, serde_json::to_string_pretty(&results)?)?;
    }
    Ok(())
}

fn print_row(name: &str, ours: &serde_json::Value, colmap: &serde_json::Value) {
    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap_or(f64::NAN);
    let side = |label: &str, v: &serde_json::Value| {
        format!(
            "| {name} | {label} | {}/{} | {:.3} | {:.3} | {:.2}% | {:.2} | {:.1} | {:.0} |",
            v["registered"],
            v["views"],
            f(v, "rotation_deg"),
            f(v, "translation_deg"),
            100.0 * f(v, "focal_rel"),
            f(v, "reprojection_px"),
            f(v, "seconds"),
            f(v, "peak_rss_mb")
        )
    };
    println!("| set | side | registered | rotation (deg, median) | baseline dir. (deg, median) | focal error | reproj. (px, mean) | wall (s) | peak RSS (MB) |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    println!("{}", side("dens3r", ours));
    if !colmap.is_null() {
        println!("{}", side("COLMAP 3.8", colmap));
        let (ro, rc) = (f(ours, "rotation_deg"), f(colmap, "rotation_deg"));
        let (to, tc) = (f(ours, "seconds"), f(colmap, "seconds"));
        let goal = (1.25 * rc).max(rc + 0.1);
        if colmap["registered"].as_u64() == Some(0) {
            println!(
                "{name}: COLMAP registered no view (no initial pair); dens3r {}, rotation {ro:.3} deg",
                ours["registered"]
            );
            return;
        }
        println!(
            "{name}: rotation {ro:.3} vs {rc:.3} deg (goal <= {goal:.3}: {}); time {:.2}x COLMAP's (goal <= 1.5x: {}); registered {} vs {}",
            if ro <= goal { "met" } else { "missed" },
            to / tc,
            if to <= 1.5 * tc { "met" } else { "missed" },
            ours["registered"],
            colmap["registered"]
        );
    }
}
