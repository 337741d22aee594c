//! Issue 66, the second reliability round: every case found by the probe of hostile inputs,
//! run as a user runs the binary. Each test failed on main 535a603.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

#[path = "../../../tests/support/fixtures.rs"]
mod fixtures;
use fixtures::{parity, A};

fn dens3r<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dens3r")).args(args).output().expect("binary runs")
}

fn ok<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(args: &[S]) -> String {
    let out = dens3r(args);
    assert!(out.status.success(), "{args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap() + &String::from_utf8_lossy(&out.stderr)
}

/// A command that must fail: exit 2, one stderr line starting `error:`, no panic.
fn fails<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(args: &[S]) -> String {
    let out = dens3r(args);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{args:?}: one line expected, got {err}");
    assert!(lines[0].starts_with("error:"), "{err}");
    lines[0].to_string()
}

fn samples() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples")
}

/// Every file under `dir` (relative paths, sorted) with its bytes.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push((p.strip_prefix(root).unwrap().display().to_string(), std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// A render of 3000 views into `out` (minutes), started in the background.
fn long_render(out: &str) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_dens3r"))
        .args(["render", "--procedural", "room", "--views", "3000", "--width", "160", "--height", "120", "-o", out])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap()
}

/// Runs a command; `must`: whether it must succeed (`None`: either). Never a panic.
fn run<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(args: &[S], must: Option<bool>) {
    let out = dens3r(args);
    if let Some(m) = must {
        assert_eq!(out.status.success(), m, "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
    }
    assert!(!String::from_utf8_lossy(&out.stderr).contains("panicked"), "{args:?}");
}

/// `reconstruct PHOTOS -o OUT` with fixture A's small network at 64 px, 5 alignment
/// iterations, then `extra`.
fn reconstruct_args(photos: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let a = parity(A);
    let mut args: Vec<String> = vec!["reconstruct".into(), photos.display().to_string(), "-o".into()];
    args.push(out.display().to_string());
    for (flag, path) in [("--weights", a.join("weights.safetensors")), ("--config", a.join("config.json"))] {
        args.extend([flag.to_string(), path.display().to_string()]);
    }
    args.extend(["--size", "64", "--iterations", "5"].map(String::from));
    args.extend(extra.iter().map(|e| e.to_string()));
    args
}

/// predict with fixture A's small network at 64 px.
fn predict_args<'a>(w: &'a str, c: &'a str, images: &[&'a str], out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["predict", "--weights", w, "--config", c, "--size", "64"];
    args.extend_from_slice(images);
    args.extend(["-o", out]);
    args.extend_from_slice(extra);
    args
}

/// Issue 66, 1: `--overwrite` replaces only what dens3r wrote. Photos and notes in the output
/// folder survive predict and render, with and without --overwrite; a user's file where an
/// output goes is refused before the network runs, and left as it was.
#[test]
fn overwrite_never_touches_the_users_files() {
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("photos");
    std::fs::create_dir_all(&out).unwrap();
    for (src, dst) in [("chelsea.png", "a.png"), ("coffee.png", "b.png")] {
        std::fs::copy(samples().join("photos").join(src), out.join(dst)).unwrap();
    }
    std::fs::write(out.join("notes.txt"), "my notes").unwrap();
    let users = snapshot(&out);
    let (pa, pb) = (out.join("a.png"), out.join("b.png"));
    let (pa, pb, o) = (pa.to_str().unwrap(), pb.to_str().unwrap(), out.to_str().unwrap());
    ok(&predict_args(w, c, &[pa, pb], o, &[]));
    let e = fails(&predict_args(w, c, &[pa, pb], o, &[]));
    assert!(e.contains("already holds a scene") && e.contains("--overwrite"), "{e}");
    ok(&predict_args(w, c, &[pa], o, &["--overwrite"]));
    // The photos and notes are byte for byte what the user had; the scene is the new one.
    let now = snapshot(&out);
    for f in &users {
        assert!(now.contains(f), "{} changed or went", f.0);
    }
    let scene = dens3r_scene::Scene::open(&out).unwrap();
    assert_eq!(scene.frames().len(), 1);
    assert!(!out.join("depth/b.npy").exists(), "the earlier run's frame b survives");
    assert!(out.join(".dens3r-outputs.json").is_file());
    let hidden: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.') && n != ".dens3r-outputs.json")
        .collect();
    assert!(hidden.is_empty(), "left behind: {hidden:?}");

    // A photo of the user's where a frame's picture goes: refused, untouched, nothing run.
    let clash = dir.path().join("clash");
    std::fs::create_dir_all(clash.join("images")).unwrap();
    std::fs::copy(samples().join("photos/chelsea.png"), clash.join("images/a.png")).unwrap();
    let before = snapshot(&clash);
    let img = clash.join("images/a.png");
    let e = fails(&predict_args(w, c, &[img.to_str().unwrap()], clash.to_str().unwrap(), &["--overwrite"]));
    assert!(e.contains("images/a.png") && e.contains("not written by dens3r"), "{e}");
    assert_eq!(snapshot(&clash), before);

    // render --overwrite keeps notes beside the scene and drops its own stale frames.
    let room = dir.path().join("room");
    std::fs::create_dir_all(&room).unwrap();
    std::fs::write(room.join("notes.txt"), "keep me").unwrap();
    let r = room.to_str().unwrap();
    let render = |views: &'static str, extra: &[&'static str]| {
        let mut args = vec!["render", "--procedural", "room", "--views", views, "--width", "32", "--height", "24"];
        args.extend_from_slice(extra);
        args.extend(["-o", r]);
        ok(&args);
    };
    render("3", &[]);
    render("2", &["--overwrite"]);
    assert_eq!(std::fs::read_to_string(room.join("notes.txt")).unwrap(), "keep me");
    assert!(room.join("depth/0001.npy").is_file() && !room.join("depth/0002.npy").exists());
}

/// Issue 66, 5: a run that fails after writing leaves nothing (not even the folders it
/// created); one killed with SIGKILL leaves no scene, only a hidden staging folder that the
/// next run sweeps.
#[test]
fn failures_and_kills_leave_no_half_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("new/deep/rec");
    let photos = samples().join("photos");
    // Fusion fails at the end (a voxel far too fine for the budget), after the scene and the
    // exports were written.
    let e = fails(&reconstruct_args(&photos, &out, &["--no-cache", "--voxel", "0.00001", "--budget-mb", "1"]));
    assert!(e.contains("budget"), "{e}");
    let left: Vec<String> = snapshot(dir.path()).into_iter().map(|f| f.0).collect();
    assert!(!dir.path().join("new").exists(), "a failed reconstruct left {left:?}");

    // SIGKILL halfway through a render into a new folder.
    let o = dir.path().join("killed");
    let os = o.to_str().unwrap();
    let mut child = long_render(os);
    std::thread::sleep(std::time::Duration::from_millis(1500));
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!dens3r_scene::holds_scene(&o), "a killed run left a scene");
    let visible: Vec<_> = snapshot(&o).into_iter().filter(|(n, _)| !n.starts_with('.')).collect();
    assert!(visible.is_empty(), "a killed run left {:?}", visible.iter().map(|f| &f.0).collect::<Vec<_>>());
    ok(&["render", "--procedural", "room", "--views", "2", "--width", "32", "--height", "24", "-o", os]);
    let names: Vec<_> =
        std::fs::read_dir(&o).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(!names.iter().any(|n| n.contains("dens3r-stage") || n.contains("dens3r-lock")), "{names:?}");
}

/// Issue 66, 9: a second run into a folder another run is writing is refused in one line.
#[test]
fn two_runs_into_one_folder_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("busy");
    let os = o.to_str().unwrap();
    let mut first = long_render(os);
    let lock = o.join(".dens3r-lock");
    for _ in 0..100 {
        if lock.is_file() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let e = fails(&["render", "--procedural", "room", "--views", "2", "--width", "32", "--height", "24", "-o", os]);
    first.kill().unwrap();
    first.wait().unwrap();
    assert!(e.contains("another dens3r run") && e.contains(&first.id().to_string()), "{e}");
}

/// Issue 66, 2: the pair cache is keyed by the weights' content and config: weights edited in
/// place with their size and modification time kept (`cp -p`, `rsync -t`) reuse no pair.
#[test]
fn edited_weights_reuse_no_cached_pair() {
    let a = parity(A);
    let dir = tempfile::tempdir().unwrap();
    let w = dir.path().join("w.safetensors");
    std::fs::copy(a.join("weights.safetensors"), &w).unwrap();
    let out = dir.path().join("rec");
    let photos = samples().join("photos");
    let run = || {
        let mut args = reconstruct_args(&photos, &out, &["--no-mesh"]);
        args[5] = w.display().to_string(); // --weights: the copy edited below
        ok(&args)
    };
    let first = run();
    assert!(first.contains("(0 from the cache"), "{first}");
    let again = run();
    assert!(again.contains("(2 from the cache"), "{again}");
    // One weight byte changed in place, size and modification time restored.
    let mtime = std::fs::metadata(&w).unwrap().modified().unwrap();
    let mut bytes = std::fs::read(&w).unwrap();
    let last = bytes.len() - 3;
    bytes[last] ^= 0x01;
    std::fs::write(&w, &bytes).unwrap();
    std::fs::File::options().write(true).open(&w).unwrap().set_modified(mtime).unwrap();
    let edited = run();
    assert!(edited.contains("(0 from the cache"), "stale pairs reused: {edited}");
}

/// Issue 66, 4: pickles nested 10^6 deep (a stack overflow, exit 134, before) are refused in
/// one line by every command that reads a checkpoint.
#[test]
fn deeply_nested_pickles_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let deep = dir.path().join("deep.pth");
    let mut p = vec![0x80, 2];
    p.extend(std::iter::repeat_n(b']', 1_000_000));
    p.extend(std::iter::repeat_n(b'a', 999_999));
    p.push(b'.');
    std::fs::write(&deep, &p).unwrap();
    let d = deep.to_str().unwrap();
    let out = dir.path().join("out");
    let e = fails(&["convert", d, "-o", out.to_str().unwrap()]);
    assert!(e.contains("deep.pth") && e.contains("levels deep"), "{e}");
    let img = samples().join("photos/chelsea.png");
    let e = fails(&["predict", "--weights", d, img.to_str().unwrap(), "-o", out.to_str().unwrap()]);
    assert!(e.contains("levels deep"), "{e}");
    assert!(!out.exists());
}

/// Issue 66, 7: numeric flags that hung, aborted or meant nothing are refused up front,
/// naming the flag.
#[test]
fn numeric_flags_are_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let room = samples().join("room");
    let r = room.to_str().unwrap();
    let m = dir.path().join("m.ply");
    let m = m.to_str().unwrap();
    let e = fails(&["fuse", r, "-o", m, "--trunc", "1e15"]);
    assert!(e.contains("--trunc"), "{e}");
    for (flag, v) in [("--rays", "100000000"), ("--samples", "100000")] {
        let e = fails(&["nsdf", r, "-o", m, flag, v]);
        assert!(e.contains(flag), "{e}");
    }
    let e = fails(&["nsdf", r, "-o", m, "--voxel", "1e30", "--iters", "1"]);
    assert!(e.contains("--voxel") && e.contains("bounding cube"), "{e}");
    let img = samples().join("photos/chelsea.png");
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let out = dir.path().join("p");
    let (w, c, o) = (w.to_str().unwrap(), c.to_str().unwrap(), out.to_str().unwrap());
    let e = fails(&predict_args(w, c, &[img.to_str().unwrap()], o, &["--focal", "1e30"]));
    assert!(e.contains("--focal") && e.contains("degrees"), "{e}");
    assert!(!out.exists());
}

/// Issue 66, 8: evaluation reports what it scored: a prediction missing a frame is named and
/// counted ("mean of 2/3"), a map invalid on half its pixels reports 50% coverage.
#[test]
fn evaluation_reports_its_coverage() {
    let dir = tempfile::tempdir().unwrap();
    let gt = dir.path().join("gt");
    let g = gt.to_str().unwrap();
    ok(&["render", "--procedural", "room", "--views", "3", "--width", "32", "--height", "24", "-o", g]);
    // The prediction: the ground truth less frame 0002, frame 0001 infinite on its top half.
    let pred = dir.path().join("pred");
    let sc = dens3r_scene::Scene::open(&gt).unwrap();
    let mut wr = dens3r_scene::SceneWriter::create(&pred).unwrap();
    for f in sc.frames().iter().take(2) {
        wr.add_frame(f.clone(), &sc.image(f).unwrap()).unwrap();
        let mut d = sc.depth(f).unwrap().unwrap();
        if f.name == "0001" {
            let (w, h) = (d.width(), d.height());
            for i in 0..w * h / 2 {
                d.data_mut()[i] = f32::INFINITY;
            }
        }
        wr.write_depth(&f.name, &d).unwrap();
    }
    wr.finish().unwrap();
    let p = pred.to_str().unwrap();
    let out = dens3r(&["eval", "depth", p, g]);
    assert!(out.status.success());
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("mean of 2/3"), "{stdout}");
    assert!(stderr.contains("0002") && stderr.contains("1 of the ground truth's 3 frames"), "{stderr}");
    assert!(stderr.contains("'0001'") && stderr.contains("50.0%"), "{stderr}");
    let j: serde_json::Value = serde_json::from_slice(&dens3r(&["eval", "depth", p, g, "--json"]).stdout).unwrap();
    assert_eq!(j["frames_total"], 3);
    assert_eq!(j["missing"][0], "0002");
    let cov = j["coverage"].as_f64().unwrap();
    assert!((cov - 0.5).abs() < 0.02, "{cov}"); // (1 + 0.5 + 0) / 3
    let cams = dens3r(&["eval", "cameras", p, g]);
    assert!(String::from_utf8_lossy(&cams.stdout).contains("2 views of 3"));
}

/// Issue 66, 10: `verify DIR` reads an official checkpoint's own file name; `--size` takes
/// `WxH` in predict as train does (and train a long side); a folder named like an image is
/// called a folder.
#[test]
fn interface_takes_the_forms_users_try() {
    let a = parity(A);
    let dir = tempfile::tempdir().unwrap();
    let v = dir.path().join("v");
    std::fs::create_dir_all(&v).unwrap();
    for e in std::fs::read_dir(&a).unwrap() {
        let e = e.unwrap();
        let name = e.file_name().to_string_lossy().replace("weights.safetensors", "model.safetensors");
        std::fs::copy(e.path(), v.join(name)).unwrap();
    }
    let report = ok(&["verify", v.to_str().unwrap()]);
    assert!(report.contains(", 0 over tolerance"), "{report}");

    let img = samples().join("photos/chelsea.png");
    let out = dir.path().join("p");
    let w = a.join("weights.safetensors");
    let c = a.join("config.json");
    let args = |size: &'static str, image: &Path, out: &Path| {
        dens3r(&[
            "predict",
            "--weights",
            w.to_str().unwrap(),
            "--config",
            c.to_str().unwrap(),
            "--size",
            size,
            image.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
    };
    let o = args("64x48", &img, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let sc = dens3r_scene::Scene::open(&out).unwrap();
    let f = &sc.frames()[0];
    assert_eq!(f.width.max(f.height), 64);
    let folder = dir.path().join("IMG_0001.jpg");
    std::fs::create_dir_all(&folder).unwrap();
    let e = fails(&["predict", folder.to_str().unwrap(), "-o", dir.path().join("q").to_str().unwrap()]);
    assert!(e.contains("is a folder"), "{e}");
}

/// Issue 66, done-when 2: no command changes or removes a file it did not create, under any
/// flag or failure. Every command that writes a folder or a file is pointed at folders holding
/// the user's files (photos, notes, a file in `images/`, a model config), succeeding and
/// failing, with and without --overwrite and reruns; every one of those files is then byte
/// for byte what it was, and no staging folder or lock is left.
#[test]
fn no_command_touches_files_it_did_not_create() {
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let dir = tempfile::tempdir().unwrap();
    let photos = samples().join("photos");
    let canary = |name: &str| {
        let d = dir.path().join(name);
        std::fs::create_dir_all(d.join("images")).unwrap();
        std::fs::write(d.join("notes.txt"), format!("notes of {name}")).unwrap();
        std::fs::copy(photos.join("chelsea.png"), d.join("photo.png")).unwrap();
        std::fs::copy(photos.join("coffee.png"), d.join("images/mine.png")).unwrap();
        let files = snapshot(&d);
        (d, files)
    };
    let mut checked = Vec::new();
    let room = samples().join("room");
    let r = room.to_str().unwrap();

    let (d, files) = canary("render");
    let o = d.to_str().unwrap();
    run(&["render", "--procedural", "room", "--views", "3", "--width", "32", "--height", "24", "-o", o], Some(true));
    run(&["render", "--procedural", "room", "--views", "2", "--width", "32", "--height", "24", "-o", o], Some(false));
    run(
        &["render", "--procedural", "room", "--views", "2", "--width", "32", "--height", "24", "-o", o, "--overwrite"],
        Some(true),
    );
    run(&["render", "--mesh", "/no/such.ply", "-o", o, "--overwrite"], Some(false));
    checked.push((d, files));

    let (d, files) = canary("predict");
    let (o, img) = (d.to_str().unwrap().to_string(), d.join("photo.png"));
    let img = img.to_str().unwrap();
    run(&predict_args(w, c, &[img], &o, &[]), Some(true));
    run(&predict_args(w, c, &[img], &o, &["--overwrite"]), Some(true));
    run(&predict_args(w, c, &[img, "/no/such.png"], &o, &["--overwrite"]), Some(false));
    run(&predict_args(w, c, &[img], &o, &["--overwrite", "--focal", "0"]), Some(false));
    checked.push((d, files));

    let (d, files) = canary("reconstruct");
    let rec = |extra: &[&str]| reconstruct_args(&photos, &d, extra);
    run(&rec(&["--no-mesh"]), Some(true));
    run(&rec(&[]), None);
    run(&rec(&["--voxel", "0.00001", "--budget-mb", "1"]), Some(false));
    checked.push((d, files));

    let (d, files) = canary("convert");
    let o = d.to_str().unwrap();
    run(&["convert", w, "-o", o], Some(true));
    run(&["convert", w, "-o", o, "--overwrite"], Some(true));
    std::fs::write(d.join("config.json"), "{\"mine\": true}").unwrap();
    let files: Vec<_> = snapshot(&d).into_iter().filter(|f| f.0 == "config.json").chain(files).collect();
    run(&["convert", w, "-o", o, "--overwrite"], Some(true));
    run(&["convert", "/no/such.pth", "-o", o, "--overwrite"], Some(false));
    checked.push((d, files));

    let (d, files) = canary("meshes");
    let m = d.join("m.ply");
    let m = m.to_str().unwrap();
    run(&["fuse", r, "-o", m, "--voxel", "0.05"], Some(true));
    run(&["fuse", r, "-o", m, "--voxel", "0.05", "--trunc", "1e15"], Some(false));
    run(
        &["nsdf", r, "-o", m, "--iters", "2", "--rays", "64", "--samples", "8", "--levels", "4", "--max-res", "32"],
        None,
    );
    run(&["nsdf", r, "-o", m, "--rays", "100000000"], Some(false));
    checked.push((d, files));

    for (d, files) in &checked {
        let now = snapshot(d);
        for f in files {
            assert!(now.contains(f), "{}: {} changed or went", d.display(), f.0);
        }
        for (name, _) in &now {
            assert!(!name.contains("dens3r-stage") && !name.contains(".dens3r-lock"), "{}: {name} left", d.display());
        }
    }
}

// Issue 77, the third reliability round: output folders someone else made. Each test below
// holds a case main 850b8c2 got wrong (the issue's list; the comment of each says how).

/// Renders a 2- or 3-view room into `out` (`--overwrite` when `again`).
fn small_render(out: &Path, views: &str, again: bool) -> Output {
    let mut args = vec!["render", "--procedural", "room", "--views", views, "--width", "32", "--height", "24"];
    if again {
        args.push("--overwrite");
    }
    args.extend(["-o", out.to_str().unwrap()]);
    dens3r(&args)
}

/// Issue 77, 1 and 3: a received folder's manifest that lists files outside the folder (`..`,
/// absolute, `scene/../../x`), folders anywhere, a user's file inside it, or files reached
/// through a link out of the folder: a rerun removes none of them, and names what it left.
/// Folders whose names only contain dens3r's temporary markers are the user's.
#[test]
fn a_received_manifest_removes_nothing_it_should_not() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("received");
    let outside = dir.path().join("outside");
    std::fs::create_dir_all(outside.join("empty")).unwrap();
    for f in ["victim.txt", "deep.txt", "abs.txt"] {
        std::fs::write(outside.join(f), format!("user's {f}")).unwrap();
    }
    assert!(small_render(&out, "3", false).status.success());
    std::fs::write(out.join("notes.txt"), "my notes, edited after receiving").unwrap();
    std::fs::create_dir_all(out.join("archive-dens3r-old-2024")).unwrap();
    std::fs::write(out.join("archive-dens3r-old-2024/a.txt"), "old").unwrap();
    std::fs::create_dir_all(out.join(".dens3r-stage-4000000001-mine")).unwrap();
    std::fs::write(out.join(".dens3r-stage-4000000001-mine/b.txt"), "mine").unwrap();
    // A link out of the folder, and a file through it that the manifest claims (with its
    // stamp, as a forger could).
    std::os::unix::fs::symlink(&outside, out.join("link")).unwrap();
    let manifest_path = out.join(".dens3r-outputs.json");
    let mut m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&manifest_path).unwrap()).unwrap();
    let abs = outside.join("abs.txt").display().to_string();
    // A forger computes the true stamp of the file it wants removed.
    let stamp = |p: &Path| serde_json::to_value(dens3r_io::output::Stamp::of(p).unwrap()).unwrap();
    for f in ["../outside/victim.txt", abs.as_str(), "depth/../../outside/deep.txt", "notes.txt", "link/victim.txt"] {
        m["files"].as_array_mut().unwrap().push(f.into());
    }
    m["stamps"]["link/victim.txt"] = stamp(&outside.join("victim.txt"));
    m["stamps"]["../outside/victim.txt"] = stamp(&outside.join("victim.txt"));
    m["stamps"]["notes.txt"] = serde_json::json!({"size": 3, "hash": "0000000000000000"});
    m["dirs"].as_array_mut().unwrap().extend(["../outside/empty".into(), "link".into()]);
    std::fs::write(&manifest_path, serde_json::to_string(&m).unwrap()).unwrap();
    let kept_outside = snapshot(&outside);
    let kept_notes = std::fs::read(out.join("notes.txt")).unwrap();

    let rerun = small_render(&out, "2", true);
    let err = String::from_utf8_lossy(&rerun.stderr);
    assert!(rerun.status.success(), "{err}");
    assert_eq!(snapshot(&outside), kept_outside, "a file outside the folder was touched");
    assert!(outside.join("empty").is_dir());
    assert_eq!(std::fs::read(out.join("notes.txt")).unwrap(), kept_notes);
    assert!(
        out.join("archive-dens3r-old-2024/a.txt").is_file()
            && out.join(".dens3r-stage-4000000001-mine/b.txt").is_file()
    );
    assert!(out.join("link").symlink_metadata().unwrap().file_type().is_symlink());
    assert!(err.contains("notes.txt") && err.contains("left as it is"), "{err}");
    assert!(err.contains("../outside/victim.txt") && err.contains("ignored"), "{err}");
    // dens3r's own stale frame did go, and the new manifest lists only plain paths.
    assert!(out.join("depth/0001.npy").is_file() && !out.join("depth/0002.npy").exists());
    let text = std::fs::read_to_string(&manifest_path).unwrap();
    assert!(!text.contains("..") && !text.contains(&abs) && !text.contains("notes.txt"), "{text}");

    // A user's edit of an output dens3r wrote makes it the user's: refused, not replaced.
    std::fs::write(out.join("depth/0000.npy"), "edited by hand").unwrap();
    let e = String::from_utf8_lossy(&small_render(&out, "2", true).stderr).to_string();
    assert!(e.contains("depth/0000.npy") && e.contains("not written by dens3r"), "{e}");
    assert_eq!(std::fs::read_to_string(out.join("depth/0000.npy")).unwrap(), "edited by hand");

    // A folder of dens3r's outputs replaced by a link out of the folder: refused.
    let out2 = dir.path().join("linked");
    assert!(small_render(&out2, "2", false).status.success());
    let moved = dir.path().join("moved-depth");
    std::fs::rename(out2.join("depth"), &moved).unwrap();
    std::os::unix::fs::symlink(&moved, out2.join("depth")).unwrap();
    let before = snapshot(&moved);
    let e = String::from_utf8_lossy(&small_render(&out2, "2", true).stderr).to_string();
    assert!(e.contains("depth") && e.contains("not written by dens3r"), "{e}");
    assert_eq!(snapshot(&moved), before);
}

/// Issue 77, 2: `predict --overwrite` into a scene written by hand or another tool (no
/// manifest) deleted its ground truth, labels and masks. Refused in one line.
#[test]
fn overwrite_refuses_a_scene_dens3r_did_not_write() {
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("room");
    let copy = |from: &Path, to: &Path| {
        let status = Command::new("cp").arg("-r").arg(from).arg(to).status().unwrap();
        assert!(status.success());
    };
    copy(&samples().join("room"), &scene);
    let before = snapshot(&scene);
    let img = scene.join("images/0000.png");
    let args = predict_args(
        w.to_str().unwrap(),
        c.to_str().unwrap(),
        &[img.to_str().unwrap()],
        scene.to_str().unwrap(),
        &["--overwrite"],
    );
    let e = fails(&args);
    assert!(e.contains("did not write") && e.contains("new folder"), "{e}");
    assert_eq!(snapshot(&scene), before);
    // render --overwrite the same.
    let e = String::from_utf8_lossy(&small_render(&scene, "2", true).stderr).to_string();
    assert!(e.contains("did not write"), "{e}");
    assert_eq!(snapshot(&scene), before);
}

/// Issue 77, 6: `dens3r pairs` with a cache it cannot store in said "N of N network runs",
/// exit 0.
#[test]
fn pairs_fails_when_it_stores_nothing() {
    let a = parity(A);
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("cache-is-a-file");
    std::fs::write(&file, "x").unwrap();
    let mut args: Vec<String> = vec!["pairs".into(), samples().join("photos").display().to_string()];
    args.extend(["--cache".into(), file.display().to_string()]);
    for (flag, path) in [("--weights", a.join("weights.safetensors")), ("--config", a.join("config.json"))] {
        args.extend([flag.to_string(), path.display().to_string()]);
    }
    args.extend(["--size", "64"].map(String::from));
    let e = fails(&args);
    assert!(e.contains("cache-is-a-file") && e.contains("cache"), "{e}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "x");
}

/// Issue 77, 8: all-black, all-white, noise, 8x8 and 1x1 photos each gave cameras and a
/// mesh. They are left out and named; with fewer than two photos of a scene, refused.
#[test]
fn photos_without_a_scene_are_left_out() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    image::RgbImage::new(200, 150).save(photos.join("black.png")).unwrap();
    image::RgbImage::from_pixel(1, 1, image::Rgb([9, 9, 9])).save(photos.join("dot.png")).unwrap();
    let mut seed = 7u64;
    let noise = image::RgbImage::from_fn(200, 150, |_, _| {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        image::Rgb([(seed >> 56) as u8, (seed >> 48) as u8, (seed >> 40) as u8])
    });
    noise.save(photos.join("noise.png")).unwrap();
    std::fs::copy(samples().join("photos/chelsea.png"), photos.join("cat.png")).unwrap();
    let e = fails(&reconstruct_args(&photos, &dir.path().join("out"), &[]));
    assert!(e.contains("at least 2 photos of a scene") && e.contains("black.png") && e.contains("noise"), "{e}");
    assert!(!dir.path().join("out").exists());
}

/// Issue 77, 10: a reused pid in a leftover lock blocked the folder forever with no hint; a
/// pipe or a device given as a photo got "no such file"; negative numbers got clap's `-- -1`
/// tip; `eval cameras` printed "NaN deg" when the truth's cameras coincide.
#[test]
fn small_cases_of_the_third_round() {
    let dir = tempfile::tempdir().unwrap();
    // A lock left by a dead run whose pid now names another process (pid 1, started at
    // another time): taken over. One whose writer is alive but unknown: refused with a hint.
    let o = dir.path().join("locked");
    std::fs::create_dir_all(&o).unwrap();
    std::fs::write(o.join(".dens3r-lock"), "1 123456789012").unwrap();
    assert!(small_render(&o, "2", false).status.success(), "a reused pid's stale lock blocked the folder");
    std::fs::write(o.join(".dens3r-lock"), "1").unwrap();
    let e = fails(&[
        "render",
        "--procedural",
        "room",
        "--views",
        "2",
        "--width",
        "32",
        "--height",
        "24",
        "--overwrite",
        "-o",
        o.to_str().unwrap(),
    ]);
    assert!(e.contains("another dens3r run") && e.contains("remove") && e.contains(".dens3r-lock"), "{e}");

    // A pipe and a device as photos.
    let fifo = dir.path().join("fifo.png");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let photo = samples().join("photos/chelsea.png");
    for odd in [fifo.as_path(), Path::new("/dev/zero")] {
        let mut args = reconstruct_args(&photo, &dir.path().join("x"), &[]);
        args.insert(1, odd.display().to_string());
        let e = fails(&args);
        assert!(e.contains("not a regular file") && e.contains(&odd.display().to_string()), "{e}");
    }

    // Negative numbers are values: the flag's own bounds answer.
    let room = samples().join("room");
    let mesh = dir.path().join("m.ply");
    let e = fails(&["fuse", room.to_str().unwrap(), "-o", mesh.to_str().unwrap(), "--voxel", "-1"]);
    assert!(e.contains("voxel size -1") && !e.contains("-- -1"), "{e}");

    // eval cameras against a truth whose cameras share one centre.
    let gt = dir.path().join("gt");
    assert!(Command::new("cp").arg("-r").arg(&room).arg(&gt).status().unwrap().success());
    let mut cams: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(room.join("cameras.json")).unwrap()).unwrap();
    for f in cams["frames"].as_array_mut().unwrap() {
        for row in 0..3 {
            f["cam_to_world"][row][3] = 0.5.into();
        }
    }
    std::fs::write(gt.join("cameras.json"), serde_json::to_string(&cams).unwrap()).unwrap();
    let out = ok(&["eval", "cameras", room.to_str().unwrap(), gt.to_str().unwrap()]);
    assert!(!out.contains("NaN") && out.contains("not scored"), "{out}");
}
