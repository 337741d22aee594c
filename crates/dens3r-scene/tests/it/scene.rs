use dens3r_geom::camera::look_at;
use dens3r_geom::{DVec3, Intrinsics, PinholeCamera, Raster, Vec3};
use dens3r_scene::{Frame, Scene, SceneWriter};
use std::collections::BTreeMap;
use std::path::Path;

const W: usize = 8;
const H: usize = 6;

fn cam() -> PinholeCamera {
    PinholeCamera {
        intrinsics: Intrinsics::from_hfov(W, H, 60.0),
        width: W,
        height: H,
        cam_to_world: look_at(DVec3::new(1.0, 2.0, 3.0), DVec3::ZERO, DVec3::Z).unwrap(),
    }
}

/// A complete two-frame scene with every layer.
fn write_scene(dir: &Path) {
    let mut w = SceneWriter::create(dir).unwrap();
    for name in ["a", "b"] {
        let rgb = image::RgbImage::from_fn(W as u32, H as u32, |x, y| image::Rgb([x as u8 * 20, y as u8 * 30, 7]));
        w.add_frame(Frame::new(name, &cam()), &rgb).unwrap();
        w.write_depth(name, &Raster::from_fn(W, H, |x, y| (x + y) as f32 * 0.5)).unwrap();
        w.write_normals(name, &Raster::from_fn(W, H, |x, _| Vec3::new(x as f32, 0.0, -1.0).normalize())).unwrap();
        w.write_conf(name, &Raster::filled(W, H, 2.0)).unwrap();
        w.write_mask(name, &Raster::from_fn(W, H, |x, _| x > 2)).unwrap();
        w.write_labels(name, &Raster::from_fn(W, H, |x, _| x as u16)).unwrap();
        w.write_instances(name, &Raster::from_fn(W, H, |x, y| (x * 1000 + y) as u16)).unwrap();
    }
    w.write_classes(&BTreeMap::from([(0, "bg".to_string()), (3, "wall".to_string())])).unwrap();
    w.finish().unwrap();
}

#[test]
fn written_scene_reads_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path());
    let s = Scene::open(dir.path()).unwrap();
    assert_eq!(s.frames().len(), 2);
    let f = s.frame("b").unwrap();
    assert_eq!(f.camera(), cam());
    assert_eq!(s.image(f).unwrap().get_pixel(3, 2).0, [60, 60, 7]);
    assert_eq!(*s.depth(f).unwrap().unwrap().get(5, 4), 4.5);
    assert_eq!(*s.normals(f).unwrap().unwrap().get(0, 1), Vec3::new(0.0, 0.0, -1.0));
    assert_eq!(*s.conf(f).unwrap().unwrap().get(1, 1), 2.0);
    let mask = s.mask(f).unwrap().unwrap();
    assert!(!*mask.get(2, 0) && *mask.get(3, 0));
    assert_eq!(*s.labels(f).unwrap().unwrap().get(7, 0), 7);
    assert_eq!(*s.instances(f).unwrap().unwrap().get(7, 5), 7005, "16-bit ids survive");
    assert_eq!(s.classes().unwrap()[&3], "wall");
    // Layout and JSON as documented.
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("cameras.json")).unwrap()).unwrap();
    assert_eq!(json["convention"], "opencv");
    assert_eq!(json["frames"][0]["image"], "images/a.png");
    assert_eq!(json["frames"][0]["K"][0][0].as_f64().unwrap(), cam().intrinsics.fx);
    assert_eq!(json["frames"][0]["cam_to_world"][3], serde_json::json!([0.0, 0.0, 0.0, 1.0]));
    for p in ["depth/a.npy", "normals/a.npy", "conf/a.npy", "masks/a.png", "labels/a.png", "instances/a.png"] {
        assert!(dir.path().join(p).is_file(), "{p}");
    }
    // Nothing temporary is left anywhere.
    let leftovers: Vec<_> = walk(dir.path()).into_iter().filter(|p| p.contains(".dens3r-tmp")).collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

fn walk(p: &Path) -> Vec<String> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(p).unwrap() {
        let e = e.unwrap().path();
        if e.is_dir() {
            out.extend(walk(&e));
        } else {
            out.push(e.display().to_string());
        }
    }
    out
}

/// Opens (and reads frame "a" of) a scene after `breakit` damaged it; returns the error.
fn error_after(breakit: impl FnOnce(&Path)) -> String {
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path());
    breakit(dir.path());
    let r = Scene::open(dir.path()).and_then(|s| {
        let f = s.frame("a").unwrap().clone();
        s.image(&f)?;
        s.depth(&f)?;
        s.normals(&f)?;
        s.labels(&f)?;
        Ok(())
    });
    let e = r.expect_err("damaged scene must not load").to_string();
    assert!(!e.contains('\n'), "one line: {e}");
    e
}

fn edit_cameras(dir: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let p = dir.join("cameras.json");
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
}

#[test]
fn bad_scenes_give_one_clear_line() {
    let e = error_after(|d| std::fs::remove_file(d.join("cameras.json")).unwrap());
    assert!(e.contains("cameras.json") && e.contains("missing"), "{e}");

    let e = error_after(|d| std::fs::write(d.join("cameras.json"), "{ not json").unwrap());
    assert!(e.contains("cameras.json") && e.contains("invalid"), "{e}");

    // NaN is not JSON, so Python's json.dump(NaN) output is rejected at parse time...
    let e = error_after(|d| {
        edit_cameras(d, |v| v["frames"][0]["cam_to_world"][0][0] = "NAN_MARKER".into());
        let t = std::fs::read_to_string(d.join("cameras.json")).unwrap();
        assert!(t.contains("\"NAN_MARKER\""));
        std::fs::write(d.join("cameras.json"), t.replace("\"NAN_MARKER\"", "NaN")).unwrap();
    });
    assert!(e.contains("cameras.json"), "{e}");
    // ...and a pose that is not rigid is named.
    let e = error_after(|d| edit_cameras(d, |v| v["frames"][0]["cam_to_world"][0][0] = 2.0.into()));
    assert!(e.contains("frame 'a'") && e.contains("not a rotation"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["frames"][1]["cam_to_world"][3][2] = 1.0.into()));
    assert!(e.contains("frame 'b'") && e.contains("last row"), "{e}");

    let e = error_after(|d| edit_cameras(d, |v| v["frames"][0]["K"][0][0] = (-5.0).into()));
    assert!(e.contains("K must be"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["frames"][0]["K"] = serde_json::json!([[1, 0, 0], [0, 1, 0]])));
    assert!(e.contains("cameras.json"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["convention"] = "opengl".into()));
    assert!(e.contains("convention 'opengl'"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["frames"][1]["name"] = "a".into()));
    assert!(e.contains("used twice"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["frames"][0]["width"] = 100000.into()));
    assert!(e.contains("outside"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["frames"][0]["image"] = "../../etc/passwd".into()));
    assert!(e.contains("inside the scene folder"), "{e}");
    let e = error_after(|d| edit_cameras(d, |v| v["frames"] = serde_json::json!([])));
    assert!(e.contains("no frames"), "{e}");

    let e = error_after(|d| std::fs::remove_file(d.join("images/b.png")).unwrap());
    assert!(e.contains("images/b.png") && e.contains("missing"), "{e}");
    let e = error_after(|d| std::fs::write(d.join("images/a.png"), b"\x89PNG but not really").unwrap());
    assert!(e.contains("images/a.png") && e.contains("unreadable image"), "{e}");
    let e = error_after(|d| {
        image::RgbImage::new(5, 5).save(d.join("images/a.png")).unwrap();
    });
    assert!(e.contains("is 5x5 but cameras.json says 8x6"), "{e}");

    // Wrong array shapes are named with the expected shape.
    let e = error_after(|d| dens3r_scene::npy::write_f32(&d.join("depth/a.npy"), &[W, H], &[0.0; W * H]).unwrap());
    assert!(e.contains("depth/a.npy") && e.contains("should be [6, 8]"), "{e}");
    let e = error_after(|d| dens3r_scene::npy::write_f32(&d.join("normals/a.npy"), &[H, W], &[0.0; W * H]).unwrap());
    assert!(e.contains("normals/a.npy") && e.contains("HxWx3"), "{e}");
    let e = error_after(|d| std::fs::write(d.join("depth/a.npy"), b"\x93NUMPY\x01\x00garbage").unwrap());
    assert!(e.contains("depth/a.npy") && e.contains("not a valid .npy"), "{e}");
    let e = error_after(|d| image::RgbImage::new(W as u32, H as u32).save(d.join("labels/a.png")).unwrap());
    assert!(e.contains("labels/a.png") && e.contains("single-channel"), "{e}");

    let missing = Scene::open(Path::new("/nonexistent/scene")).unwrap_err().to_string();
    assert!(missing.contains("/nonexistent/scene") && missing.contains("not found"), "{missing}");
}

#[test]
fn writer_refuses_mismatched_layers_and_finishing_empty() {
    let dir = tempfile::tempdir().unwrap();
    let mut w = SceneWriter::create(dir.path()).unwrap();
    assert!(w.write_depth("x", &Raster::filled(W, H, 1.0)).unwrap_err().to_string().contains("must be added"));
    let rgb = image::RgbImage::new(W as u32, H as u32);
    w.add_frame(Frame::new("x", &cam()), &rgb).unwrap();
    assert!(w.add_frame(Frame::new("x", &cam()), &rgb).is_err());
    let e = w.write_depth("x", &Raster::filled(3, 3, 1.0)).unwrap_err().to_string();
    assert!(e.contains("3x3") && e.contains("8x6"), "{e}");
    // A writer that never finishes leaves no cameras.json: the folder is not a scene.
    drop(w);
    assert!(!dir.path().join("cameras.json").exists());
    assert!(Scene::open(dir.path()).is_err());
    let w = SceneWriter::create(&dir.path().join("empty")).unwrap();
    assert!(w.finish().unwrap_err().to_string().contains("no frames"));
}

/// Writing into a folder that holds a scene replaces it whole at `finish` (no stale frame or
/// layer survives); a writer dropped before `finish` leaves the old scene exactly as it was,
/// and neither leaves a staging folder beside it.
#[test]
fn an_existing_scene_is_replaced_whole_or_not_at_all() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("s");
    write_scene(&dir);
    let before = walk(&dir);
    let rgb = image::RgbImage::from_pixel(W as u32, H as u32, image::Rgb([1, 2, 3]));

    // Abandoned half-way: the old scene is untouched.
    {
        let mut w = SceneWriter::create(&dir).unwrap();
        w.add_frame(Frame::new("c", &cam()), &rgb).unwrap();
        assert_ne!(w.root(), dir.as_path(), "an existing scene is never written into");
        assert_eq!(Scene::open(&dir).unwrap().frames().len(), 2, "the old scene reads while the new one is staged");
    }
    assert_eq!(walk(&dir), before);
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 1, "staging folder left behind");

    // Finished: only the new frame remains.
    let mut w = SceneWriter::create(&dir).unwrap();
    w.add_frame(Frame::new("c", &cam()), &rgb).unwrap();
    w.write_depth("c", &Raster::filled(W, H, 1.0)).unwrap();
    w.finish().unwrap();
    let s = Scene::open(&dir).unwrap();
    assert_eq!(s.frames().iter().map(|f| f.name.as_str()).collect::<Vec<_>>(), ["c"]);
    let mut files: Vec<String> =
        walk(&dir).iter().map(|f| Path::new(f).strip_prefix(&dir).unwrap().display().to_string()).collect();
    files.sort();
    // Beside the scene, the list of what dens3r wrote (what a later run may replace).
    assert_eq!(files, [".dens3r-outputs.json", "cameras.json", "depth/c.npy", "images/c.png"]);
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 1);
}

/// A reconstruction known up to a similarity (scale 0.4, a turn, a shift) of the truth's
/// cameras: `camera_similarity` finds that similarity's inverse from the camera centres, and
/// refuses cameras on one line.
#[test]
fn camera_similarity_places_a_scene_on_its_truth() {
    use dens3r_geom::transform::{axis_angle, Sim3};
    let dir = tempfile::tempdir().unwrap();
    let (gt, pred) = (dir.path().join("gt"), dir.path().join("pred"));
    let to_pred = Sim3 {
        scale: 0.4,
        rotation: axis_angle(DVec3::new(1.0, 2.0, 0.5), 0.7),
        translation: DVec3::new(3.0, -1.0, 2.0),
    };
    let write = |root: &Path, eyes: &[DVec3], sim: &Sim3| {
        let mut w = SceneWriter::create(root).unwrap();
        let rgb = image::RgbImage::new(W as u32, H as u32);
        for (i, &e) in eyes.iter().enumerate() {
            let c2w = look_at(e, DVec3::ZERO, DVec3::Z).unwrap();
            let mut cam = cam();
            // The similarity applied to the pose: rotation turned, centre moved and scaled.
            let r = sim.rotation * glam::DMat3::from_mat4(c2w);
            cam.cam_to_world = glam::DMat4::from_cols(
                r.x_axis.extend(0.0),
                r.y_axis.extend(0.0),
                r.z_axis.extend(0.0),
                sim.apply(e).extend(1.0),
            );
            w.add_frame(Frame::new(&format!("v{i}"), &cam), &rgb).unwrap();
        }
        w.finish().unwrap();
    };
    let eyes: Vec<DVec3> = (0..6)
        .map(|k| {
            let a = k as f64;
            DVec3::new(2.0 * a.cos(), 2.0 * a.sin(), 0.5 + 0.1 * a)
        })
        .collect();
    write(&gt, &eyes, &Sim3::rigid(glam::DMat3::IDENTITY, DVec3::ZERO));
    write(&pred, &eyes, &to_pred);
    let (sim, n) = dens3r_scene::eval::camera_similarity(&pred, &gt).unwrap();
    assert_eq!(n, 6);
    let back = to_pred.inverse();
    assert!((sim.scale - back.scale).abs() < 1e-9, "{} vs {}", sim.scale, back.scale);
    for &e in &eyes {
        assert!((sim.apply(to_pred.apply(e)) - e).length() < 1e-9);
    }
    let line: Vec<DVec3> = (0..4).map(|k| DVec3::new(k as f64, 1.0, 1.0)).collect();
    write(&gt, &line, &Sim3::rigid(glam::DMat3::IDENTITY, DVec3::ZERO));
    write(&pred, &line, &to_pred);
    let e = dens3r_scene::eval::camera_similarity(&pred, &gt).unwrap_err().to_string();
    assert!(e.contains("at least 3 not on one line"), "{e}");
}

/// Issue 77, 2: a scene folder without a manifest (written by hand, by another tool, or by a
/// dens3r before the manifest) holds nothing of dens3r's: its files, which an earlier rule
/// took from its cameras.json, are never replaced; the new scene is refused before anything
/// moves. With a manifest, a user's file where the next scene's frame goes is refused too.
#[test]
fn scenes_without_a_manifest_are_never_replaced() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("old");
    write_scene(&dir);
    std::fs::remove_file(dir.join(dens3r_io::output::MANIFEST)).unwrap();
    std::fs::write(dir.join("notes.txt"), "mine").unwrap();
    let rgb = image::RgbImage::from_pixel(W as u32, H as u32, image::Rgb([1, 2, 3]));
    let snapshot = || -> Vec<_> { walk(&dir).iter().map(|f| (f.clone(), std::fs::read(f).unwrap())).collect() };
    let before = snapshot();
    let mut w = SceneWriter::create(&dir).unwrap();
    w.add_frame(Frame::new("c", &cam()), &rgb).unwrap();
    let e = w.finish().unwrap_err().to_string();
    assert!(e.contains("cameras.json") && e.contains("not written by dens3r"), "{e}");
    assert_eq!(snapshot(), before);

    let dir = tmp.path().join("new");
    let mut w = SceneWriter::create(&dir).unwrap();
    w.add_frame(Frame::new("c", &cam()), &rgb).unwrap();
    w.finish().unwrap();
    // A user's picture where the next scene's frame goes: refused at finish, nothing moved.
    std::fs::write(dir.join("images/d.png"), "my picture").unwrap();
    let before: Vec<_> = walk(&dir).iter().map(|f| (f.clone(), std::fs::read(f).unwrap())).collect();
    let mut w = SceneWriter::create(&dir).unwrap();
    w.add_frame(Frame::new("d", &cam()), &rgb).unwrap();
    let e = w.finish().unwrap_err().to_string();
    assert!(e.contains("images/d.png") && e.contains("not written by dens3r"), "{e}");
    let after: Vec<_> = walk(&dir).iter().map(|f| (f.clone(), std::fs::read(f).unwrap())).collect();
    assert_eq!(after, before);
}
