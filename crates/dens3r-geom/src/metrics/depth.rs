//! Depth metrics: AbsRel, RMSE and the delta < 1.25^k accuracies.

use super::MetricError;
use crate::pointmap::depth_valid;
use crate::raster::Raster;

/// How a prediction is aligned to the ground truth before scoring.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DepthAlign {
    /// Compare as is (metric predictions).
    None,
    /// Multiply by `median(gt) / median(pred)` (scale-ambiguous predictions).
    MedianScale,
    /// Least-squares scale and shift `s * pred + t` (affine-invariant predictions, MonoSDF).
    ScaleShift,
}

/// Depth errors over the pixels valid in both maps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthMetrics {
    /// mean |p - g| / g.
    pub abs_rel: f64,
    /// sqrt(mean (p - g)^2), in ground-truth units.
    pub rmse: f64,
    /// Fraction with max(p/g, g/p) < 1.25, 1.25^2, 1.25^3 (non-positive aligned values fail).
    pub delta: [f64; 3],
    /// Scale applied to the prediction.
    pub scale: f64,
    /// Shift applied to the prediction.
    pub shift: f64,
    /// Number of pixels scored.
    pub count: usize,
    /// The share of the ground truth's valid pixels (within the mask) that were scored: where
    /// the prediction is invalid (NaN, infinite, zero) a pixel is not, so a map valid on half
    /// of them scores 0.5 here whatever its errors.
    pub coverage: f64,
}

/// Scores `pred` against `gt`. A pixel counts when both are finite and > 0 and `mask`
/// (if given) is true.
pub fn depth_metrics(
    pred: &Raster<f32>,
    gt: &Raster<f32>,
    mask: Option<&Raster<bool>>,
    align: DepthAlign,
) -> Result<DepthMetrics, MetricError> {
    super::check_sizes(pred, gt, mask)?;
    let pairs: Vec<(f64, f64)> = (0..gt.data().len())
        .filter(|&i| mask.is_none_or(|m| m.data()[i]))
        .map(|i| (pred.data()[i], gt.data()[i]))
        .filter(|&(p, g)| depth_valid(p) && depth_valid(g))
        .map(|(p, g)| (p as f64, g as f64))
        .collect();
    if pairs.is_empty() {
        return Err(MetricError::NoValidPixels);
    }
    let gt_valid =
        (0..gt.data().len()).filter(|&i| mask.is_none_or(|m| m.data()[i]) && depth_valid(gt.data()[i])).count();
    let (scale, shift) = match align {
        DepthAlign::None => (1.0, 0.0),
        DepthAlign::MedianScale => {
            let mut p: Vec<f64> = pairs.iter().map(|x| x.0).collect();
            let mut g: Vec<f64> = pairs.iter().map(|x| x.1).collect();
            let (mp, mg) = (crate::focal::median(&mut p).unwrap(), crate::focal::median(&mut g).unwrap());
            (mg / mp, 0.0)
        }
        DepthAlign::ScaleShift => scale_shift(&pairs),
    };
    let n = pairs.len() as f64;
    let (mut abs_rel, mut sq, mut delta) = (0.0, 0.0, [0.0; 3]);
    for &(p, g) in &pairs {
        let p = scale * p + shift;
        abs_rel += (p - g).abs() / g;
        sq += (p - g) * (p - g);
        if p > 0.0 {
            let ratio = (p / g).max(g / p);
            for (k, d) in delta.iter_mut().enumerate() {
                if ratio < 1.25f64.powi(k as i32 + 1) {
                    *d += 1.0;
                }
            }
        }
    }
    Ok(DepthMetrics {
        abs_rel: abs_rel / n,
        rmse: (sq / n).sqrt(),
        delta: delta.map(|d| d / n),
        scale,
        shift,
        count: pairs.len(),
        coverage: pairs.len() as f64 / gt_valid.max(1) as f64,
    })
}

/// Closed-form least-squares `(s, t)` minimising `sum (s p + t - g)^2`. A singular system (every
/// `p` the same) has its minimum at any `s p + t = mean(g)`: `(0, mean(g))`.
pub fn scale_shift(pairs: &[(f64, f64)]) -> (f64, f64) {
    let (mut a00, mut a01, mut b0, mut b1) = (0.0, 0.0, 0.0, 0.0);
    for &(p, g) in pairs {
        a00 += p * p;
        a01 += p;
        b0 += p * g;
        b1 += g;
    }
    let a11 = pairs.len() as f64;
    let det = a00 * a11 - a01 * a01;
    if det.abs() <= 1e-12 * (a00 * a11).max(1e-300) {
        return (0.0, b1 / a11.max(1.0));
    }
    ((a11 * b0 - a01 * b1) / det, (-a01 * b0 + a00 * b1) / det)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn analytic_values() {
        let gt = Raster::from_fn(8, 4, |x, y| 1.0 + (x + 8 * y) as f32 * 0.1);
        // Identical maps: zero error, perfect accuracy.
        let m = depth_metrics(&gt, &gt, None, DepthAlign::None).unwrap();
        assert_eq!((m.abs_rel, m.rmse, m.delta, m.count), (0.0, 0.0, [1.0; 3], 32));
        // pred = 1.1 * gt: AbsRel 0.1, delta1 all pass (1.1 < 1.25); median scale undoes it.
        let pred = gt.map(|g| g * 1.1);
        let m = depth_metrics(&pred, &gt, None, DepthAlign::None).unwrap();
        assert!((m.abs_rel - 0.1).abs() < 1e-6 && m.delta[0] == 1.0);
        let m = depth_metrics(&pred, &gt, None, DepthAlign::MedianScale).unwrap();
        assert!(m.abs_rel < 1e-6 && (m.scale - 1.0 / 1.1).abs() < 1e-6);
        // Affine prediction: only scale+shift alignment recovers it.
        let pred = gt.map(|g| 0.5 * g - 0.2);
        let m = depth_metrics(&pred, &gt, None, DepthAlign::ScaleShift).unwrap();
        assert!(m.abs_rel < 1e-6 && (m.scale - 2.0).abs() < 1e-5 && (m.shift - 0.4).abs() < 1e-5);
        // pred = 2 * gt: ratio 2 exceeds 1.25^3 = 1.953, so every threshold fails.
        let m = depth_metrics(&gt.map(|g| g * 2.0), &gt, None, DepthAlign::None).unwrap();
        assert_eq!(m.delta, [0.0, 0.0, 0.0]);
        let m = depth_metrics(&gt.map(|g| g * 1.5), &gt, None, DepthAlign::None).unwrap();
        assert_eq!(m.delta, [0.0, 1.0, 1.0]);
    }

    #[test]
    fn a_constant_prediction_scales_and_shifts_to_the_mean() {
        // Every scale and shift of a constant is a constant; the least-squares one is the
        // ground truth's mean (3): AbsRel (2 + 0.5 + 0 + 0.5) / 4.
        let gt = Raster::from_vec(4, 1, vec![1.0f32, 2.0, 3.0, 6.0]).unwrap();
        let m = depth_metrics(&gt.map(|_| 5.0), &gt, None, DepthAlign::ScaleShift).unwrap();
        assert!((m.abs_rel - 0.75).abs() < 1e-12 && m.scale == 0.0 && (m.shift - 3.0).abs() < 1e-12, "{m:?}");
    }

    #[test]
    fn invalid_pixels_and_errors() {
        let gt = Raster::from_vec(2, 1, vec![0.0f32, 2.0]).unwrap();
        let pred = Raster::from_vec(2, 1, vec![5.0f32, 3.0]).unwrap();
        let m = depth_metrics(&pred, &gt, None, DepthAlign::None).unwrap();
        assert_eq!(m.count, 1);
        assert!((m.rmse - 1.0).abs() < 1e-12);
        let none = Raster::from_vec(2, 1, vec![f32::NAN, 0.0]).unwrap();
        assert_eq!(depth_metrics(&none, &gt, None, DepthAlign::None), Err(MetricError::NoValidPixels));
        let small = Raster::filled(1, 1, 1.0f32);
        assert!(matches!(depth_metrics(&small, &gt, None, DepthAlign::None), Err(MetricError::SizeMismatch(..))));
    }
}
