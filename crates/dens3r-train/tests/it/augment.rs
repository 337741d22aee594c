//! The camera degradations and grey of training images, against closed forms.

use dens3r_train::augment::{gaussian_blur, to_grey, Degradation};
use dens3r_train::{Dataset, TrainConfig};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A blurred impulse keeps its mass and spreads with the Gaussian's variance, sigma^2, along
/// each axis (from 1 px on, where the kernel sampled at whole pixels and cut at 3 sigma keeps it
/// within 1%).
#[test]
fn blur_spreads_an_impulse_by_sigma_squared() {
    let (w, h) = (41, 31);
    for sigma in [1.0f32, 1.7, 2.5] {
        let mut plane = vec![0.0f32; w * h];
        plane[15 * w + 20] = 1.0;
        gaussian_blur(&mut plane, (w, h), sigma);
        let mass: f32 = plane.iter().sum();
        assert!((mass - 1.0).abs() < 1e-5, "sigma {sigma}: mass {mass}");
        let var_x: f32 = plane.iter().enumerate().map(|(i, v)| v * ((i % w) as f32 - 20.0).powi(2)).sum();
        let var_y: f32 = plane.iter().enumerate().map(|(i, v)| v * ((i / w) as f32 - 15.0).powi(2)).sum();
        let want = sigma * sigma;
        for got in [var_x, var_y] {
            assert!((got - want).abs() < 0.02 * want, "sigma {sigma}: variance {got}, want {want}");
        }
    }
}

/// With no degradation an image comes back unchanged; vignetting, gains and the tone curve
/// give `(0.5 gain (1 - v r^2))^gamma` on a uniform grey; noise has the drawn deviation.
#[test]
fn degradations_match_their_closed_forms() {
    let (w, h) = (64, 48);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let img: Vec<f32> = (0..3 * w * h).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let mut same = img.clone();
    Degradation::NONE.apply(&mut same, (w, h), &mut rng);
    let worst = img.iter().zip(&same).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(worst < 1e-5, "no degradation changed the image by {worst}");

    let d = Degradation { vignette: 0.3, gains: [0.9, 1.0, 1.1], gamma: 1.5, ..Degradation::NONE };
    let mut grey = vec![0.0f32; 3 * w * h];
    d.apply(&mut grey, (w, h), &mut rng);
    let n = w * h;
    for c in 0..3 {
        let centre = 0.5 * d.gains[c];
        // The centre (between four pixels: r^2 = 0.5 px^2 of the corner's 39.3^2) and a corner.
        let at_centre = (grey[c * n + (h / 2) * w + w / 2] + 1.0) / 2.0;
        let at_corner = (grey[c * n] + 1.0) / 2.0;
        let r2 = (0.5f32 * 0.5 + 0.5 * 0.5) / (31.5f32 * 31.5 + 23.5 * 23.5);
        assert!((at_centre - (centre * (1.0 - 0.3 * r2)).powf(1.5)).abs() < 1e-5, "channel {c} centre {at_centre}");
        assert!((at_corner - (centre * 0.7).powf(1.5)).abs() < 1e-5, "channel {c} corner {at_corner}");
    }

    let d = Degradation { noise: 0.02, ..Degradation::NONE };
    let mut noisy = vec![0.0f32; 3 * w * h];
    d.apply(&mut noisy, (w, h), &mut rng);
    // Residuals in [0, 1] intensities (the image is stored as 2x - 1).
    let res: Vec<f32> = noisy.iter().map(|v| v / 2.0).collect();
    let mean = res.iter().sum::<f32>() / res.len() as f32;
    let sd = (res.iter().map(|r| (r - mean).powi(2)).sum::<f32>() / res.len() as f32).sqrt();
    assert!(mean.abs() < 1e-3 && (sd - 0.02).abs() < 0.001, "noise mean {mean}, deviation {sd}");
}

/// `degrade = 1` changes every view's pixels, within [-1, 1], and leaves every pair of a
/// batch, its ground truth and its correspondences as drawn without it; out of [0, 1] it is
/// refused.
#[test]
fn degrade_changes_the_images_only() {
    let orbit = crate::fixtures::repo_root().join("data-samples/orbit");
    let device = dens3r_backbone::Device::flex();
    let base = TrainConfig { size: (64, 48), batch: 2, n_corres: 64, ..Default::default() };
    let degraded = TrainConfig { degrade: 1.0, ..base.clone() };
    let data = Dataset::load(&[orbit], (64, 48), (0.1, 0.98)).unwrap();
    let vals = |t: dens3r_backbone::Tensor<4>| t.into_data().try_to_vec::<f32>().unwrap();
    for step in 0..3 {
        let (a, b) = (data.batch(&base, 16, step, &device).unwrap(), data.batch(&degraded, 16, step, &device).unwrap());
        for k in 0..2 {
            let (x, y) = (vals(a.images[k].clone()), vals(b.images[k].clone()));
            let moved = x.iter().zip(&y).filter(|(p, q)| (*p - *q).abs() > 1e-3).count();
            assert!(moved * 2 > x.len(), "step {step} view {k}: {moved} of {} pixels changed", x.len());
            assert!(y.iter().all(|v| (-1.0..=1.0).contains(v)), "step {step} view {k} out of range");
        }
        for (ta, tb) in a.targets.iter().zip(&b.targets) {
            assert_eq!(ta.pts, tb.pts, "step {step}: same ground truth");
            assert_eq!(ta.matches.idx1, tb.matches.idx1, "step {step}: same correspondences");
        }
    }
    for p in [-0.1, 1.5, f32::NAN] {
        assert!(TrainConfig { degrade: p, ..base.clone() }.check(16).is_err(), "{p}");
    }
}

/// Grey is BT.601 luma in every channel (red 0.299, green 0.587, blue 0.114 of the way up from
/// black, in the normalised [-1, 1] range too, since the weights sum to 1).
#[test]
fn grey_is_bt601_luma() {
    // Three pixels, planes R, G, B: pure red, pure green, pure blue (normalised: 1 on, -1 off).
    let mut img = vec![1.0, -1.0, -1.0, -1.0, 1.0, -1.0, -1.0, -1.0, 1.0];
    to_grey(&mut img);
    for (px, w) in [0.299f32, 0.587, 0.114].into_iter().enumerate() {
        let want = 2.0 * w - 1.0;
        for c in 0..3 {
            assert!((img[c * 3 + px] - want).abs() < 1e-6, "pixel {px} channel {c}: {}", img[c * 3 + px]);
        }
    }
}

/// `grey = 1` makes both views of every pair grey and leaves the pairs, their ground truth and
/// correspondences as drawn without it; `grey = 0.5` greys some pairs and not others, both views
/// together; out of [0, 1] it is refused.
#[test]
fn grey_pairs_change_the_images_only() {
    let orbit = crate::fixtures::repo_root().join("data-samples/orbit");
    let device = dens3r_backbone::Device::flex();
    let base = TrainConfig { size: (64, 48), batch: 2, n_corres: 64, ..Default::default() };
    let data = Dataset::load(&[orbit], (64, 48), (0.1, 0.98)).unwrap();
    let vals = |t: dens3r_backbone::Tensor<4>| t.into_data().try_to_vec::<f32>().unwrap();
    // Per pair and view: whether its three planes are equal.
    let grey_views = |x: &[f32], b: usize| -> Vec<bool> {
        let n = x.len() / b / 3;
        (0..b)
            .map(|i| (0..n).all(|p| (0..3).all(|c| (x[(i * 3 + c) * n + p] - x[i * 3 * n + p]).abs() < 1e-6)))
            .collect()
    };
    let (mut some, mut none) = (false, false);
    for step in 0..8 {
        let a = data.batch(&base, 16, step, &device).unwrap();
        let all = data.batch(&TrainConfig { grey: 1.0, ..base.clone() }, 16, step, &device).unwrap();
        let half = data.batch(&TrainConfig { grey: 0.5, ..base.clone() }, 16, step, &device).unwrap();
        for k in 0..2 {
            let x = vals(a.images[k].clone());
            assert!(grey_views(&x, 2).iter().all(|g| !g), "step {step}: the renders are in colour");
            let y = vals(all.images[k].clone());
            assert!(grey_views(&y, 2).iter().all(|g| *g), "step {step} view {k}");
            // The same jittered view, turned grey.
            let mut want = x.clone();
            want.chunks_mut(x.len() / 2).for_each(to_grey);
            assert!(want.iter().zip(&y).all(|(p, q)| (p - q).abs() < 1e-6), "step {step} view {k}");
        }
        let (h1, h2) = (grey_views(&vals(half.images[0].clone()), 2), grey_views(&vals(half.images[1].clone()), 2));
        assert_eq!(h1, h2, "step {step}: both views of a pair or neither");
        some |= h1.iter().any(|g| *g);
        none |= h1.iter().any(|g| !*g);
        for (ta, tb) in a.targets.iter().zip(&all.targets) {
            assert_eq!(ta.pts, tb.pts, "step {step}: same ground truth");
            assert_eq!(ta.matches.idx1, tb.matches.idx1, "step {step}: same correspondences");
        }
    }
    assert!(some && none, "grey 0.5 greys some pairs and not others");
    for p in [-0.1, 1.5, f32::NAN] {
        assert!(TrainConfig { grey: p, ..base.clone() }.check(16).is_err(), "{p}");
    }
}
