//! Losses on burn tensors (differentiable on an autodiff device): cross-entropy with an ignore
//! index and class weights, scale-invariant log depth (SILog, Eigen et al.), and the
//! affine-invariant depth loss (per-image median and mean-absolute-deviation normalisation,
//! MiDaS).

use burn::tensor::activation::log_softmax;
use burn::tensor::{Device, Tensor, TensorData};
use dens3r_geom::pointmap::depth_valid;

/// Label value that is ignored (VOC's border colour).
pub const IGNORE: u16 = 255;

/// Mean cross-entropy of logits `(B, K, H, W)` against labels (`B*H*W` row-major ids;
/// [`IGNORE`] and ids >= K are skipped), each pixel weighted by its class weight when given
/// (normalised by the sum of the weights, as PyTorch's `CrossEntropyLoss(weight=...)`).
/// Returns `None` when no pixel counts.
pub fn cross_entropy(logits: Tensor<4>, labels: &[u16], class_weights: Option<&[f32]>) -> Option<Tensor<1>> {
    let [b, k, h, w] = logits.dims();
    let device = logits.device();
    let mut target = vec![0f32; b * k * h * w];
    let mut total = 0.0f64;
    for bi in 0..b {
        for px in 0..h * w {
            let l = labels[bi * h * w + px] as usize;
            if l >= k {
                continue;
            }
            let wt = class_weights.map_or(1.0, |cw| cw[l]);
            target[(bi * k + l) * h * w + px] = wt;
            total += wt as f64;
        }
    }
    if total <= 0.0 {
        return None;
    }
    let t = Tensor::<4>::from_data(TensorData::new(target, [b, k, h, w]), &device);
    let lp = log_softmax(logits, 1);
    Some((lp * t).sum().neg().div_scalar(total as f32))
}

/// Mask and log of valid ground-truth depths (finite, > 0).
fn depth_targets(gt: &[f32], shape: [usize; 4], device: &Device) -> Option<(Tensor<4>, Tensor<4>, f32)> {
    let mask: Vec<f32> = gt.iter().map(|&d| depth_valid(d) as u8 as f32).collect();
    let n: f32 = mask.iter().sum();
    if n < 2.0 {
        return None;
    }
    let log_gt: Vec<f32> = gt.iter().map(|&d| if depth_valid(d) { d.ln() } else { 0.0 }).collect();
    Some((
        Tensor::from_data(TensorData::new(mask, shape), device),
        Tensor::from_data(TensorData::new(log_gt, shape), device),
        n,
    ))
}

/// SILog: `sqrt(mean(g^2) - lambda mean(g)^2)` with `g = log_pred - log_gt` over valid pixels
/// (ground truth finite and > 0), `lambda = 0.85`. `log_pred` is `(B, 1, H, W)`.
pub fn silog(log_pred: Tensor<4>, gt: &[f32]) -> Option<Tensor<1>> {
    let shape = log_pred.dims();
    let (mask, log_gt, n) = depth_targets(gt, shape, &log_pred.device())?;
    let g = (log_pred - log_gt) * mask;
    let m1 = g.clone().sum().div_scalar(n);
    let m2 = g.square().sum().div_scalar(n);
    Some((m2 - m1.square().mul_scalar(0.85)).clamp_min(1e-12).sqrt())
}

/// Index of the (lower) median of `v` over `valid`.
fn median_index(v: &[f32], valid: &[usize]) -> usize {
    let mut order: Vec<usize> = valid.to_vec();
    order.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
    order[(order.len() - 1) / 2]
}

/// Affine-invariant depth loss (MiDaS's scale-and-shift-invariant loss, Ranftl et al. 2020):
/// per image, the prediction `exp(log_pred)` and the ground truth are each shifted by their
/// median and divided by their mean absolute deviation from it over valid pixels; the loss is
/// the mean absolute difference. The normalisation keeps the sign of the scale, so an inverted
/// prediction is penalised (a least-squares fit would flip it for free). The gradient flows
/// through the median element, as with `torch.median`.
pub fn affine_invariant(log_pred: Tensor<4>, gt: &[f32]) -> Option<Tensor<1>> {
    let [b, _, h, w] = log_pred.dims();
    let n = h * w;
    let device = log_pred.device();
    let pred = log_pred.exp().reshape([b, n]);
    let host = crate::features::to_vec(pred.clone());
    let mut losses = Vec::new();
    for bi in 0..b {
        let g = &gt[bi * n..(bi + 1) * n];
        let valid: Vec<usize> = (0..n).filter(|&i| depth_valid(g[i])).collect();
        if valid.len() < 2 {
            continue;
        }
        let gm = g[median_index(g, &valid)];
        let gmad = valid.iter().map(|&i| (g[i] - gm).abs()).sum::<f32>() / valid.len() as f32;
        // The prediction's median and MAD are taken on the tensor, so gradients flow.
        let k = median_index(&host[bi * n..(bi + 1) * n], &valid);
        let mut mask = vec![0f32; n];
        let mut g_hat = vec![0f32; n];
        for &i in &valid {
            mask[i] = 1.0;
            g_hat[i] = (g[i] - gm) / gmad.max(1e-12);
        }
        let mask = Tensor::<2>::from_data(TensorData::new(mask, [1, n]), &device);
        let g_hat = Tensor::<2>::from_data(TensorData::new(g_hat, [1, n]), &device);
        let p = pred.clone().slice([bi..bi + 1, 0..n]);
        let med = p.clone().slice([0..1, k..k + 1]);
        let centred = (p - med) * mask.clone();
        let mad = centred.clone().abs().sum().div_scalar(valid.len() as f32).clamp_min(1e-12);
        let p_hat = centred / mad.reshape([1, 1]);
        losses.push(((p_hat - g_hat) * mask).abs().sum().div_scalar(valid.len() as f32));
    }
    if losses.is_empty() {
        return None;
    }
    let k = losses.len() as f32;
    Some(Tensor::cat(losses, 0).sum().div_scalar(k))
}
