//! The DPT head on the CPU kernels (its full-resolution tail in bands of rows) against burn's
//! own convolution and interpolation on the same weights.

use burn::tensor::{Device, Tensor, TensorData};
use dens3r_backbone::config::DptConfig;
use dens3r_backbone::model::Dpt;

/// Seeded values in `[-scale, scale]`.
fn values(n: usize, seed: u64, scale: f32) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
        })
        .collect()
}

/// A grid of 9 x 3 tokens gives a 144 x 48 output: the CPU tail runs it as bands of 64, 64 and
/// 16 rows, each with a row of the upsampled map above and below. A misplaced or missing
/// neighbour row changes whole rows of the output; the reference (burn's ops, on the autodiff
/// device, where the CPU kernels never serve) does not band.
#[test]
fn banded_tail_equals_burns_dpt() {
    let c = DptConfig {
        prefix: "t".into(),
        layer_dims: [8, 16, 24, 32],
        feature_dim: 16,
        head_dim: 8,
        last_dim: 12,
        out_channels: 4,
        up: [4, 2],
    };
    let (dim, h, w) = (20, 9, 3);
    let in_dims = [dim; 4];
    // Weights scaled by 1 / sqrt(fan-in) so activations stay of order 1 through the layers.
    let params: Vec<(String, Vec<f32>)> = Dpt::parameter_layout(&c, in_dims)
        .into_iter()
        .enumerate()
        .map(|(k, (name, shape))| {
            let n: usize = shape.iter().product();
            let scale = if shape.len() > 1 { 1.0 / ((n / shape[0]) as f32).sqrt() } else { 0.1 };
            (name, values(n, k as u64 + 1, scale * 3f32.sqrt()))
        })
        .collect();
    let maps: Vec<Vec<f32>> = (0..4).map(|i| values(dim * h * w, 100 + i, 1.0)).collect();
    let run = |device: &Device| -> Vec<f32> {
        let dpt = Dpt::from_flat(&c, in_dims, &|name: &str| {
            let v = &params.iter().find(|(n, _)| n == name).unwrap_or_else(|| panic!("{name} not in the layout")).1;
            Tensor::<1>::from_data(TensorData::new(v.clone(), [v.len()]), device)
        });
        let layers =
            std::array::from_fn(|i| Tensor::<4>::from_data(TensorData::new(maps[i].clone(), [1, dim, h, w]), device));
        let out = dpt.forward_maps(layers);
        assert_eq!(out.dims(), [1, 4, 16 * h, 16 * w]);
        out.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
    };
    let ours = run(&Device::flex());
    let reference = run(&Device::autodiff(Device::flex()));
    let scale = reference.iter().fold(0f32, |m, v| m.max(v.abs()));
    let worst = ours.iter().zip(&reference).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(scale > 1e-2, "a degenerate reference (largest |value| {scale})");
    assert!(worst <= 1e-5 * scale.max(1.0), "largest difference {worst} (reference's largest |value| {scale})");
}
