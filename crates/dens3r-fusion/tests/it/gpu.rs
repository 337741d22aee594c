//! The GPU (wgpu/WGSL) integration gives the CPU path's TSDF. Runs on any adapter wgpu finds,
//! a software one included (Debian's mesa-vulkan-drivers: lavapipe); with no adapter it says
//! SKIPPED, and fails instead when `DENS3R_REQUIRE_GPU=1` (as `.ci/run` sets).
#![cfg(feature = "gpu")]

use dens3r_fusion::{extract_mesh, ExtractOptions, FrameInput, FusionError, GpuTsdf, SparseTsdf, TsdfParams};
use dens3r_geom::{Intrinsics, PinholeCamera};
use dens3r_render::material::{Material, Texture};
use dens3r_render::path::orbit;
use dens3r_render::{Object, Shape, World};
use glam::{Quat, Vec3};

fn gpu_or_skip(params: TsdfParams) -> Option<GpuTsdf> {
    match GpuTsdf::new(params) {
        Ok(g) => {
            eprintln!("GPU adapter: {}", g.adapter());
            Some(g)
        }
        Err(e @ FusionError::Gpu(_)) => {
            assert!(std::env::var("DENS3R_REQUIRE_GPU").as_deref() != Ok("1"), "DENS3R_REQUIRE_GPU=1 but {e}");
            eprintln!("SKIPPED: {e}");
            None
        }
        Err(e) => panic!("{e}"),
    }
}

/// Integrates the same orbit of renders of a textured sphere (with a hole of NaN depth in
/// every frame) into both volumes.
fn fuse_both(params: TsdfParams, weights: bool) -> Option<(SparseTsdf, SparseTsdf)> {
    let mut gpu = gpu_or_skip(params.clone())?;
    let (c, r) = (Vec3::new(0.013, -0.021, 0.007), 0.3f32);
    let mat = Material { color: [0.2, 0.6, 0.9], texture: Texture::Checker { size: 0.1 }, seed: 3 };
    let world = World::new(vec![Object {
        name: "sphere".into(),
        shape: Shape::Sphere { radius: r },
        rotation: Quat::IDENTITY,
        translation: c,
        class_id: 1,
        material: mat,
    }])
    .unwrap();
    let (w, h) = (160, 120);
    let k = Intrinsics::from_hfov(w, h, 60.0);
    let mut cpu = SparseTsdf::new(params).unwrap();
    for el in [35.0, -35.0] {
        for pose in orbit(c.as_dvec3(), 1.2, el, 0.0, 8) {
            let cam = PinholeCamera { intrinsics: k, width: w, height: h, cam_to_world: pose };
            let mut view = world.render(&cam);
            for y in 50..60 {
                for x in 70..90 {
                    *view.depth.get_mut(x, y) = f32::NAN;
                }
            }
            let aw = weights.then(|| dens3r_fusion::tsdf::angle_weights(&view.normals, &cam));
            let f =
                FrameInput { name: "v", camera: &cam, depth: &view.depth, color: Some(&view.rgb), weight: aw.as_ref() };
            cpu.integrate(&f).unwrap();
            gpu.integrate(&f).unwrap();
        }
    }
    Some((cpu, gpu.finish().unwrap()))
}

/// Compares two volumes voxel by voxel: same blocks, and the share of observed voxels whose
/// distance, weight or colour differ beyond float tolerance.
fn compare(cpu: &SparseTsdf, gpu: &SparseTsdf) -> (usize, f64, f32) {
    assert_eq!(cpu.block_count(), gpu.block_count());
    assert_eq!(cpu.frame_count(), gpu.frame_count());
    let (mut observed, mut off, mut max_diff) = (0usize, 0usize, 0f32);
    for (key, a) in cpu.blocks() {
        let b = gpu.block(key).expect("the GPU grid has every CPU block");
        for i in 0..a.tsdf.len() {
            observed += (a.weight[i] > 0.0) as usize;
            max_diff = max_diff.max((a.tsdf[i] - b.tsdf[i]).abs());
            let tol = 1e-4 * (1.0 + a.weight[i].abs());
            let mut bad = (a.tsdf[i] - b.tsdf[i]).abs() > 1e-4 || (a.weight[i] - b.weight[i]).abs() > tol;
            if !a.color.is_empty() {
                bad |= (0..3).any(|c| (a.color[i][c] - b.color[i][c]).abs() > 0.05);
            }
            off += bad as usize;
        }
    }
    (observed, off as f64 / observed.max(1) as f64, max_diff)
}

#[test]
fn gpu_tsdf_equals_cpu_tsdf() {
    // 5 mm voxels: the pool grows past its first allocation (1024 blocks) mid-run.
    for (color, weights) in [(true, true), (false, false)] {
        let mut params = TsdfParams::new(0.005);
        params.color = color;
        let Some((cpu, gpu)) = fuse_both(params, weights) else { return };
        assert!(cpu.block_count() > 1024, "{} blocks", cpu.block_count());
        let (observed, off, max_diff) = compare(&cpu, &gpu);
        eprintln!(
            "colour {color}, weights {weights}: {} blocks, {observed} observed voxels, {:.5}% differ, max |tsdf diff| {max_diff:e}",
            cpu.block_count(),
            100.0 * off
        );
        assert!(observed > 100_000);
        // A voxel whose projection lies within rounding of a pixel border may pick the
        // neighbouring pixel on one side; nothing else may differ.
        assert!(off < 1e-3, "{:.4}% of voxels differ", 100.0 * off);
        // And the meshes agree.
        let (ma, mb) = (
            extract_mesh(cpu.grid(), &ExtractOptions::default()),
            extract_mesh(gpu.grid(), &ExtractOptions::default()),
        );
        let (na, nb) = (ma.indices.len() as f64, mb.indices.len() as f64);
        assert!((na - nb).abs() / na < 1e-3, "{na} vs {nb} triangles");
    }
}

#[test]
fn gpu_budget_is_checked_before_allocating() {
    let mut params = TsdfParams::new(0.005);
    params.budget_bytes = Some(200 * params.block_bytes());
    let Some(mut gpu) = gpu_or_skip(params) else { return };
    let world = World::new(vec![Object {
        name: "ball".into(),
        shape: Shape::Sphere { radius: 0.3 },
        rotation: Quat::IDENTITY,
        translation: Vec3::ZERO,
        class_id: 1,
        material: Material { color: [0.5; 3], texture: Texture::Plain, seed: 1 },
    }])
    .unwrap();
    let cam = PinholeCamera {
        intrinsics: Intrinsics::from_hfov(160, 120, 60.0),
        width: 160,
        height: 120,
        cam_to_world: orbit(glam::DVec3::ZERO, 1.2, 20.0, 0.0, 1)[0],
    };
    let view = world.render(&cam);
    let f = FrameInput { name: "v", camera: &cam, depth: &view.depth, color: Some(&view.rgb), weight: None };
    let err = gpu.integrate(&f).unwrap_err();
    assert!(matches!(err, FusionError::Budget { .. }), "{err}");
    assert_eq!(gpu.grid().block_count(), 0);
}
