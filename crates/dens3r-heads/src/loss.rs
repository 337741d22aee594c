//! Losses on burn tensors (differentiable on an autodiff device): cross-entropy with an ignore
//! index and class weights, scale-invariant log depth (SILog, Eigen et al.), and the
//! affine-invariant depth loss (per-image least-squares scale and shift, MiDaS).

use burn::tensor::activation::log_softmax;
use burn::tensor::{Device, Tensor, TensorData};

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
    let mask: Vec<f32> = gt.iter().map(|&d| (d.is_finite() && d > 0.0) as u8 as f32).collect();
    let n: f32 = mask.iter().sum();
    if n < 2.0 {
        return None;
    }
    let log_gt: Vec<f32> = gt.iter().map(|&d| if d.is_finite() && d > 0.0 { d.ln() } else { 0.0 }).collect();
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

/// Affine-invariant depth loss: per image, the prediction `exp(log_pred)` is aligned to the
/// ground truth by the least-squares scale and shift over valid pixels, then the mean absolute
/// residual is divided by the mean ground truth.
pub fn affine_invariant(log_pred: Tensor<4>, gt: &[f32]) -> Option<Tensor<1>> {
    let [b, _, h, w] = log_pred.dims();
    let device = log_pred.device();
    let pred = log_pred.exp();
    let mut losses = Vec::new();
    for bi in 0..b {
        let g = &gt[bi * h * w..(bi + 1) * h * w];
        let Some((mask, _, n)) = depth_targets(g, [1, 1, h, w], &device) else { continue };
        let gt_t = Tensor::<4>::from_data(
            TensorData::new(
                g.iter().map(|&d| if d.is_finite() && d > 0.0 { d } else { 0.0 }).collect::<Vec<_>>(),
                [1, 1, h, w],
            ),
            &device,
        );
        let p = pred.clone().slice([bi..bi + 1, 0..1, 0..h, 0..w]) * mask.clone();
        // Normal equations of min sum (s p + t - g)^2 over the mask.
        let (sp, sg) = (p.clone().sum(), gt_t.clone().sum());
        let (spp, spg) = (p.clone().square().sum(), (p.clone() * gt_t.clone()).sum());
        let det = spp.clone().mul_scalar(n) - sp.clone().square();
        let det = det.clamp_min(1e-12);
        let s = (spg.clone().mul_scalar(n) - sp.clone() * sg.clone()) / det.clone();
        let t = (spp * sg.clone() - sp * spg) / det;
        let r = ((p * s.reshape([1, 1, 1, 1]) + t.reshape([1, 1, 1, 1])) * mask.clone() - gt_t).abs() * mask;
        losses.push(r.sum() / sg);
    }
    if losses.is_empty() {
        return None;
    }
    let k = losses.len() as f32;
    Some(Tensor::cat(losses, 0).sum().div_scalar(k))
}
