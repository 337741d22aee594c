//! The page `reconstruct` writes (OUT/index.html), opened from the file system in headless
//! Chromium as a person would double-click it, and `dens3r view` serving it.

use std::path::{Path, PathBuf};
use std::process::Command;

fn ok(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_dens3r")).args(args).output().expect("binary runs");
    assert!(out.status.success(), "{args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Why the browser check cannot run here, if it cannot (node, the viewer's npm packages,
/// Chromium); with DENS3R_REQUIRE_BROWSER=1 (set by scripts/test.sh once
/// scripts/browser-setup.sh succeeded) that is a failure, not a skip.
fn browser_missing() -> Option<String> {
    let web = root().join("crates/dens3r-viewer/web");
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    let why = if Command::new("node").arg("--version").output().is_err() {
        Some("node not found".to_string())
    } else if !web.join("node_modules/playwright-core").is_dir() {
        Some("crates/dens3r-viewer/web/node_modules absent: run scripts/browser-setup.sh".into())
    } else if !Path::new(&chromium).is_file() {
        Some(format!("no Chromium at {chromium}: run scripts/browser-setup.sh"))
    } else {
        None
    };
    if let Some(w) = &why {
        assert!(std::env::var("DENS3R_REQUIRE_BROWSER").as_deref() != Ok("1"), "DENS3R_REQUIRE_BROWSER=1 but {w}");
        eprintln!("SKIPPED: the page test needs a browser: {w}");
    }
    why
}

/// What `check-page.mjs` saw.
fn check_page(index: &Path) -> serde_json::Value {
    let script = root().join("crates/dens3r-viewer/web/test/check-page.mjs");
    let out = Command::new("node").arg(&script).arg(index).output().expect("node runs");
    assert!(
        out.status.success(),
        "check-page failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("check-page prints JSON")
}

/// Issue 69's browser test: a small reconstruction (6 views circling the bundled object, the
/// bundled model) opened by file:// in headless Chromium: no console error and every file
/// loaded, the 3-D canvas draws the mesh and the points over a part of it (not background),
/// moving the confidence slider changes what is drawn, clicking a view's picture moves the
/// 3-D view to its camera, the per-view pictures and match
/// pictures load, and the scores `eval cameras` added are shown.
#[test]
fn the_page_shows_a_reconstruction_in_a_browser() {
    let model = root().join("data-samples/models/dens3r-s");
    if !model.join("vit_s_focus.onnx").is_file() {
        assert!(std::env::var_os("CI").is_none(), "the bundled model's encoder is absent: run scripts/fetch-data.sh");
        eprintln!("SKIPPED: data-samples/models/dens3r-s/vit_s_focus.onnx absent: run scripts/fetch-data.sh");
        return;
    }
    if browser_missing().is_some() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (orbit, recon) = (dir.path().join("orbit"), dir.path().join("recon"));
    let (mesh, texture) =
        (root().join("data-samples/orbit/gt_mesh.ply"), root().join("data-samples/textures/gravel.png"));
    #[rustfmt::skip]
    ok(&["render", "--mesh", mesh.to_str().unwrap(), "--views", "8", "--width", "256", "--height", "192",
        "--texture", texture.to_str().unwrap(), "-o", orbit.to_str().unwrap()]);
    #[rustfmt::skip]
    let out = ok(&["reconstruct", orbit.join("images").to_str().unwrap(), "-o", recon.to_str().unwrap(),
        "--graph", "swin", "--window", "2", "--cyclic", "--masks", orbit.join("masks").to_str().unwrap()]);
    assert!(out.contains(&format!("page: {}", recon.join("index.html").display())), "{out}");
    // `eval` adds its scores to the page that shows the scene it scored.
    let scene = recon.join("scene");
    let eval = Command::new(env!("CARGO_BIN_EXE_dens3r"))
        .args(["eval", "cameras", scene.to_str().unwrap(), orbit.to_str().unwrap(), "--json"])
        .output()
        .unwrap();
    assert!(eval.status.success());
    let scored: serde_json::Value = serde_json::from_slice(&eval.stdout).expect("--json output stays JSON");
    assert!(String::from_utf8_lossy(&eval.stderr).contains("scores added to"));
    let app = std::fs::read_to_string(recon.join("viewer/app.js")).unwrap();
    assert!(!app.contains("built without its 3-D viewer"), "the viewer was not bundled: run scripts/build-viewer.sh");
    let r = check_page(&recon.join("index.html"));
    eprintln!("{r}");
    assert_eq!(r["errors"], serde_json::json!([]), "console errors or failed loads");
    assert_eq!(r["viewer"], true, "the page reported a problem");
    let frac = |k: &str| r[k].as_f64().unwrap_or_else(|| panic!("{k} missing: {r}"));
    // The object fills a good part of the overview; the background is one flat colour.
    assert!(frac("mesh_drawn") > 0.03, "{r}");
    assert!(frac("points_drawn") > 0.03, "{r}");
    assert!(frac("changed_by_slider") > 0.005, "the slider changed nothing: {r}");
    assert!(frac("points_drawn_high") < frac("points_drawn"), "{r}");
    assert!(frac("changed_by_view_click") > 0.01, "clicking a view's picture moved nothing: {r}");
    let views = dens3r_scene::Scene::open(&recon.join("scene")).unwrap().frames().len() as u64;
    assert_eq!(r["pictures"].as_u64(), Some(views));
    assert_eq!(r["pictures_loaded"].as_u64(), Some(views), "every picture decodes");
    assert!(r["summary_rows"].as_u64().unwrap() >= 8 && r["match_pictures"].as_u64().unwrap() >= 1, "{r}");
    assert_eq!(r["score_tables"].as_u64(), Some(1), "the cameras' scores are shown: {r}");
    let page_scores = std::fs::read_to_string(recon.join("viewer/scores.js")).unwrap();
    let median = scored["rotation_median_deg"].as_f64().unwrap();
    assert!(page_scores.contains(&format!("\"rotation_median_deg\":{median}")), "{page_scores}");
}

/// `dens3r view` serves the folder on 127.0.0.1: the page, its script and a picture, and
/// nothing outside the folder.
#[test]
fn view_serves_the_page_on_localhost() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    std::fs::create_dir_all(out.join("viewer")).unwrap();
    std::fs::write(out.join("index.html"), "<!doctype html>page").unwrap();
    std::fs::write(out.join("viewer/app.js"), "x").unwrap();
    // A large file, for a client that asks for it and never reads.
    std::fs::write(out.join("viewer/big.js"), vec![b'y'; 64 << 20]).unwrap();
    std::fs::write(dir.path().join("secret.txt"), "SECRET-CONTENT").unwrap();
    std::os::unix::fs::symlink(dir.path(), out.join("rootfs")).unwrap();
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let mut child = Command::new(env!("CARGO_BIN_EXE_dens3r"))
        .args(["view", out.to_str().unwrap(), "--port", &port.to_string()])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let connect = || {
        for _ in 0..100 {
            if let Ok(s) = std::net::TcpStream::connect(("127.0.0.1", port)) {
                s.set_read_timeout(Some(std::time::Duration::from_secs(5))).unwrap();
                return s;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        panic!("the server does not answer");
    };
    let get_as = |path: &str, host: &str| -> String {
        use std::io::{Read, Write};
        let mut s = connect();
        write!(s, "GET {path} HTTP/1.0\r\nHost: {host}\r\n\r\n").unwrap();
        let mut text = String::new();
        // No answer within 5 s is a failure asserted below (after the server is stopped).
        match s.read_to_string(&mut text) {
            Ok(_) => text,
            Err(e) => format!("no answer within 5 s: {e}"),
        }
    };
    let here = format!("127.0.0.1:{port}");
    let get = |path: &str| get_as(path, &here);
    let page = get("/");
    // Issue 77, 4: a client that sends nothing, and one that asks for 64 MB and reads none of
    // it, stall only themselves: the others are answered at once.
    let idle = connect();
    let mut hog = connect();
    std::io::Write::write_all(&mut hog, format!("GET /viewer/big.js HTTP/1.0\r\nHost: {here}\r\n\r\n").as_bytes())
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(300));
    let t = std::time::Instant::now();
    let script = get("/viewer/app.js");
    let waited = t.elapsed();
    let outside = get("/../secret.txt");
    let through_link = get("/rootfs/secret.txt");
    let rebound = get_as("/", &format!("attacker.example:{port}"));
    let localhost = get_as("/viewer/app.js", &format!("localhost:{port}"));
    drop((idle, hog));
    child.kill().unwrap();
    let _ = child.wait();
    assert!(page.starts_with("HTTP/1.1 200") && page.contains("text/html") && page.ends_with("page"), "{page}");
    assert!(
        script.starts_with("HTTP/1.1 200") && script.contains("text/javascript") && script.ends_with('x'),
        "{script}"
    );
    assert!(waited < std::time::Duration::from_secs(2), "a stalled client held the server {waited:?}");
    assert!(outside.starts_with("HTTP/1.1 404") && !outside.contains("SECRET-CONTENT"), "{outside}");
    assert!(through_link.starts_with("HTTP/1.1 404") && !through_link.contains("SECRET"), "{through_link}");
    assert!(rebound.starts_with("HTTP/1.1 421") && !rebound.contains("page"), "{rebound}");
    assert!(localhost.starts_with("HTTP/1.1 200") && localhost.ends_with('x'), "{localhost}");
    let bad = Command::new(env!("CARGO_BIN_EXE_dens3r")).args(["view", dir.path().to_str().unwrap()]).output().unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(bad.status.code(), Some(2));
    assert!(err.trim().lines().count() == 1 && err.contains("no index.html"), "{err}");
}
