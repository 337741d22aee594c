//! NeuS volume rendering along rays from SDF samples (the discrete form of Wang et al. 2021,
//! eq. 13): `alpha_i = max((Phi_s(f_i) - Phi_s(f_{i+1})) / Phi_s(f_i), 0)` with `Phi_s` the
//! logistic sigmoid of sharpness `s`, transmittance the product of `1 - alpha` before a section,
//! and section weights `w_i = T_i alpha_i`.

use burn::tensor::activation::sigmoid;
use burn::tensor::Tensor;

/// What the renderer gives per ray.
pub struct Rendered {
    /// Section weights `(rays, samples - 1)`.
    pub weights: Tensor<2>,
    /// Sum of weights (opacity), `(rays, 1)`.
    pub opacity: Tensor<2>,
    /// Weighted mean distance, normalised by the opacity, `(rays, 1)`.
    pub distance: Tensor<2>,
}

/// Renders rays from SDF values `sdf (rays, samples)` at distances `t (rays, samples)` with
/// sharpness `s (1, 1)`.
pub fn neus(sdf: Tensor<2>, t: Tensor<2>, s: Tensor<2>) -> Rendered {
    let [r, n] = sdf.dims();
    let cdf = sigmoid(sdf * s);
    let prev = cdf.clone().slice([0..r, 0..n - 1]);
    let next = cdf.slice([0..r, 1..n]);
    let alpha = ((prev.clone() - next) / (prev + 1e-5)).clamp(0.0, 1.0);
    let log_keep = (alpha.clone().neg() + (1.0 + 1e-7)).log();
    // Exclusive cumulative sum: transmittance before each section.
    let trans = (log_keep.clone().cumsum(1) - log_keep).exp();
    let weights = trans * alpha;
    let mid = (t.clone().slice([0..r, 0..n - 1]) + t.slice([0..r, 1..n])) * 0.5;
    let opacity = weights.clone().sum_dim(1);
    let distance = (weights.clone() * mid).sum_dim(1) / (opacity.clone() + 1e-5);
    Rendered { weights, opacity, distance }
}

/// Weighted mean of per-sample values `v (rays, samples, c)` with section weights, each section
/// taking the mean of its two ends: `(rays, c)`, normalised by the opacity.
pub fn weighted(weights: &Tensor<2>, opacity: &Tensor<2>, v: Tensor<3>) -> Tensor<2> {
    let [r, n, c] = v.dims();
    let mid = (v.clone().slice([0..r, 0..n - 1, 0..c]) + v.slice([0..r, 1..n, 0..c])) * 0.5;
    let w = weights.clone().reshape([r, n - 1, 1]);
    (mid * w).sum_dim(1).reshape([r, c]) / (opacity.clone() + 1e-5)
}
