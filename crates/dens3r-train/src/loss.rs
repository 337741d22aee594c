//! Dens3R's training losses (model spec section 5) on burn tensors, differentiable on an
//! autodiff device. Shapes follow the network's outputs: pointmaps and normals `(B, H, W, 3)`,
//! confidences and masks `(B, H, W)`, descriptors `(B, H, W, D)`. Masks are 0 / 1 floats.

use burn::tensor::{Int, Tensor, TensorData};

/// `sum(x * mask) / max(n, 1)` with `n` the mask's count, or `count` when given: the mean
/// over valid pixels (0 with none), or a shard's share of the mean over a whole batch whose
/// valid pixels number `count`.
fn masked_mean(x: Tensor<3>, mask: Tensor<3>, count: Option<f32>) -> Tensor<1> {
    let sum = (x * mask.clone()).sum();
    match count {
        Some(n) => sum.div_scalar(n.max(1.0)),
        None => sum / mask.sum().clamp_min(1.0),
    }
}

/// Euclidean norm over the last axis: `(B, H, W, 3) -> (B, H, W)`. Computed as
/// `sqrt(max(|p|^2, 1e-24))`: at a zero vector the gradient is zero (as PyTorch's norm),
/// not NaN.
fn norm3(p: Tensor<4>) -> Tensor<3> {
    let [b, h, w, _] = p.dims();
    p.square().sum_dim(3).clamp_min(1e-24).sqrt().reshape([b, h, w])
}

/// DUSt3R's 'avg_dis' normalisation of a view pair: both pointmaps divided by the mean
/// Euclidean norm over the valid pixels of **both** views (invalid points count as zero and are
/// left out of the count; `sum / (count + 1e-8)`, clamped at 1e-8), per sample.
pub fn normalize_avg_dis(p1: Tensor<4>, p2: Tensor<4>, v1: Tensor<3>, v2: Tensor<3>) -> (Tensor<4>, Tensor<4>) {
    let b = p1.dims()[0];
    let sum = |p: Tensor<4>, v: Tensor<3>| (norm3(p) * v).reshape([b as i32, -1]).sum_dim(1);
    let count = |v: Tensor<3>| v.reshape([b as i32, -1]).sum_dim(1);
    let total = sum(p1.clone(), v1.clone()) + sum(p2.clone(), v2.clone());
    let factor = (total / (count(v1) + count(v2)).add_scalar(1e-8)).clamp_min(1e-8).reshape([b, 1, 1, 1]);
    (p1 / factor.clone(), p2 / factor)
}

/// One view of a confidence-weighted regression: `mean_valid(l * c - alpha * ln c)`.
fn conf_weighted(l: Tensor<3>, conf: Tensor<3>, valid: Tensor<3>, count: Option<f32>, alpha: f32) -> Tensor<1> {
    let term = l * conf.clone() - conf.log().mul_scalar(alpha);
    masked_mean(term, valid, count)
}

/// A view's prediction and ground truth for the 3-D regression.
pub struct RegrView {
    /// Predicted points `(B, H, W, 3)`.
    pub pred: Tensor<4>,
    /// Predicted confidence `(B, H, W)` (`1 + exp`, so > 1).
    pub conf: Tensor<3>,
    /// Ground-truth points `(B, H, W, 3)` in the frame the prediction is in.
    pub gt: Tensor<4>,
    /// Valid ground truth `(B, H, W)`.
    pub valid: Tensor<3>,
    /// The valid pixels of the whole batch when these tensors are a shard of it (the mean's
    /// denominator); `None`: `valid`'s own count.
    pub count: Option<f32>,
}

/// `ConfLoss(Regr3D(L21, norm_mode='avg_dis'), alpha)` over a view pair: prediction and ground
/// truth each normalised by their own 'avg_dis' factor over both views' valid pixels, the
/// per-pixel Euclidean distance weighted by confidence with the `-alpha ln c` term, averaged
/// over each view's valid pixels and summed over the two views. Which frame the points are in
/// (view 2 in view 1's camera, or each view in its own) is the caller's choice of `gt`.
pub fn conf_regr3d(v1: RegrView, v2: RegrView, alpha: f32) -> Tensor<1> {
    let (p1, p2) = normalize_avg_dis(v1.pred, v2.pred, v1.valid.clone(), v2.valid.clone());
    let (g1, g2) = normalize_avg_dis(v1.gt, v2.gt, v1.valid.clone(), v2.valid.clone());
    let l1 = norm3(p1 - g1);
    let l2 = norm3(p2 - g2);
    conf_weighted(l1, v1.conf, v1.valid, v1.count, alpha) + conf_weighted(l2, v2.conf, v2.valid, v2.count, alpha)
}

/// A scale-and-shift-invariant depth loss (MiDaS-style), per sample: the predicted depth
/// `(B, H, W)` fitted to the ground truth by least squares (`s z + t`) over the valid pixels,
/// the mean absolute residual divided by the ground truth's mean absolute deviation plus 5% of
/// its mean; averaged over the batch (over `samples` when the tensors are a shard of a batch of
/// that many). A constant prediction scores about 1 whatever the scene's
/// depth range, so a shallow scene (a tote seen from above) weighs as much as a deep room,
/// where the pointmap regression, normalised by the mean distance, barely sees its relief.
pub fn ssi_depth_l1(pred: Tensor<3>, gt: Tensor<3>, valid: Tensor<3>, samples: Option<usize>) -> Tensor<1> {
    let b = pred.dims()[0];
    let flat = |t: Tensor<3>| t.reshape([b as i32, -1]);
    let (p, g, v) = (flat(pred), flat(gt), flat(valid));
    let n = v.clone().sum_dim(1).clamp_min(1.0);
    let mean = |x: Tensor<2>| (x * v.clone()).sum_dim(1) / n.clone();
    let (mp, mg) = (mean(p.clone()), mean(g.clone()));
    let (dp, dg) = (p - mp, g - mg.clone());
    let var = mean(dp.clone().square());
    let cov = mean(dp.clone() * dg.clone());
    let s = cov / var.add_scalar(1e-12);
    let r = (dp * s - dg.clone()).abs();
    let spread = mean(dg.abs()) + mg.mul_scalar(0.05);
    let per = mean(r) / spread.clamp_min(1e-12);
    per.sum().div_scalar(samples.unwrap_or(b).max(1) as f32)
}

/// Dens3R's `pcd2normal` on a pointmap `(B, H, W, 3)`: on interior pixels
/// `a = P[i, j+1] - P[i, j-1]`, `b = P[i-1, j] - P[i+1, j]`, `n = a x b` with `n_y` negated,
/// divided by `max(|n|, 1e-12)`; a one-pixel zero border. Dens3R raw normal convention.
pub fn pointmap_normals(p: Tensor<4>) -> Tensor<4> {
    let [b, h, w, _] = p.dims();
    let (ih, iw) = (h - 2, w - 2);
    let a = p.clone().slice([0..b, 1..h - 1, 2..w, 0..3]) - p.clone().slice([0..b, 1..h - 1, 0..w - 2, 0..3]);
    let bv = p.clone().slice([0..b, 0..h - 2, 1..w - 1, 0..3]) - p.slice([0..b, 2..h, 1..w - 1, 0..3]);
    let c = |t: &Tensor<4>, i: usize| t.clone().narrow(3, i, 1);
    let (ax, ay, az) = (c(&a, 0), c(&a, 1), c(&a, 2));
    let (bx, by, bz) = (c(&bv, 0), c(&bv, 1), c(&bv, 2));
    let nx = ay.clone() * bz.clone() - az.clone() * by.clone();
    let ny = (az * bx.clone() - ax.clone() * bz).neg();
    let nz = ax * by - ay * bx;
    let n = Tensor::cat(vec![nx, ny, nz], 3);
    // max(|n|, 1e-12), with a zero gradient at a zero cross product (flat, ReLU-dead output).
    let len = n.clone().square().sum_dim(3).clamp_min(1e-24).sqrt();
    let n = n / len;
    debug_assert_eq!(n.dims(), [b, ih, iw, 3]);
    // Zero border: pad columns, then rows.
    let device = n.device();
    let zc = Tensor::<4>::zeros([b, ih, 1, 3], &device);
    let n = Tensor::cat(vec![zc.clone(), n, zc], 2);
    let zr = Tensor::<4>::zeros([b, 1, w, 3], &device);
    Tensor::cat(vec![zr.clone(), n, zr], 1)
}

/// `ABSNormalLoss` of one view: the mean over valid pixels (`valid` and `|n_gt|_1 > 0`) of
/// `sum_xyz |n_pred - n_gt|`; `count`: the whole batch's such pixels when the tensors are a
/// shard of it (`None`: their own).
pub fn normal_l1(pred: Tensor<4>, gt: Tensor<4>, valid: Tensor<3>, count: Option<f32>) -> Tensor<1> {
    let [b, h, w, _] = pred.dims();
    let has = gt.clone().abs().sum_dim(3).reshape([b, h, w]).greater_elem(0.0).float();
    let l = (pred - gt).abs().sum_dim(3).reshape([b, h, w]);
    masked_mean(l, valid * has, count)
}

/// `ABSNormalFromDepthLoss` over a view pair: [`pointmap_normals`] of each predicted pointmap
/// (both in view 1's frame) against `normalmap` (view 1) and `normalmap_transformed` (view 2's
/// normals rotated into view 1's frame), raw convention, by [`normal_l1`]; summed.
pub fn pointmap_normal_loss(
    pts: [Tensor<4>; 2],
    gt: [Tensor<4>; 2],
    valid: [Tensor<3>; 2],
    counts: [Option<f32>; 2],
) -> Tensor<1> {
    let [p1, p2] = pts;
    let [g1, g2] = gt;
    let [v1, v2] = valid;
    let [c1, c2] = counts;
    normal_l1(pointmap_normals(p1), g1, v1, c1) + normal_l1(pointmap_normals(p2), g2, v2, c2)
}

/// Ground-truth correspondences of one sample: flat pixel indices (`y * W + x`) in view 1 and
/// view 2, matched one to one.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Matches {
    /// Pixels of view 1.
    pub idx1: Vec<u32>,
    /// Their matches in view 2.
    pub idx2: Vec<u32>,
}

/// Gathers `(H*W, C)` rows of `x` (one sample, flattened) at `idx`.
fn gather(x: Tensor<2>, idx: &[u32]) -> Tensor<2> {
    let device = x.device();
    let ids: Vec<i64> = idx.iter().map(|&i| i as i64).collect();
    let ids = Tensor::<1, Int>::from_data(TensorData::new(ids, [idx.len()]), &device);
    x.select(0, ids)
}

/// MASt3R's matching loss (`ConfMatchingLoss(MatchingLoss(InfoNCE(mode='proper',
/// temperature)), alpha, confmode='mean')`): per sample, descriptors gathered at the
/// correspondences give `S = d1 d2^T / tau`; each match `i` costs
/// `-[ln(e_ii / sum_k e_ki) + ln(e_ii / sum_k e_ik)]` with each ratio clamped at 1e-8, over
/// blocks of at most `block` correspondences; weighted by `c = (c1 + c2) / 2` of the
/// descriptor confidences at the matched pixels with the `-alpha ln c` term, and averaged over
/// every match of the batch (over `total` matches when the tensors are a shard of a batch
/// with that many). `None` when no sample has a match.
pub fn matching_loss(
    desc: [Tensor<4>; 2],
    desc_conf: [Tensor<3>; 2],
    matches: &[Matches],
    temperature: f32,
    alpha: f32,
    block: usize,
    total: Option<usize>,
) -> Option<Tensor<1>> {
    let [d1, d2] = desc;
    let [c1, c2] = desc_conf;
    let [b, h, w, d] = d1.dims();
    let mut terms = Vec::new();
    let mut count = 0usize;
    let floor = (1e-8f32).ln();
    for (s, m) in matches.iter().enumerate().take(b) {
        if m.idx1.is_empty() {
            continue;
        }
        let flat_d = |t: &Tensor<4>| t.clone().narrow(0, s, 1).reshape([h * w, d]);
        let flat_c = |t: &Tensor<3>| t.clone().narrow(0, s, 1).reshape([h * w, 1]);
        for (i1, i2) in m.idx1.chunks(block).zip(m.idx2.chunks(block)) {
            let n = i1.len();
            let (a, bb) = (gather(flat_d(&d1), i1), gather(flat_d(&d2), i2));
            let diag = (a.clone() * bb.clone()).sum_dim(1).div_scalar(temperature); // (n, 1)
            let sim = a.matmul(bb.transpose()).div_scalar(temperature); // (n, n)
                                                                        // ln(e_ii / sum_k e_ik) (rows) and ln(e_ii / sum_k e_ki) (columns).
            let lse_row = log_sum_exp(sim.clone(), 1);
            let lse_col = log_sum_exp(sim, 0).transpose();
            let l = (diag.clone() - lse_row).clamp_min(floor) + (diag - lse_col).clamp_min(floor);
            let l = l.neg(); // (n, 1)
            let c = (gather(flat_c(&c1), i1) + gather(flat_c(&c2), i2)).div_scalar(2.0);
            terms.push((l * c.clone() - c.log().mul_scalar(alpha)).sum());
            count += n;
        }
    }
    if count == 0 {
        return None;
    }
    let sum = terms.into_iter().reduce(|a, b| a + b)?;
    Some(sum.div_scalar(total.unwrap_or(count).max(1) as f32))
}

/// `ln sum exp` along `dim` of a matrix, kept as a size-1 axis (max-shifted).
fn log_sum_exp(x: Tensor<2>, dim: usize) -> Tensor<2> {
    let m = x.clone().max_dim(dim).detach();
    (x - m.clone()).exp().sum_dim(dim).log() + m
}
