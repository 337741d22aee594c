//! `predict_mono` / `predict_pair` on the fixture model: the self-pair is the pair of an image
//! with itself, and each view's maps come back in that view's own orientation.

use dens3r_backbone::predict::{predict_mono, predict_pair, Resolution};
use dens3r_backbone::preprocess::preprocess;
use dens3r_backbone::verify::load_model;
use dens3r_backbone::HeadOutputs;
use std::path::PathBuf;

use crate::fixtures::{parity, shared_parity, A};

#[test]
fn pair_and_mono_agree_and_keep_orientations() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let a = parity(A);
    let device = dens3r_backbone::device::cpu();
    let (model, _) = load_model(&a.join("weights.safetensors"), Some(&a.join("config.json")), &device).unwrap();
    let img = image::open(root.join("../../data-samples/room/images/0000.png")).unwrap();
    let land = preprocess(&img, 64, true).unwrap();
    let port = preprocess(&img.rotate90(), 64, true).unwrap();
    assert!(port.info.rotated && !land.info.rotated);

    // predict_pair (encoder outputs reused across pairs) equals the plain forward pass.
    let direct = model.forward(land.tensor(&device), port.tensor(&device));
    let [p1, _] = predict_pair(&model, &land, &port, Resolution::Network);
    let raw: Vec<f32> = direct.views[0].pts3d.to_data().try_to_vec::<f32>().unwrap();
    let got: Vec<f32> = p1.points.data().iter().flat_map(|p| p.to_array()).collect();
    assert_eq!(raw, got, "same numbers as model.forward");

    let mono = predict_mono(&model, &land, Resolution::Network, HeadOutputs::ALL);
    let [v1, v2] = predict_pair(&model, &land, &land, Resolution::Network);
    let worst = mono.points.data().iter().zip(v1.points.data()).map(|(a, b)| (*a - *b).length()).fold(0.0, f32::max);
    assert!(worst < 1e-6, "the self-pair's first view is predict_mono ({worst})");
    assert_eq!((v1.frame, v2.frame), (0, 0));
    // Without the descriptor head (what `dens3r predict` asks for), the rest is unchanged.
    let lean = predict_mono(&model, &land, Resolution::Network, HeadOutputs { normal: true, desc: false });
    assert!(mono.desc.is_some() && lean.desc.is_none() && lean.desc_conf.is_none());
    assert_eq!(lean.points.data(), mono.points.data());
    assert_eq!(lean.conf.as_ref().unwrap().data(), mono.conf.as_ref().unwrap().data());
    assert_eq!(lean.normals.as_ref().unwrap().data(), mono.normals.as_ref().unwrap().data());

    // A portrait second view: its maps are portrait-shaped; the first view's are not.
    let [w1, w2] = predict_pair(&model, &land, &port, Resolution::Network);
    assert_eq!((w1.points.width(), w1.points.height()), (64, 48));
    assert_eq!((w2.points.width(), w2.points.height()), (48, 64));
    assert_eq!((w2.normals.as_ref().unwrap().width(), w2.conf.as_ref().unwrap().height()), (48, 64));
    // Network inputs of a portrait image and of its landscape twin are the same pixels, so
    // the two pairs see identical inputs: the rotated-back second view is the first pair's
    // second view rotated clockwise (pixel (x, y) of the portrait map = (y, 47 - x)).
    assert_eq!(port.rgb.as_raw(), land.rgb.as_raw());
    for y in 0..64 {
        for x in 0..48 {
            assert_eq!(w2.depth.get(x, y), v2.depth.get(y, 47 - x), "({x},{y})");
        }
    }
    // Descriptors follow the same pixel grid (not rotated as vectors: they are not spatial),
    // are unit length, and come with a confidence map.
    let (d2, e2) = (w2.desc.as_ref().unwrap(), v2.desc.as_ref().unwrap());
    assert_eq!((d2.width, d2.height, d2.dim, e2.width, e2.height), (48, 64, 24, 64, 48));
    for y in 0..64 {
        for x in 0..48 {
            let (a, b) = ((y * 48 + x) * 24, ((47 - x) * 64 + y) * 24);
            assert_eq!(d2.data[a..a + 24], e2.data[b..b + 24], "desc ({x},{y})");
            let n: f32 = d2.data[a..a + 24].iter().map(|v| v * v).sum();
            assert!((n - 1.0).abs() < 1e-4, "unit descriptors: {n}");
        }
    }
    let dc = w2.desc_conf.as_ref().unwrap();
    assert_eq!((dc.width(), dc.height()), (48, 64));
    // At the original size the maps have the photo's size in each orientation.
    let [o1, o2] = predict_pair(&model, &land, &port, Resolution::Original);
    assert_eq!((o1.depth.width(), o1.depth.height(), o2.depth.width(), o2.depth.height()), (160, 120, 120, 160));
}

/// `forward_mono` skips the second encoder pass (and, with a shared decoder, the second
/// decoder path and view 2's heads): it must still equal view 1 of `forward(x, x)`, for a
/// shared decoder (fixture A) and for two decoders (fixture B).
#[test]
fn forward_mono_equals_the_self_pair() {
    let device = dens3r_backbone::device::cpu();
    let b = "B_two_dec_descconf_48x64_64x48";
    let cases = [(A, Some(parity(A))), (b, shared_parity(b, "forward_mono with two decoders (fixture B)"))];
    for (case, a) in cases.into_iter().filter_map(|(c, p)| Some((c, p?))) {
        let (model, _) = load_model(&a.join("weights.safetensors"), Some(&a.join("config.json")), &device).unwrap();
        let (shape, img) = dens3r_scene::npy::read_f32(&a.join("img1.npy")).unwrap();
        let shape: [usize; 4] = shape.try_into().unwrap();
        let x = dens3r_backbone::Tensor::<4>::from_data(dens3r_backbone::TensorData::new(img, shape), &device);
        let mono = model.forward_mono(x.clone());
        let pair = model.forward(x.clone(), x);
        let vals = |t: &dens3r_backbone::Tensor<4>| t.to_data().try_to_vec::<f32>().unwrap();
        let pairs =
            [(vals(&mono.pts3d), vals(&pair.views[0].pts3d)), (vals(&mono.raw_pts), vals(&pair.views[0].raw_pts))];
        for (m, p) in pairs {
            assert_eq!(m.len(), p.len());
            let err = m.iter().zip(&p).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(err < 1e-6, "{case}: {err}");
        }
        let (mn, pn) = (mono.normal.as_ref().map(vals), pair.views[0].normal.as_ref().map(vals));
        assert_eq!(mn.is_some(), pn.is_some());
        if let (Some(m), Some(p)) = (mn, pn) {
            assert!(m.iter().zip(&p).all(|(a, b)| (a - b).abs() < 1e-6), "{case}: normals");
        }
    }
}
