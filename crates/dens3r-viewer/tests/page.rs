//! The page's geometry against analytic scenes, the files it writes, and the server's paths.

use dens3r_geom::{look_at, Intrinsics, PinholeCamera, Raster};
use dens3r_mesh::primitives::icosphere;
use dens3r_viewer::cloud::{cloud, stride_for};
use dens3r_viewer::decimate::decimate;
use dens3r_viewer::serve::resolve;
use dens3r_viewer::{write_page, MatchPicture, Page, PageOptions, View};
use glam::{DVec3, Vec3};
use image::RgbImage;

/// A camera at `eye` looking at the origin, 64 x 48, 60 degrees across.
fn camera(eye: DVec3) -> PinholeCamera {
    PinholeCamera {
        intrinsics: Intrinsics::from_hfov(64, 48, 60.0),
        width: 64,
        height: 48,
        cam_to_world: look_at(eye, DVec3::ZERO, DVec3::new(0.0, -1.0, 0.0)).unwrap(),
    }
}

/// The exact depth of the unit sphere seen by `cam` (0 where a ray misses it).
fn sphere_depth(cam: &PinholeCamera) -> Raster<f32> {
    let c = cam.center();
    Raster::from_fn(cam.width, cam.height, |x, y| {
        let ray = cam.intrinsics.unproject(x as f64, y as f64); // camera frame, z = 1
        let dir = cam.cam_to_world.transform_vector3(ray);
        // |c + t dir|^2 = 1, nearest root; depth is t (z = 1 along the ray).
        let (a, b, cc) = (dir.length_squared(), 2.0 * c.dot(dir), c.length_squared() - 1.0);
        let disc = b * b - 4.0 * a * cc;
        if disc < 0.0 {
            0.0
        } else {
            ((-b - disc.sqrt()) / (2.0 * a)) as f32
        }
    })
}

#[test]
fn the_cloud_lies_on_the_surface_the_depth_maps_saw_and_keeps_the_budget() {
    let cams = [camera(DVec3::new(0.0, 0.0, -3.0)), camera(DVec3::new(3.0, 0.0, 0.0))];
    let depths: Vec<_> = cams.iter().map(sphere_depth).collect();
    let conf: Vec<Raster<f32>> =
        cams.iter().enumerate().map(|(k, c)| Raster::filled(c.width, c.height, 1.0 + k as f32)).collect();
    let rgb = RgbImage::new(64, 48);
    let views: Vec<View> = (0..2)
        .map(|k| View {
            name: "v",
            camera: cams[k],
            rgb: &rgb,
            depth: &depths[k],
            conf: Some(&conf[k]),
            normals: None,
            mask: None,
            photo: None,
        })
        .collect();
    let all = cloud(&views, usize::MAX);
    let valid: usize = depths.iter().map(|d| d.data().iter().filter(|z| **z > 0.0).count()).sum();
    assert_eq!(all.positions.len(), valid);
    for p in &all.positions {
        assert!((p.length() - 1.0).abs() < 1e-4, "{p} is not on the unit sphere");
    }
    // Sorted by confidence: the second view's points (confidence 2) first.
    assert!(all.conf.windows(2).all(|w| w[0] >= w[1]));
    assert_eq!(all.conf[0], 2.0);
    let few = cloud(&views, 300);
    assert!(few.positions.len() <= 300 && few.positions.len() > 300 / 4, "{}", few.positions.len());
    // The spacing the page sizes points by is the distance between neighbouring samples.
    let mut nearest: Vec<f32> = few
        .positions
        .iter()
        .map(|p| few.positions.iter().filter(|q| *q != p).map(|q| q.distance(*p)).fold(f32::MAX, f32::min))
        .collect();
    nearest.sort_by(f32::total_cmp);
    let measured = nearest[nearest.len() / 2];
    assert!(few.spacing > 0.6 * measured && few.spacing < 1.6 * measured, "{} against {measured}", few.spacing);
    assert_eq!(stride_for(1000, 1000), 1);
    assert_eq!(stride_for(1001, 1000), 2);
    assert_eq!(stride_for(4001, 1000), 3);
}

#[test]
fn decimation_keeps_the_budget_and_the_shape() {
    let sphere = icosphere(1.0, 5); // 20 * 4^5 = 20480 triangles
    assert_eq!(sphere.indices.len(), 20480);
    let small = decimate(&sphere, 2000);
    assert!(small.indices.len() <= 2000 && small.indices.len() > 200, "{}", small.indices.len());
    small.validate().unwrap();
    // Cluster means of points on the unit sphere lie just inside it.
    for p in &small.positions {
        assert!(p.length() > 0.95 && p.length() <= 1.0 + 1e-5, "{}", p.length());
    }
    // Every vertex is used, and the surface still encloses about the sphere's volume.
    let mut used = vec![false; small.positions.len()];
    small.indices.iter().flatten().for_each(|&i| used[i as usize] = true);
    assert!(used.iter().all(|u| *u));
    let volume: f32 = small
        .indices
        .iter()
        .map(|t| {
            small.positions[t[0] as usize].dot(small.positions[t[1] as usize].cross(small.positions[t[2] as usize]))
                / 6.0
        })
        .sum();
    let exact = 4.0 / 3.0 * std::f32::consts::PI;
    assert!((volume.abs() - exact).abs() / exact < 0.05, "volume {volume} against {exact}");
    // Small meshes pass through unchanged.
    assert_eq!(decimate(&sphere, 1 << 20), sphere);
}

#[test]
fn the_page_holds_the_views_the_geometry_and_the_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let cam = camera(DVec3::new(0.0, 0.0, -3.0));
    let depth = sphere_depth(&cam);
    let conf = Raster::filled(64, 48, 3.0f32);
    let normals = Raster::filled(64, 48, Vec3::new(0.0, 0.0, -1.0));
    let rgb = RgbImage::from_pixel(64, 48, image::Rgb([200, 10, 10]));
    let mesh = icosphere(1.0, 2);
    let page = Page {
        title: "a <test>".into(),
        views: vec![View {
            name: "f#1",
            camera: cam,
            rgb: &rgb,
            depth: &depth,
            conf: Some(&conf),
            normals: Some(&normals),
            mask: None,
            photo: Some("scene/images/f#1.png".into()),
        }],
        mesh: Some(&mesh),
        summary: Some(serde_json::json!({"photos": 1})),
        scores: None,
        matches: vec![MatchPicture { a: "f#1".into(), b: "g".into(), path: "matches/f#1-g.png".into() }],
        min_conf: 1.5,
    };
    let s = write_page(dir.path(), &page, &PageOptions::default()).unwrap();
    assert_eq!(s.triangles, mesh.indices.len());
    let html = std::fs::read_to_string(dir.path().join("index.html")).unwrap();
    assert!(html.contains("<title>a &lt;test&gt; - dens3r</title>"));
    assert!(
        html.contains(r#"<script src="viewer/scene.js"></script>"#)
            && html.contains(r#"<script src="viewer/app.js"></script>"#)
    );
    assert!(!html.contains("https://"), "the page loads nothing from the network");
    let script = std::fs::read_to_string(dir.path().join("viewer/scene.js")).unwrap();
    let json = script.strip_prefix("window.DENS3R_SCENE = ").unwrap().trim_end().strip_suffix(';').unwrap();
    let data: serde_json::Value = serde_json::from_str(json).unwrap();
    let v = &data["views"][0];
    assert_eq!(v["name"], "f#1");
    // The pose as rows: the camera centre in the last column.
    assert!((v["c2w"][11].as_f64().unwrap() + 3.0).abs() < 1e-12);
    assert_eq!(v["pictures"]["photo"], "scene/images/f%231.png", "a '#' in a name is escaped");
    for kind in ["depth", "normals", "conf"] {
        let p = v["pictures"][kind].as_str().unwrap();
        let img = image::open(dir.path().join(p)).unwrap();
        assert_eq!((img.width(), img.height()), (64, 48), "{kind}");
    }
    // A camera-facing normal in the official colours.
    let n = image::open(dir.path().join(v["pictures"]["normals"].as_str().unwrap())).unwrap().to_rgb8();
    assert_eq!(n.get_pixel(10, 10).0, [127, 127, 255]);
    assert!(v["thumb"].as_str().unwrap().starts_with("data:image/jpeg;base64,"));
    assert_eq!(data["matches"][0]["path"], "matches/f%231-g.png");
    assert_eq!(data["mesh"]["triangles"], mesh.indices.len());
    let count = data["points"]["count"].as_u64().unwrap() as usize;
    assert_eq!(count, depth.data().iter().filter(|z| **z > 0.0).count());
    use base64::Engine;
    let bytes =
        base64::engine::general_purpose::STANDARD.decode(data["points"]["positions"].as_str().unwrap()).unwrap();
    assert_eq!(bytes.len(), count * 12);
    let radius = data["bounds"]["radius"].as_f64().unwrap();
    assert!(radius > 0.5 && radius < 1.8, "{radius}");
    assert!(dir.path().join("viewer/app.js").is_file() && dir.path().join("viewer/THREE-LICENSE.txt").is_file());
    let licence = std::fs::read_to_string(dir.path().join("viewer/THREE-LICENSE.txt")).unwrap();
    assert!(licence.contains("MIT") || licence.contains("Permission is hereby granted"));
}

#[test]
fn the_server_serves_only_files_under_its_folder() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("viewer")).unwrap();
    std::fs::write(dir.path().join("index.html"), "x").unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("scene/images")).unwrap();
    std::fs::write(root.join("viewer/app.js"), "x").unwrap();
    std::fs::write(root.join("scene/images/f#1.png"), "x").unwrap();
    assert_eq!(resolve(root, "/"), Some(root.join("index.html")));
    assert_eq!(resolve(root, "/viewer/app.js?x=1"), Some(root.join("viewer/app.js")));
    assert_eq!(resolve(root, "/scene/images/f%231.png"), Some(root.join("scene/images/f#1.png")));
    assert_eq!(resolve(root, "/../secret"), None);
    assert_eq!(resolve(root, "/viewer/%2e%2e/%2e%2e/etc/passwd"), None);
    assert_eq!(resolve(root, "/%zz"), None);
    assert_eq!(resolve(root, "/missing.js"), None);
    // Issue 77, 4: symbolic links out of the folder served what they point at.
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink("/", root.join("rootfs")).unwrap();
        std::os::unix::fs::symlink("/etc/passwd", root.join("viewer/p.js")).unwrap();
        std::os::unix::fs::symlink("app.js", root.join("viewer/inside.js")).unwrap();
        assert_eq!(resolve(root, "/rootfs/etc/passwd"), None);
        assert_eq!(resolve(root, "/viewer/p.js"), None);
        assert_eq!(resolve(root, "/viewer/inside.js"), Some(root.join("viewer/inside.js")), "a link inside stays");
    }
    // Only requests for this machine (DNS rebinding sends the attacker's name).
    use dens3r_viewer::serve::local_host;
    for ok in ["127.0.0.1:8473", "localhost:8473", "LOCALHOST:8473", "[::1]:8473", "localhost"] {
        assert!(local_host(ok, 8473), "{ok}");
    }
    for bad in ["evil.example:8473", "127.0.0.1.evil.example:8473", "localhost:80", "127.0.0.2:8473", "", "[::1]:1"] {
        assert!(!local_host(bad, 8473), "{bad}");
    }
}

#[test]
fn eval_scores_join_the_page_that_shows_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    std::fs::create_dir_all(out.join("scene")).unwrap();
    // The page as an output transaction writes it: staged, then moved in with dens3r's list.
    let o = dens3r_io::output::OutputDir::begin(&out).unwrap();
    write_page(o.root(), &Page { title: "t".into(), ..Default::default() }, &PageOptions::default()).unwrap();
    o.finish().unwrap();
    assert_eq!(std::fs::read_to_string(out.join("viewer/scores.js")).unwrap(), "window.DENS3R_SCORES = null;\n");
    // A scene folder inside the output, and a mesh file beside the page, both find it.
    let page =
        dens3r_viewer::add_scores(&out.join("scene"), "cameras", serde_json::json!({"rotation_median_deg": 0.5}));
    assert_eq!(page.unwrap(), Some(out.join("index.html")));
    dens3r_viewer::add_scores(&out.join("mesh.glb"), "mesh", serde_json::json!({"chamfer_l1": 0.01})).unwrap();
    dens3r_viewer::add_scores(&out.join("scene"), "cameras", serde_json::json!({"rotation_median_deg": 0.25})).unwrap();
    let text = std::fs::read_to_string(out.join("viewer/scores.js")).unwrap();
    let json: serde_json::Value =
        serde_json::from_str(text.strip_prefix("window.DENS3R_SCORES = ").unwrap().trim_end().trim_end_matches(';'))
            .unwrap();
    assert_eq!(json, serde_json::json!({"cameras": {"rotation_median_deg": 0.25}, "mesh": {"chamfer_l1": 0.01}}));
    // A page dens3r did not write (no list of its outputs names it): left alone.
    let theirs = dir.path().join("theirs");
    std::fs::create_dir_all(theirs.join("viewer")).unwrap();
    std::fs::write(theirs.join("index.html"), "mine").unwrap();
    std::fs::write(theirs.join("viewer/scores.js"), "mine").unwrap();
    assert_eq!(dens3r_viewer::add_scores(&theirs, "cameras", serde_json::json!({})).unwrap(), None);
    assert_eq!(std::fs::read_to_string(theirs.join("viewer/scores.js")).unwrap(), "mine");
    // A folder no page shows: nothing written.
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir_all(&elsewhere).unwrap();
    assert_eq!(dens3r_viewer::add_scores(&elsewhere, "cameras", serde_json::json!({})).unwrap(), None);
    assert!(!elsewhere.join("viewer").exists());
}

/// Large frames are read every s-th pixel with the camera scaled to match: the points still
/// lie where the full-size depth puts them (a slanted plane seen by an identity camera).
#[test]
fn large_frames_are_read_subsampled_with_their_camera() {
    use dens3r_viewer::scene_views::{SceneViews, MAX_SIDE};
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (1300usize, 900usize);
    let cam = PinholeCamera {
        intrinsics: Intrinsics { fx: 1000.0, fy: 1000.0, cx: 650.0, cy: 450.0 },
        width: w,
        height: h,
        cam_to_world: glam::DMat4::IDENTITY,
    };
    // The plane z = 2 + 0.5 x (camera frame): depth d at pixel u solves d = 2 + 0.5 d (u - cx) / fx.
    let depth = Raster::from_fn(w, h, |x, _| (2.0 / (1.0 - 0.5 * (x as f64 - 650.0) / 1000.0)) as f32);
    let mut sw = dens3r_scene::SceneWriter::create(&dir.path().join("scene")).unwrap();
    sw.add_frame(dens3r_scene::Frame::new("big", &cam), &RgbImage::new(w as u32, h as u32)).unwrap();
    sw.write_depth("big", &depth).unwrap();
    sw.finish().unwrap();
    let scene = dens3r_scene::Scene::open(&dir.path().join("scene")).unwrap();
    let views = SceneViews::read(&scene, "scene/").unwrap();
    let (d, c) = (&views.depth[0], &views.cameras[0]);
    assert!(d.width().max(d.height()) <= MAX_SIDE && d.width() >= MAX_SIDE / 2, "{}x{}", d.width(), d.height());
    assert_eq!((c.width, c.height), (d.width(), d.height()));
    let pts = cloud(&views.views(), usize::MAX);
    assert_eq!(pts.positions.len(), d.width() * d.height());
    for p in &pts.positions {
        assert!((p.z - (2.0 + 0.5 * p.x)).abs() < 1e-4, "{p} is off the plane");
    }
    // The subsampled image spans the full one's field of view.
    let xs = pts.positions.iter().map(|p| p.x / p.z);
    let (lo, hi) = xs.fold((f32::MAX, f32::MIN), |(l, h), x| (l.min(x), h.max(x)));
    assert!((lo + 0.65).abs() < 0.01 && (hi - 0.65).abs() < 0.01, "{lo} {hi}");
    assert_eq!(views.photos[0], "scene/images/big.png");
}
