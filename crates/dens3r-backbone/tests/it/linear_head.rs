//! DUSt3R's linear point head (`downstream_headK.proj`): fixture A's encoder and decoder with
//! linear heads in place of its DPT heads. The reference is written here from the official
//! `LinearPts3d` (project the last decoder layer, `pixel_shuffle` by the patch size, then the
//! 'exp' depth and confidence modes) and applied to the decoder output the PyTorch code dumped.

use dens3r_backbone::config::{PtsDecoder, RopeScaling};
use dens3r_backbone::verify::heads_from_config;
use dens3r_backbone::{Dens3r, Device, ModelConfig, Tensor, TensorData, Weights};
use rand::{Rng, SeedableRng};

use crate::fixtures::{parity, A};

/// PyTorch's `pixel_shuffle` of one `(C r^2, h, w)` map, by its documented index rule:
/// `out[c, y r + i, x r + j] = in[c r^2 + i r + j, y, x]`.
fn pixel_shuffle_reference(v: &[f32], c: usize, r: usize, h: usize, w: usize) -> Vec<f32> {
    let mut out = vec![0.0; c * h * r * w * r];
    for ch in 0..c {
        for y in 0..h {
            for x in 0..w {
                for i in 0..r {
                    for j in 0..r {
                        let src = ((ch * r * r + i * r + j) * h + y) * w + x;
                        out[(ch * h * r + y * r + i) * w * r + x * r + j] = v[src];
                    }
                }
            }
        }
    }
    out
}

#[test]
fn dust3r_linear_head_matches_the_official_formula_on_the_dumped_decoder() {
    let dir = parity(A);
    let w = dens3r_io::tensors::TensorFile::open(&dir.join("weights.safetensors"), "the parity fixture").unwrap();
    let keep: Vec<(String, Vec<usize>, Vec<f32>)> = w
        .names()
        .into_iter()
        .filter(|n| !n.starts_with("ptsmatch_") && !n.starts_with("normal_local_head"))
        .map(|n| {
            let (s, v) = w.get(&n).unwrap();
            (n, s, v)
        })
        .collect();
    let dec_dim = keep.iter().find(|(n, ..)| n == "decoder_embed.weight").unwrap().1[0];
    let (p, out_ch) = (16usize, 4usize);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut heads = Vec::new();
    for k in 1..=2 {
        let wt: Vec<f32> = (0..out_ch * p * p * dec_dim).map(|_| rng.gen_range(-0.05..0.05)).collect();
        let b: Vec<f32> = (0..out_ch * p * p).map(|_| rng.gen_range(-0.1..0.1)).collect();
        heads.push((format!("downstream_head{k}.proj.weight"), vec![out_ch * p * p, dec_dim], wt));
        heads.push((format!("downstream_head{k}.proj.bias"), vec![out_ch * p * p], b));
    }
    let all: Vec<_> = keep.iter().chain(&heads).map(|(n, s, v)| (n.clone(), s.clone(), v.as_slice())).collect();
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("linear.safetensors");
    dens3r_io::tensors::save(&file, &all).unwrap();

    let device = Device::flex();
    let w = Weights::from_safetensors(&file).unwrap();
    let mut config = ModelConfig::from_weights(&w, heads_from_config(&dir.join("config.json")).unwrap()).unwrap();
    assert_eq!(config.head1.decoder, PtsDecoder::Linear { out_channels: 4 });
    assert!(config.has_conf && config.normal_head.is_none() && config.desc_dim == 0);
    // DUSt3R's keys give upstream RoPE; the fixture's decoder was dumped with Dens3R's.
    assert_eq!(config.rope, RopeScaling::Plain);
    config.rope = RopeScaling::Interpolated;
    let (model, unexpected) = Dens3r::load(&w, config, &device).unwrap();
    assert!(unexpected.is_empty(), "{unexpected:?}");

    let img = |n: &str| {
        let (s, v) = dens3r_scene::npy::read_f32(&dir.join(n)).unwrap();
        Tensor::<4>::from_data(TensorData::new(v, [s[0], s[1], s[2], s[3]]), &device)
    };
    let pred = model.forward(img("img1.npy"), img("img2.npy"));
    for (view, k) in [(0usize, 1usize), (1, 2)] {
        // The official decoder's last layer (after dec_norm), (1, N, D).
        let (ds, dec) = dens3r_scene::npy::read_f32(&dir.join(format!("dec{k}_layers.npy"))).unwrap();
        let n = ds[2];
        let last = &dec[(ds[0] - 1) * n * dec_dim..ds[0] * n * dec_dim];
        let (wt, b) = (&heads[2 * (k - 1)].2, &heads[2 * (k - 1) + 1].2);
        let v = &pred.views[view];
        let [_, hh, ww, _] = v.pts3d.dims();
        let (h, w) = (hh / p, ww / p);
        assert_eq!(h * w, n);
        // proj, then (B, S, D) -> (B, D, h, w) as the official transpose + view does.
        let mut chw = vec![0.0f32; out_ch * p * p * n];
        for t in 0..n {
            for o in 0..out_ch * p * p {
                let dot: f32 = (0..dec_dim).map(|i| wt[o * dec_dim + i] * last[t * dec_dim + i]).sum();
                chw[o * n + t] = dot + b[o];
            }
        }
        let raw = pixel_shuffle_reference(&chw, out_ch, p, h, w);
        let plane = hh * ww;
        let pts = v.pts3d.clone().into_data().try_to_vec::<f32>().unwrap();
        let conf = v.conf.clone().unwrap().into_data().try_to_vec::<f32>().unwrap();
        let (mut err_p, mut err_c) = (0.0f32, 0.0f32);
        for px in 0..plane {
            let xyz = [raw[px], raw[plane + px], raw[2 * plane + px]];
            let d = xyz.iter().map(|a| a * a).sum::<f32>().sqrt();
            for (c, a) in xyz.iter().enumerate() {
                let want = a / d.max(1e-8) * d.exp_m1();
                err_p = err_p.max((pts[px * 3 + c] - want).abs() / want.abs().max(1e-3));
            }
            let want = 1.0 + raw[3 * plane + px].exp();
            err_c = err_c.max((conf[px] - want).abs() / want);
        }
        assert!(err_p < 1e-3 && err_c < 1e-3, "view {k}: pointmap rel err {err_p:.2e}, confidence {err_c:.2e}");
    }
}
