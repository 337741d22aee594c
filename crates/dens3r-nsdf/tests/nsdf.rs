//! Neural SDF: gradients against finite differences, the numerical normals against the field's
//! analytic gradient, a fit of a rendered sphere against the analytic surface, checkpoint
//! resumption and bad checkpoints.

use burn::tensor::{Device, Tensor, TensorData};
use dens3r_geom::Intrinsics;
use dens3r_nsdf::field::{self, encode, grid_backward, FieldConfig, Params};
use dens3r_nsdf::train::{tetra_matrix, tetra_points};
use dens3r_nsdf::{render, FitOptions, NsdfError, TrainOptions};
use dens3r_render::{Material, Object, Shape, Texture, World};
use glam::{DVec3, Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

fn tiny() -> FieldConfig {
    FieldConfig {
        levels: 3,
        features: 2,
        log2_table: 8,
        base_res: 4,
        max_res: 16,
        hidden: 8,
        layers: 2,
        color: true,
        init_radius: 0.5,
    }
}

/// Initial values with every entry perturbed, so the grid and all layers matter.
fn random_values(cfg: &FieldConfig, seed: u64) -> Vec<(Vec<f32>, [usize; 2])> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut v = field::init_values(cfg, seed);
    for (vals, _) in v.iter_mut() {
        for x in vals.iter_mut() {
            *x += rng.gen_range(-0.3..0.3);
        }
    }
    v
}

fn ad() -> Device {
    Device::autodiff(Device::flex())
}

/// A scalar built from the field the way training uses it: NeuS-rendered distance, opacity and
/// colour of a few rays, plus SDF values at free points.
struct Case {
    rays: usize,
    samples: usize,
    pts: Vec<Vec3>,
    t: Vec<f32>,
    extra: Vec<Vec3>,
    coef: Vec<f32>,
}

fn case() -> Case {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (rays, samples) = (5, 8);
    let mut pts = Vec::new();
    let mut t = Vec::new();
    for _ in 0..rays {
        let o = Vec3::new(rng.gen_range(-0.2..0.2), rng.gen_range(-0.2..0.2), -0.9);
        let d = Vec3::new(rng.gen_range(-0.3..0.3), rng.gen_range(-0.3..0.3), 1.0).normalize();
        for j in 0..samples {
            let tj = 0.3 + 0.15 * j as f32 + rng.gen_range(0.0..0.1);
            t.push(tj);
            pts.push(o + d * tj);
        }
    }
    let extra = (0..6)
        .map(|_| Vec3::new(rng.gen_range(-0.8..0.8), rng.gen_range(-0.8..0.8), rng.gen_range(-0.8..0.8)))
        .collect();
    let coef = (0..64).map(|_| rng.gen_range(-1.0..1.0)).collect();
    Case { rays, samples, pts, t, extra, coef }
}

/// The scalar and, on an autodiff device, its gradient (table first, as in the values).
fn loss(
    cfg: &FieldConfig,
    values: &[(Vec<f32>, [usize; 2])],
    c: &Case,
    device: &Device,
    grad: bool,
) -> (f64, Vec<Vec<f32>>) {
    let (table, params) = Params::from_values(values, device, grad);
    let mut all = c.pts.clone();
    all.extend_from_slice(&c.extra);
    let mask = vec![1.0; cfg.levels];
    let ev = params.forward(cfg, &table, encode(cfg, &all), &mask, grad);
    let n = c.rays * c.samples;
    let sdf = ev.out.clone().slice([0..n, 0..1]).reshape([c.rays, c.samples]);
    let t = Tensor::<2>::from_data(TensorData::new(c.t.clone(), [c.rays, c.samples]), device);
    let r = render::neus(sdf, t, params.sharpness().div_scalar(4.0));
    let rgb = burn::tensor::activation::sigmoid(ev.out.clone().slice([0..n, 1..4])).reshape([c.rays, c.samples, 3]);
    let col = render::weighted(&r.weights, &r.opacity, rgb);
    let k = |a: usize, len: usize, shape: [usize; 2]| {
        Tensor::<2>::from_data(TensorData::new(c.coef[a..a + len].to_vec(), shape), device)
    };
    let free = ev.out.clone().slice([n..n + c.extra.len(), 0..1]);
    let total = (r.distance * k(0, c.rays, [c.rays, 1])).sum()
        + (r.opacity * k(8, c.rays, [c.rays, 1])).sum()
        + (col * k(16, c.rays * 3, [c.rays, 3])).sum()
        + (free.square() * k(40, c.extra.len(), [c.extra.len(), 1])).sum();
    let value = field::to_vec(total.clone())[0] as f64;
    if !grad {
        return (value, Vec::new());
    }
    let grads = total.backward();
    let mut gt = vec![0f32; table.len()];
    let dfeat = field::to_vec(ev.features.grad(&grads).expect("feature gradient"));
    grid_backward(cfg, &ev.enc, &mask, &dfeat, &mut gt);
    let mut out = vec![gt];
    for p in &params.tensors {
        out.push(p.grad(&grads).map_or_else(|| vec![0.0; p.shape().num_elements()], field::to_vec));
    }
    (value, out)
}

#[test]
fn gradients_match_finite_differences() {
    let cfg = tiny();
    let values = random_values(&cfg, 11);
    let c = case();
    let (_, g) = loss(&cfg, &values, &c, &ad(), true);
    let plain = Device::flex();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (mut checked, mut worst) = (0, 0.0f64);
    for (ti, (vals, _)) in values.iter().enumerate() {
        // Entries with the largest gradients (the table is mostly untouched) plus random ones.
        let mut idx: Vec<usize> = (0..vals.len()).collect();
        idx.sort_by(|&a, &b| g[ti][b].abs().total_cmp(&g[ti][a].abs()));
        let mut pick: Vec<usize> = idx.into_iter().take(4).collect();
        pick.extend((0..3).map(|_| rng.gen_range(0..vals.len())));
        let scale = g[ti].iter().fold(0f32, |m, x| m.max(x.abs())) as f64;
        for i in pick {
            let eps = 2e-3f32;
            let mut vp = values.clone();
            vp[ti].0[i] += eps;
            let mut vm = values.clone();
            vm[ti].0[i] -= eps;
            let fd = (loss(&cfg, &vp, &c, &plain, false).0 - loss(&cfg, &vm, &c, &plain, false).0) / (2.0 * eps as f64);
            let a = g[ti][i] as f64;
            let err = (a - fd).abs() / (0.02 * a.abs() + 0.01 * scale + 1e-4);
            worst = worst.max(err);
            assert!(err <= 1.0, "tensor {ti} entry {i}: autodiff {a:.6}, finite difference {fd:.6}");
            checked += 1;
        }
    }
    eprintln!("{checked} gradient entries checked, worst error {worst:.3} of tolerance");
    assert!(g[0].iter().filter(|x| **x != 0.0).count() > 20, "the table gets a gradient");
}

/// The field's gradient in position, analytically: autodiff through the MLP, chained by hand
/// through the trilinear grid interpolation (an implementation independent of `encode`).
fn analytic_gradient(cfg: &FieldConfig, values: &[(Vec<f32>, [usize; 2])], p: Vec3) -> Vec3 {
    let (table, params) = Params::from_values(values, &ad(), false);
    let enc = encode(cfg, &[p]);
    let lf = cfg.levels * cfg.features;
    let feats = field::grid_features(cfg, &table, &enc, &vec![1.0; cfg.levels]);
    let device = ad();
    let pos = Tensor::<2>::from_data(TensorData::new(p.to_array().to_vec(), [1, 3]), &device).require_grad();
    let ft = Tensor::<2>::from_data(TensorData::new(feats, [1, lf]), &device).require_grad();
    let out = params.mlp(cfg, pos.clone(), ft.clone()).slice([0..1, 0..1]).sum();
    let grads = out.backward();
    let dpos = field::to_vec(pos.grad(&grads).unwrap());
    let dfeat = field::to_vec(ft.grad(&grads).unwrap());
    let mut g = Vec3::from_slice(&dpos);
    let u = (p + 1.0) * 0.5;
    for l in 0..cfg.levels {
        let res = cfg.level_res(l) as f32;
        let x = u * res;
        let f = x - x.floor();
        for k in 0..8 {
            let e = l * 8 + k;
            let (bx, by, bz) = ((k & 1) as f32, ((k >> 1) & 1) as f32, ((k >> 2) & 1) as f32);
            let w = |b: f32, t: f32| if b == 1.0 { t } else { 1.0 - t };
            let dw = |b: f32| if b == 1.0 { 1.0 } else { -1.0 };
            // d weight / d position: d/du = res * d/dx, d/dp = 0.5 d/du.
            let dweight = Vec3::new(
                dw(bx) * w(by, f.y) * w(bz, f.z),
                w(bx, f.x) * dw(by) * w(bz, f.z),
                w(bx, f.x) * w(by, f.y) * dw(bz),
            ) * res
                * 0.5;
            let row = enc.rows[e] as usize * cfg.features;
            for c in 0..cfg.features {
                g += dweight * table[row + c] * dfeat[l * cfg.features + c];
            }
        }
    }
    g
}

#[test]
fn numerical_normals_match_the_analytic_gradient() {
    let cfg = tiny();
    let values = random_values(&cfg, 3);
    let (table, params) = Params::from_values(&values, &Device::flex(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let h = 2e-4f32;
    let mut tested = 0;
    for _ in 0..40 {
        let p = Vec3::new(rng.gen_range(-0.9..0.9), rng.gen_range(-0.9..0.9), rng.gen_range(-0.9..0.9));
        // Trilinear interpolation is only continuous across cells: skip points whose four
        // offsets straddle a cell border on some level.
        let cell = |q: Vec3, l: usize| (((q + 1.0) * 0.5) * cfg.level_res(l) as f32).floor();
        let tp = tetra_points(&[p], h);
        if (0..cfg.levels).any(|l| tp.iter().any(|q| cell(*q, l) != cell(p, l))) {
            continue;
        }
        let out = params.forward(&cfg, &table, encode(&cfg, &tp), &vec![1.0; cfg.levels], false).out;
        let num = out.slice([0..4, 0..1]).reshape([1, 4]).matmul(tetra_matrix(h, &Device::flex()));
        let num = Vec3::from_slice(&field::to_vec(num));
        let ana = analytic_gradient(&cfg, &values, p);
        // A ReLU kink between the offsets would also break the comparison; none lies within
        // 2e-4 of these points.
        assert!((num - ana).length() <= 2e-2 * ana.length().max(0.1), "at {p}: numerical {num}, analytic {ana}");
        tested += 1;
    }
    assert!(tested >= 30, "only {tested} points tested");
}

fn sphere_scene(dir: &Path, noise: bool) -> (PathBuf, DVec3, f64) {
    let (c, r) = (Vec3::new(0.1, -0.2, 0.3), 0.5f32);
    let world = World::new(vec![Object {
        name: "ball".into(),
        shape: Shape::Sphere { radius: r },
        rotation: Quat::IDENTITY,
        translation: c,
        class_id: 1,
        material: Material { color: [0.6, 0.5, 0.4], texture: Texture::Noise { scale: 0.1 }, seed: 2 },
    }])
    .unwrap();
    let poses = dens3r_render::path::orbit(c.as_dvec3(), 1.6, 30.0, 20.0, 8);
    let k = Intrinsics::from_hfov(80, 60, 60.0);
    let out = dir.join("sphere");
    dens3r_render::render_to_scene(&world, k, (80, 60), &poses, &Default::default(), &out, |_| {}).unwrap();
    if noise {
        let n = dens3r_render::noise::Noise { depth_sigma: 0.005, normal_deg: 3.0, seed: 1 };
        dens3r_render::noise::add_noise(&out, &n).unwrap();
    }
    (out, c.as_dvec3(), r as f64)
}

/// The error of a run that must fail.
fn fit_error(data: &dens3r_nsdf::TrainData, opts: &FitOptions) -> String {
    dens3r_nsdf::fit(data, opts, None, dens3r_nsdf::cpu_device(), |_| {}).unwrap_err().to_string()
}

fn small_opts(iters: usize) -> FitOptions {
    FitOptions {
        field: FieldConfig { levels: 8, log2_table: 15, max_res: 128, hidden: 32, ..FieldConfig::default() },
        train: TrainOptions { iters, rays: 512, samples: 24, eikonal_points: 256, ..TrainOptions::default() },
        voxel: Some(0.02),
        ..FitOptions::default()
    }
}

#[test]
fn fits_a_sphere_and_resumes_where_it_stopped() {
    let dir = tempfile::tempdir().unwrap();
    let (scene_dir, c, r) = sphere_scene(dir.path(), true);
    let scene = dens3r_scene::Scene::open(&scene_dir).unwrap();
    let data = dens3r_nsdf::load_scene(&scene).unwrap();
    let iters = 240;
    let opts = small_opts(iters);
    let (mesh, summary) = dens3r_nsdf::fit(&data, &opts, None, dens3r_nsdf::cpu_device(), |_| {}).unwrap();
    let err: Vec<f64> = mesh.positions.iter().map(|p| ((p.as_dvec3() - c).length() - r).abs()).collect();
    let mean = err.iter().sum::<f64>() / err.len() as f64;
    let mut sorted = err.clone();
    sorted.sort_by(f64::total_cmp);
    let p95 = sorted[sorted.len() * 95 / 100];
    eprintln!(
        "sphere r {r}: {} vertices, mean |d| {mean:.5}, p95 {p95:.5}, last loss {:?}, {:.1}s",
        mesh.positions.len(),
        summary.last,
        summary.train_seconds
    );
    assert!(mesh.positions.len() > 500);
    assert!(mean < 0.01 * r, "mean distance to the sphere {mean}");
    assert!(p95 < 0.03 * r, "95th percentile distance {p95}");

    // Interrupted after 100 iterations (the checkpoint is every 50), then resumed.
    let ck = dir.path().join("ck");
    let stop =
        FitOptions { checkpoint_dir: Some(ck.clone()), checkpoint_every: 50, stop_after: Some(100), ..opts.clone() };
    match dens3r_nsdf::fit(&data, &stop, None, dens3r_nsdf::cpu_device(), |_| {}) {
        Err(NsdfError::Stopped(100)) => {}
        other => panic!("expected a stop at 100, got {:?}", other.map(|(_, s)| s.last)),
    }
    let mut resumed_at = None;
    let go = FitOptions { stop_after: None, ..stop };
    let (mesh2, s2) = dens3r_nsdf::fit(&data, &go, None, dens3r_nsdf::cpu_device(), |p| {
        if let dens3r_nsdf::Progress::Resumed(i) = p {
            resumed_at = Some(i);
        }
    })
    .unwrap();
    assert_eq!(resumed_at, Some(100));
    assert_eq!(s2.start_iter, 100);
    // Every step is seeded by its iteration, so the resumed run repeats the uninterrupted one.
    assert!(
        (s2.last.total - summary.last.total).abs() <= 1e-4 * summary.last.total.abs().max(1.0),
        "{:?} vs {:?}",
        s2.last,
        summary.last
    );
    assert_eq!(mesh2.indices.len(), mesh.indices.len());
    let d = mesh2.positions.iter().zip(&mesh.positions).map(|(a, b)| (*a - *b).length()).fold(0f32, f32::max);
    assert!(d < 1e-3, "resumed mesh differs by {d}");

    // A checkpoint written with other options is refused.
    let other = FitOptions { train: TrainOptions { lr: 5e-3, ..go.train.clone() }, ..go.clone() };
    let e = fit_error(&data, &other);
    assert!(e.contains("other training options") && e.contains("nsdf.safetensors"), "{e}");
    let other = FitOptions { field: FieldConfig { hidden: 16, ..go.field.clone() }, ..go.clone() };
    let e = fit_error(&data, &other);
    assert!(e.contains("another field configuration") && e.contains("nsdf.safetensors"), "{e}");
}

#[test]
fn damaged_checkpoints_are_refused_with_their_path() {
    let dir = tempfile::tempdir().unwrap();
    let (scene_dir, _, _) = sphere_scene(dir.path(), false);
    let data = dens3r_nsdf::load_scene(&dens3r_scene::Scene::open(&scene_dir).unwrap()).unwrap();
    let ck = dir.path().join("ck");
    let opts =
        FitOptions { checkpoint_dir: Some(ck.clone()), checkpoint_every: 2, stop_after: Some(2), ..small_opts(4) };
    assert!(matches!(
        dens3r_nsdf::fit(&data, &opts, None, dens3r_nsdf::cpu_device(), |_| {}),
        Err(NsdfError::Stopped(2))
    ));
    let path = ck.join("nsdf.safetensors");
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let go = FitOptions { stop_after: None, ..opts.clone() };
    let e = fit_error(&data, &go);
    assert!(e.contains("nsdf.safetensors") && e.contains("truncated"), "{e}");
    std::fs::write(ck.join("nsdf.json"), b"{not json").unwrap();
    let e = fit_error(&data, &go);
    assert!(e.contains("nsdf.json") && e.contains("not a dens3r-nsdf checkpoint"), "{e}");
}

#[test]
fn a_scene_without_depth_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (scene_dir, _, _) = sphere_scene(dir.path(), false);
    std::fs::remove_dir_all(scene_dir.join("depth")).unwrap();
    let e = dens3r_nsdf::load_scene(&dens3r_scene::Scene::open(&scene_dir).unwrap()).unwrap_err().to_string();
    assert!(e.contains("no depth") && e.contains("dens3r predict"), "{e}");
}

#[test]
fn a_tsdf_start_puts_the_surface_in_place_before_rendering() {
    let dir = tempfile::tempdir().unwrap();
    let (scene_dir, c, r) = sphere_scene(dir.path(), false);
    let scene = dens3r_scene::Scene::open(&scene_dir).unwrap();
    let data = dens3r_nsdf::load_scene(&scene).unwrap();
    let tsdf = dens3r_nsdf::warm_start_tsdf(&scene, &data).unwrap();
    assert_eq!(tsdf.params().voxel, data.default_voxel());
    let (pts, vals) = dens3r_nsdf::tsdf_targets(&tsdf, &data.bounds).unwrap();
    // Projective distances overstate the true ones away from head-on views, but their sign
    // (in front of / behind the surface) is right, but for voxels near the silhouettes that are
    // finer than a pixel's footprint there (the warm start's voxel is 2 mm here: 97.1% right
    // beyond 5 mm, every wrong one within 6.1 voxels of the surface, measured).
    let voxel = tsdf.params().voxel as f64;
    let (mut agree, mut total, mut wrong_far) = (0, 0, Vec::new());
    for (p, v) in pts.iter().zip(&vals) {
        let d = (data.bounds.to_world(*p) - c).length() - r;
        if d.abs() > 0.005 && (d > 0.0) != (*v > 0.0) {
            wrong_far.push(d.abs() / voxel);
        }
        if d.abs() > 0.005 {
            total += 1;
            agree += usize::from((d > 0.0) == (*v > 0.0));
        }
    }
    wrong_far.sort_by(f64::total_cmp);
    eprintln!(
        "voxel {voxel}: {agree} of {total} TSDF signs right; wrong ones at {:?} voxels (median, max)",
        (wrong_far.get(wrong_far.len() / 2), wrong_far.last())
    );
    assert!(total > 10_000 && agree as f64 > 0.95 * total as f64, "{agree} of {total} TSDF signs right");
    assert!(wrong_far.last().is_none_or(|&v| v < 8.0), "a wrong sign far from the surface");
    // One rendering iteration after 150 TSDF iterations: the surface is already on the sphere.
    let mut opts = small_opts(1);
    opts.train.init_tsdf_iters = 150;
    let mut init_losses = Vec::new();
    let (mesh, _) = dens3r_nsdf::fit(&data, &opts, Some(&tsdf), dens3r_nsdf::cpu_device(), |p| {
        if let dens3r_nsdf::Progress::InitTsdf(_, l) = p {
            init_losses.push(l);
        }
    })
    .unwrap();
    assert_eq!(init_losses.len(), 150);
    let mean = mesh.positions.iter().map(|p| ((p.as_dvec3() - c).length() - r).abs()).sum::<f64>()
        / mesh.positions.len() as f64;
    eprintln!("TSDF start: L1 {} -> {}, mesh mean |d| {mean:.4}", init_losses[0], init_losses[149]);
    assert!(init_losses[149] < 0.2 * init_losses[0]);
    assert!(mesh.positions.len() > 500 && mean < 0.02, "mean distance {mean} after the TSDF start");
    // Without a TSDF the start is refused, not skipped.
    let e = fit_error(&data, &opts);
    assert!(e.contains("TSDF"), "{e}");
}

/// A frame whose normals file holds only NaN counts as without normals and is named (its
/// normals were dropped silently while the run said "normals on"; issue 22 defect 8).
#[test]
fn nan_normals_are_named_not_dropped_silently() {
    let dir = tempfile::tempdir().unwrap();
    let (scene_dir, _, _) = sphere_scene(dir.path(), false);
    let data = dens3r_nsdf::load_scene(&dens3r_scene::Scene::open(&scene_dir).unwrap()).unwrap();
    assert!(data.has_normals && data.unusable_normals.is_empty());
    let path = scene_dir.join("normals/0003.npy");
    let (shape, v) = dens3r_scene::npy::read_f32(&path).unwrap();
    dens3r_scene::npy::write_f32(&path, &shape, &vec![f32::NAN; v.len()]).unwrap();
    let data = dens3r_nsdf::load_scene(&dens3r_scene::Scene::open(&scene_dir).unwrap()).unwrap();
    assert!(!data.has_normals);
    assert_eq!(data.unusable_normals, vec!["0003".to_string()]);
}
