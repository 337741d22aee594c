//! The COLMAP export read back by COLMAP's own parser (pycolmap from PyPI, installed into
//! `.cache/bench-venv` by scripts/bench-setup.sh); says SKIPPED when pycolmap is absent.

use dens3r_geom::camera::{look_at, rigid_inverse};
use dens3r_geom::{DVec3, Intrinsics, PinholeCamera};
use dens3r_scene::export::{write_colmap_text, TrackPoint};
use dens3r_scene::Frame;
use std::path::Path;
use std::process::Command;

#[test]
fn pycolmap_reads_our_colmap_model() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join(".cache/bench-venv/bin/python3");
    let has = Command::new(&python).args(["-c", "import pycolmap"]).output().is_ok_and(|o| o.status.success());
    if !has {
        eprintln!("SKIPPED: {} has no pycolmap (run scripts/bench-setup.sh)", python.display());
        return;
    }
    let cams: Vec<PinholeCamera> = (0..3)
        .map(|i| {
            let a = i as f64 * 2.0;
            PinholeCamera {
                intrinsics: Intrinsics::from_hfov(160 + 16 * i, 120, 50.0 + 5.0 * i as f64),
                width: 160 + 16 * i,
                height: 120,
                cam_to_world: look_at(DVec3::new(3.0 * a.cos(), 3.0 * a.sin(), 1.0), DVec3::ZERO, DVec3::Z).unwrap(),
            }
        })
        .collect();
    let frames: Vec<Frame> = cams.iter().enumerate().map(|(i, c)| Frame::new(&format!("f{i}"), c)).collect();
    let points: Vec<TrackPoint> = [DVec3::new(0.1, 0.2, 0.3), DVec3::new(-0.3, 0.1, 0.0)]
        .iter()
        .map(|&x| TrackPoint {
            xyz: x,
            rgb: [200, 100, 50],
            error: 0.5,
            observations: cams
                .iter()
                .enumerate()
                .map(|(i, c)| (i, c.intrinsics.project(rigid_inverse(&c.cam_to_world).transform_point3(x))))
                .collect(),
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    write_colmap_text(dir.path(), &frames, &points).unwrap();
    let out = Command::new(&python).arg(root.join("bench/pycolmap_read.py")).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let j: serde_json::Value =
        serde_json::from_slice(out.stdout.rsplit(|&b| b == b'\n').find(|l| !l.is_empty()).unwrap()).unwrap();
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    let images = j["images"].as_array().unwrap();
    assert_eq!(images.len(), 3);
    for (i, im) in images.iter().enumerate() {
        let k = cams[i].intrinsics;
        assert_eq!(im["name"], frames[i].image.as_str());
        assert_eq!(im["model"], "PINHOLE");
        assert_eq!(im["width"].as_u64().unwrap() as usize, cams[i].width);
        let p: Vec<f64> = im["params"].as_array().unwrap().iter().map(f).collect();
        let want = [k.fx, k.fy, k.cx + 0.5, k.cy + 0.5];
        assert!(p.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-9), "{p:?} vs {want:?}");
        let c: Vec<f64> = im["center"].as_array().unwrap().iter().map(f).collect();
        assert!((DVec3::new(c[0], c[1], c[2]) - cams[i].center()).length() < 1e-9, "centre {c:?}");
        let w2c = rigid_inverse(&cams[i].cam_to_world);
        for r in 0..3 {
            for col in 0..4 {
                let ours = w2c.col(col)[r];
                assert!((f(&im["world_to_cam"][r][col]) - ours).abs() < 1e-9);
            }
        }
        // Keypoints in COLMAP's convention: ours + 0.5.
        for (t, pt) in points.iter().enumerate() {
            let (u, v) = pt.observations[i].1;
            let kp = &im["points2d"][t];
            assert!((f(&kp[0]) - (u + 0.5)).abs() < 1e-9 && (f(&kp[1]) - (v + 0.5)).abs() < 1e-9);
        }
    }
    let pts = j["points"].as_array().unwrap();
    assert_eq!(pts.len(), 2);
    assert_eq!(pts[0]["track"].as_array().unwrap().len(), 3);
    eprintln!("pycolmap {} read the model back", j["pycolmap"]);
}
