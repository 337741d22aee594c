//! Real scanned meshes (Stanford bunny, armadillo, Chinese dragon from Debian's libcgal-demo),
//! fetched by `scripts/fetch-data.sh` into `.cache/data/meshes/` (or `$DENS3R_DATA/meshes`).
//! Without the data these tests print why and pass, except under CI (`CI` set), where the
//! fetch is part of the run and missing data is a failure.

use dens3r_geom::metrics::normal_metrics;
use dens3r_geom::normals::normals_from_pointmap_robust;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{focal_from_pointmap, FocalMode, Intrinsics, PinholeCamera};
use dens3r_mesh::{mesh_metrics, read_mesh, MeshMetricsOptions};
use dens3r_render::procedural::single_object;
use dens3r_render::{path, World};

use crate::fetched::fetched;

#[test]
fn scanned_meshes_render_consistently() {
    for name in ["bunny00.off", "armadillo.off", "ChineseDragon-10kv.off"] {
        let Some(p) = fetched(&format!("meshes/{name}"), "Debian's libcgal-demo") else { return };
        let mesh = read_mesh(&p).unwrap();
        assert!(mesh.indices.len() > 10_000, "{name}: {} triangles", mesh.indices.len());
        let world = World::new(single_object(mesh.clone(), 0)).unwrap();
        let (lo, hi) = world.bounds();
        let poses = path::orbit(((lo + hi) * 0.5).as_dvec3(), (hi - lo).length() as f64, 25.0, 15.0, 2);
        for pose in poses {
            // Scans have triangles smaller than a pixel at low resolution, where a pixel's face
            // normal is scan noise that depth differences average out (measured: bunny median
            // 2.0 deg at 240x180, 0.84 at 480x360, 0.06 at 960x720). Resolve the triangles.
            let cam = PinholeCamera {
                intrinsics: Intrinsics::from_hfov(960, 720, 50.0),
                width: 960,
                height: 720,
                cam_to_world: pose,
            };
            let view = world.render(&cam);
            let pts = depth_to_pointmap(&view.depth, &cam.intrinsics);
            // Rendered normals agree with the normals of the rendered depth.
            let m = normal_metrics(&normals_from_pointmap_robust(&pts, 0.05), &view.normals, None).unwrap();
            assert!(m.median < 2.0, "{name}: median {} deg", m.median);
            // Weiszfeld recovers the focal from a pointmap of a real shape.
            let f = focal_from_pointmap(&pts, (480.0, 360.0), FocalMode::Weiszfeld).unwrap();
            assert!((f / cam.intrinsics.fx - 1.0).abs() < 0.005, "{name}: focal {f} vs {}", cam.intrinsics.fx);
        }
        // A 1% scaling about the centre moves every point by about 1% of its radius.
        let mut scaled = mesh.clone();
        let c = (lo + hi) * 0.5;
        scaled.transform(
            &(glam::Mat4::from_translation(c)
                * glam::Mat4::from_scale(glam::Vec3::splat(1.01))
                * glam::Mat4::from_translation(-c)),
        );
        let opts = MeshMetricsOptions { samples: 20_000, thresholds: vec![1e-9], seed: 1 };
        let same = mesh_metrics(&mesh, &mesh, &opts).unwrap();
        let diff = mesh_metrics(&scaled, &mesh, &opts).unwrap();
        let size = (hi - lo).length() as f64;
        assert!(same.chamfer_l1 < 1e-6 * size, "{name}: {}", same.chamfer_l1);
        assert!(
            diff.chamfer_l1 > 1e-4 * size && diff.chamfer_l1 < 0.01 * size,
            "{name}: {} (size {size})",
            diff.chamfer_l1
        );
    }
}
