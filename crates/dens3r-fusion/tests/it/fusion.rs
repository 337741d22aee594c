//! TSDF fusion and marching cubes against analytic geometry and ground-truth renders.

use dens3r_fusion::{extract_mesh, ExtractOptions, FrameInput, SparseTsdf, TsdfParams};
use dens3r_geom::{DVec3, Intrinsics, PinholeCamera, Raster};
use dens3r_mesh::metrics::{mesh_metrics, MeshMetricsOptions};
use dens3r_render::material::{Material, Texture};
use dens3r_render::path::orbit;
use dens3r_render::{Object, Shape, World};
use glam::{Quat, Vec3};
use std::collections::HashMap;

fn sphere_world(center: Vec3, radius: f32) -> World {
    let mat = Material { color: [0.2, 0.6, 0.9], texture: Texture::Checker { size: 0.1 }, seed: 3 };
    World::new(vec![Object {
        name: "sphere".into(),
        shape: Shape::Sphere { radius },
        rotation: Quat::IDENTITY,
        translation: center,
        class_id: 1,
        material: mat,
    }])
    .unwrap()
}

/// Fuses an orbit of renders of `world` around `center`, optionally weighting pixels by the
/// rendered normals' angle to the ray.
fn fuse_orbit(world: &World, center: Vec3, dist: f64, n: usize, params: TsdfParams) -> SparseTsdf {
    fuse_orbit_weighted(world, center, dist, n, params, false)
}

fn fuse_orbit_weighted(
    world: &World,
    center: Vec3,
    dist: f64,
    n: usize,
    params: TsdfParams,
    angle: bool,
) -> SparseTsdf {
    let (w, h) = (160, 120);
    let k = Intrinsics::from_hfov(w, h, 60.0);
    let mut tsdf = SparseTsdf::new(params).unwrap();
    // Two rings (above and below) so the closed surface is seen everywhere.
    for el in [35.0, -35.0] {
        for pose in orbit(center.as_dvec3(), dist, el, 0.0, n) {
            let cam = PinholeCamera { intrinsics: k, width: w, height: h, cam_to_world: pose };
            let view = world.render(&cam);
            let aw = angle.then(|| dens3r_fusion::tsdf::angle_weights(&view.normals, &cam));
            let f =
                FrameInput { name: "v", camera: &cam, depth: &view.depth, color: Some(&view.rgb), weight: aw.as_ref() };
            tsdf.integrate(&f).unwrap();
        }
    }
    tsdf
}

#[test]
fn sphere_is_closed_accurate_and_oriented() {
    // Centre off the block grid so block borders cut the surface everywhere.
    let (c, r) = (Vec3::new(0.013, -0.021, 0.007), 0.3f32);
    let world = sphere_world(c, r);
    let voxel = 0.01;
    let tsdf = fuse_orbit(&world, c, 1.2, 12, TsdfParams::new(voxel));
    let mesh = extract_mesh(tsdf.grid(), &ExtractOptions::default());
    let stats = |mesh: &dens3r_mesh::TriMesh| {
        let mut err: Vec<f32> = mesh.positions.iter().map(|p| ((*p - c).length() - r).abs()).collect();
        let mut deg: Vec<f32> = mesh
            .positions
            .iter()
            .zip(mesh.normals.as_ref().unwrap())
            .map(|(p, n)| n.dot((*p - c).normalize()).clamp(-1.0, 1.0).acos().to_degrees())
            .collect();
        err.sort_by(f32::total_cmp);
        deg.sort_by(f32::total_cmp);
        let mean = err.iter().sum::<f32>() / err.len() as f32;
        let pct = |v: &[f32], q: usize| v[v.len() * q / 100];
        (mean, pct(&err, 99), err[err.len() - 1], pct(&deg, 50), pct(&deg, 99))
    };
    assert!(mesh.indices.len() > 10_000, "{} triangles", mesh.indices.len());
    // Vertices within a fraction of a voxel of the analytic sphere.
    let (mean, p99, worst, med_deg, p99_deg) = stats(&mesh);
    eprintln!("sphere: mean {mean}, p99 {p99}, worst {worst}; normals median {med_deg}, p99 {p99_deg} deg");
    assert!(mean < 0.15 * voxel && p99 < 0.4 * voxel && worst < voxel, "mean {mean}, p99 {p99}, worst {worst}");
    // Projective distances bias the field at grazing angles: normals within a few degrees...
    assert!(med_deg < 6.0, "median normal error {med_deg} deg");
    // ... and weighting pixels by the normal-to-ray angle removes most of that bias.
    let weighted = extract_mesh(
        fuse_orbit_weighted(&world, c, 1.2, 12, TsdfParams::new(voxel), true).grid(),
        &ExtractOptions::default(),
    );
    let (wmean, _, _, wmed, wp99) = stats(&weighted);
    eprintln!("sphere, angle-weighted: mean {wmean}; normals median {wmed}, p99 {wp99} deg");
    assert!(wmed < 2.5 && wp99 < 7.0 && wmed < 0.6 * med_deg, "weighted normals median {wmed}, p99 {wp99} deg");
    assert!(wmean < 0.7 * mean, "weighted mean error {wmean} vs {mean}");
    // Watertight: every edge is shared by exactly two triangles, also across block borders.
    let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
    for t in &mesh.indices {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *edges.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    let open = edges.values().filter(|&&n| n != 2).count();
    assert_eq!(open, 0, "{open} of {} edges are not shared by exactly two triangles", edges.len());
    // Faces wind counter-clockwise around the outward normal.
    let outward = (0..mesh.indices.len()).filter(|&t| mesh.face_normal(t).dot(mesh.triangle(t)[0] - c) > 0.0).count();
    assert_eq!(outward, mesh.indices.len(), "every face winds counter-clockwise seen from outside");
    // Colours come from the renders (the sphere is blue-ish: blue channel dominates).
    let colors = mesh.colors.as_ref().unwrap();
    let blue = colors.iter().filter(|c| c[2] > c[0]).count();
    assert!(blue as f64 > 0.95 * colors.len() as f64, "{blue} of {} vertices blue", colors.len());
}

#[test]
fn memory_grows_with_the_surface_not_the_box() {
    // Two spheres 4 m apart: a dense grid over their bounding box would need ~ 440^3 voxels
    // (85M, > 1 GB); the sparse grid only holds blocks near the two surfaces.
    let mat = Material { color: [0.5; 3], texture: Texture::Plain, seed: 0 };
    let obj = |x: f32| Object {
        name: "s".into(),
        shape: Shape::Sphere { radius: 0.2 },
        rotation: Quat::IDENTITY,
        translation: Vec3::new(x, 0.0, 0.0),
        class_id: 1,
        material: mat.clone(),
    };
    let world = World::new(vec![obj(-2.0), obj(2.0)]).unwrap();
    let mut params = TsdfParams::new(0.01);
    params.color = false;
    let a = fuse_orbit(&world, Vec3::new(-2.0, 0.0, 0.0), 0.8, 8, params.clone());
    let mut both = fuse_orbit(&world, Vec3::new(-2.0, 0.0, 0.0), 0.8, 8, params.clone());
    let b = fuse_orbit(&world, Vec3::new(2.0, 0.0, 0.0), 0.8, 8, params.clone());
    // Integrating the second sphere's views into the first volume adds about its own blocks.
    let (w, h) = (160, 120);
    let k = Intrinsics::from_hfov(w, h, 60.0);
    for el in [35.0, -35.0] {
        for pose in orbit(DVec3::new(2.0, 0.0, 0.0), 0.8, el, 0.0, 8) {
            let cam = PinholeCamera { intrinsics: k, width: w, height: h, cam_to_world: pose };
            let view = world.render(&cam);
            let f = FrameInput { name: "v", camera: &cam, depth: &view.depth, color: None, weight: None };
            both.integrate(&f).unwrap();
        }
    }
    let sum = a.block_count() + b.block_count();
    assert!((both.block_count() as f64 - sum as f64).abs() < 0.1 * sum as f64, "{} vs {sum}", both.block_count());
    assert!(both.memory_bytes() < 100_000_000, "{} bytes", both.memory_bytes());
    // A budget below what the scene needs stops with a clear error, before allocating.
    let mut tight = params;
    tight.budget_bytes = Some(a.memory_bytes() / 2);
    let mut t = SparseTsdf::new(tight).unwrap();
    let mut err = None;
    for pose in orbit(DVec3::new(-2.0, 0.0, 0.0), 0.8, 35.0, 0.0, 8) {
        let cam = PinholeCamera { intrinsics: k, width: w, height: h, cam_to_world: pose };
        let view = world.render(&cam);
        let f = FrameInput { name: "v", camera: &cam, depth: &view.depth, color: None, weight: None };
        if let Err(e) = t.integrate(&f) {
            err = Some(e.to_string());
            break;
        }
    }
    let err = err.expect("the budget must be hit");
    assert!(err.contains("budget") && err.contains("--voxel"), "{err}");
    assert!(t.memory_bytes() <= a.memory_bytes() / 2, "nothing allocated past the budget");
}

#[test]
fn rendered_room_matches_ground_truth() {
    let world = World::new(dens3r_render::procedural::room(1)).unwrap();
    let (lo, hi) = world.bounds();
    let (w, h) = (320, 240);
    let k = Intrinsics::from_hfov(w, h, 70.0);
    let poses = dens3r_render::path::room_walk(lo.as_dvec3(), hi.as_dvec3(), 1.5, 30, 7);
    let mut params = TsdfParams::new(0.02);
    params.depth_range = (0.1, 8.0);
    let mut tsdf = SparseTsdf::new(params).unwrap();
    for pose in &poses {
        let cam = PinholeCamera { intrinsics: k, width: w, height: h, cam_to_world: *pose };
        let view = world.render(&cam);
        let f = FrameInput { name: "v", camera: &cam, depth: &view.depth, color: Some(&view.rgb), weight: None };
        tsdf.integrate(&f).unwrap();
    }
    let mesh = extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: 50, crop: None });
    let gt = world.gt_mesh();
    let m = mesh_metrics(&mesh, &gt, &MeshMetricsOptions { samples: 50_000, thresholds: vec![0.02, 0.04], seed: 1 })
        .unwrap();
    eprintln!("room: {m:?}");
    // (Completeness and normal consistency also count the ground truth the walk never saw:
    // backs of furniture, the floor under it.)
    // Accuracy (fused surface -> truth) is what fusion controls; completeness also depends on
    // which parts of the room the 30 views saw.
    assert!(m.accuracy < 0.006, "accuracy {}", m.accuracy);
    assert!(m.fscores[0].precision > 0.97, "precision@2cm {}", m.fscores[0].precision);
}

#[test]
fn bad_parameters_and_frames_are_errors() {
    for v in [0.0, -0.01, f32::NAN] {
        let e = SparseTsdf::new(TsdfParams::new(v)).err().expect("invalid voxel").to_string();
        assert!(e.contains("voxel size"), "{e}");
    }
    let mut p = TsdfParams::new(0.01);
    p.trunc = 0.001;
    assert!(SparseTsdf::new(p).err().unwrap().to_string().contains("truncation"));
    let mut t = SparseTsdf::new(TsdfParams::new(0.01)).unwrap();
    let cam = PinholeCamera {
        intrinsics: Intrinsics::from_hfov(8, 6, 60.0),
        width: 8,
        height: 6,
        cam_to_world: glam::DMat4::IDENTITY,
    };
    let wrong = Raster::filled(4, 3, 1.0f32);
    let e = t.integrate(&FrameInput { name: "f7", camera: &cam, depth: &wrong, color: None, weight: None });
    assert!(e.err().unwrap().to_string().contains("f7"));
    // All-invalid depth integrates nothing (the scene driver reports it).
    let invalid = Raster::filled(8, 6, f32::NAN);
    t.integrate(&FrameInput { name: "f", camera: &cam, depth: &invalid, color: None, weight: None }).unwrap();
    assert_eq!(t.block_count(), 0);
}

/// Fusion gives the same grid whatever the thread count: blocks in the same order (consumers
/// such as the neural SDF's TSDF start sample them by index) and the same values, so a run
/// repeats bit for bit on a loaded or an idle machine.
#[test]
fn fusion_is_deterministic_across_thread_counts() {
    let (c, r) = (Vec3::new(0.013, -0.021, 0.007), 0.3f32);
    let world = sphere_world(c, r);
    let fuse = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| fuse_orbit(&world, c, 1.2, 6, TsdfParams::new(0.01)))
    };
    let grids: Vec<SparseTsdf> = [1, 3, 7].into_iter().map(fuse).collect();
    let keys = |t: &SparseTsdf| t.blocks().map(|(k, _)| k).collect::<Vec<_>>();
    let values = |t: &SparseTsdf| t.blocks().flat_map(|(_, b)| b.tsdf.clone()).map(f32::to_bits).collect::<Vec<_>>();
    assert!(keys(&grids[0]).len() > 100);
    for g in &grids[1..] {
        assert!(keys(g) == keys(&grids[0]), "block order depends on the thread count");
        assert!(values(g) == values(&grids[0]), "values depend on the thread count");
    }
}

/// Frames handed over from memory fuse to the same grid, bit for bit, as the scene folder the
/// same renders were written to (with its weights from confidence and normals), so a
/// reconstruction can fuse what it holds without writing and re-reading it.
#[test]
fn frames_from_memory_fuse_as_their_scene_folder() {
    use dens3r_fusion::scene::{fuse_frames, fuse_scene, FusionFrame, SceneFusion};
    use std::borrow::Cow;
    let (c, r) = (Vec3::new(0.013, -0.021, 0.007), 0.3f32);
    let world = sphere_world(c, r);
    let k = Intrinsics::from_hfov(96, 72, 60.0);
    let cams: Vec<PinholeCamera> = orbit(c.as_dvec3(), 1.2, 30.0, 0.0, 5)
        .into_iter()
        .map(|pose| PinholeCamera { intrinsics: k, width: 96, height: 72, cam_to_world: pose })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    dens3r_render::render_cameras_to_scene(&world, &cams, &Default::default(), false, dir.path(), |_| {}).unwrap();
    let scene = dens3r_scene::Scene::open(dir.path()).unwrap();
    let mut opts = SceneFusion::new(TsdfParams::new(0.02));
    opts.use_normals = true;
    let (a, sa) = fuse_scene(&scene, &opts, |_, _| {}).unwrap();
    let views: Vec<_> = cams.iter().map(|cam| world.render(cam)).collect();
    let frames = cams.iter().zip(&views).map(|(cam, v)| {
        Ok(FusionFrame {
            name: Cow::Borrowed("v"),
            camera: *cam,
            depth: Cow::Borrowed(&v.depth),
            mask: None,
            color: Some(Cow::Borrowed(&v.rgb)),
            conf: None,
            normals: Some(Cow::Borrowed(&v.normals)),
        })
    });
    let (b, sb) = fuse_frames("memory", frames, &opts, |_, _| {}).unwrap();
    assert_eq!((sa.frames, sa.blocks), (sb.frames, sb.blocks));
    assert!(sa.blocks > 50);
    let bits = |t: &SparseTsdf| {
        t.blocks()
            .flat_map(|(k, b)| {
                [k.x, k.y, k.z].map(|v| v as u32).into_iter().chain(b.tsdf.iter().chain(&b.weight).map(|v| v.to_bits()))
            })
            .collect::<Vec<_>>()
    };
    assert!(bits(&a) == bits(&b), "the grids differ");
}
