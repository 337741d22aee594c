//! Scores against ground-truth disparity whose calibration is unknown.
//!
//! A rectified pair's disparity is `d = f B / z - d0`: an affine map of inverse depth whose
//! focal length, baseline and offset `d0` a stereo dataset does not always give (OpenCV's copy
//! of Middlebury's Aloe pair ships the disparity alone). A predicted depth is therefore scored
//! in disparity, as affine-invariant depth is (MiDaS): its inverse depth aligned to `d` by
//! least-squares scale and shift, which absorbs `f B` and `d0` whatever they are. Beside it,
//! two image-blind predictors fitted the same way to `d` itself: the best constant (a
//! fronto-parallel plane) and the best affine function of the pixel (any 3-D plane, since a
//! plane's inverse depth is affine in the pixel).
//!
//! `rel_rmse` divides the RMSE by the disparity's standard deviation, so it reads as the share
//! of the scene's inverse-depth variation left unexplained: the constant scores exactly 1.

use super::baselines::fit_affine;
use super::depth::scale_shift;
use super::MetricError;
use crate::pointmap::depth_valid;
use crate::raster::Raster;

/// Errors of one predictor against the disparity, after its least-squares fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DisparityMetrics {
    /// RMSE divided by the disparity's standard deviation (1 = the best constant).
    pub rel_rmse: f64,
    /// sqrt(mean (p - d)^2), in the disparity file's units (pixels).
    pub rmse: f64,
    /// mean |p - d|, in the disparity file's units.
    pub mae: f64,
    /// Number of pixels scored.
    pub count: usize,
}

/// A prediction's score beside the two image-blind fits, over the same pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DisparityScores {
    /// The predicted depth's inverse, scaled and shifted.
    pub prediction: DisparityMetrics,
    /// Scale and shift applied to the predicted inverse depth.
    pub scale: f64,
    /// See `scale`.
    pub shift: f64,
    /// The mean disparity everywhere.
    pub constant: DisparityMetrics,
    /// The least-squares affine function of the pixel.
    pub plane: DisparityMetrics,
}

/// A scored pixel: its position, the predicted inverse depth and the disparity.
struct Px {
    x: usize,
    y: usize,
    q: f64,
    d: f64,
}

/// Scores predicted depth `pred` against disparity `gt`. A pixel counts when the depth is
/// finite and > 0, the disparity finite and > 0 (0 marks unknown in Middlebury's files) and
/// `mask` (if given) is true.
pub fn disparity_scores(
    pred: &Raster<f32>,
    gt: &Raster<f32>,
    mask: Option<&Raster<bool>>,
) -> Result<DisparityScores, MetricError> {
    super::check_sizes(pred, gt, mask)?;
    let w = gt.width();
    let px: Vec<Px> = (0..gt.data().len())
        .filter(|&i| mask.is_none_or(|m| m.data()[i]))
        .filter(|&i| depth_valid(pred.data()[i]) && depth_valid(gt.data()[i]))
        .map(|i| Px { x: i % w, y: i / w, q: 1.0 / pred.data()[i] as f64, d: gt.data()[i] as f64 })
        .collect();
    if px.is_empty() {
        return Err(MetricError::NoValidPixels);
    }
    let n = px.len() as f64;
    let mean = px.iter().map(|p| p.d).sum::<f64>() / n;
    let std = (px.iter().map(|p| (p.d - mean).powi(2)).sum::<f64>() / n).sqrt();
    let score = |fit: &dyn Fn(&Px) -> f64| {
        let (mut sq, mut abs) = (0.0, 0.0);
        for p in &px {
            let e = fit(p) - p.d;
            sq += e * e;
            abs += e.abs();
        }
        let rmse = (sq / n).sqrt();
        DisparityMetrics { rel_rmse: if std > 0.0 { rmse / std } else { 0.0 }, rmse, mae: abs / n, count: px.len() }
    };
    let (scale, shift) = scale_shift(&px.iter().map(|p| (p.q, p.d)).collect::<Vec<_>>());
    // The plane; a degenerate one (pixels on one line) is the constant.
    let (pa, pb, pc) =
        fit_affine((gt.width(), gt.height()), px.iter().map(|p| (p.x, p.y, p.d))).unwrap_or((0.0, 0.0, mean));
    Ok(DisparityScores {
        prediction: score(&|p| scale * p.q + shift),
        scale,
        shift,
        constant: score(&|_| mean),
        plane: score(&|p| pa * p.x as f64 + pb * p.y as f64 + pc),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A slanted plane's disparity with a bump: d = 40 + 0.3 x + 0.1 y (+ 20 inside a square).
    fn disparity(bump: bool) -> Raster<f32> {
        Raster::from_fn(40, 30, |x, y| {
            let b = if bump && (10..20).contains(&x) && (10..20).contains(&y) { 20.0 } else { 0.0 };
            40.0 + 0.3 * x as f32 + 0.1 * y as f32 + b
        })
    }

    #[test]
    fn exact_inverse_depth_scores_zero_whatever_the_calibration() {
        let d = disparity(true);
        // z = f B / (d + d0) for two calibrations: both are affine in inverse depth.
        for (fb, d0) in [(500.0f32, 270.0f32), (3.0, 0.0)] {
            let z = d.map(|d| fb / (d + d0));
            let s = disparity_scores(&z, &d, None).unwrap();
            assert!(s.prediction.rel_rmse < 1e-5, "{:?}", s.prediction);
            assert!((s.scale - fb as f64).abs() < 1e-3 * fb as f64 && (s.shift + d0 as f64).abs() < 1e-2);
        }
    }

    #[test]
    fn baselines_match_their_definitions() {
        let d = disparity(true);
        let s = disparity_scores(&d.map(|_| 2.0), &d, None).unwrap();
        // The constant's RMSE is the standard deviation, and a constant prediction is the constant.
        assert!((s.constant.rel_rmse - 1.0).abs() < 1e-12);
        assert_eq!(s.prediction.rel_rmse, s.constant.rel_rmse);
        // A plane is fitted exactly; with the bump only the bump is left: the best plane of a
        // 10x10 square of +20 in 40x30 leaves less than the constant does.
        let flat = disparity(false);
        let s = disparity_scores(&flat.map(|d| 1.0 / d), &flat, None).unwrap();
        assert!(s.plane.rmse < 1e-4 && s.prediction.rmse < 1e-3, "{s:?}");
        let s = disparity_scores(&d.map(|d| 1.0 / d), &d, None).unwrap();
        assert!(s.plane.rel_rmse > 0.3 && s.plane.rel_rmse < s.constant.rel_rmse);
        assert!(s.prediction.rel_rmse < 1e-5);
        // Depth linear in disparity (the wrong way round) is not an affine map of it.
        let s = disparity_scores(&d.map(|d| *d), &d, None).unwrap();
        assert!(s.prediction.rel_rmse > 1e-3 && s.prediction.rel_rmse < 1.0, "{:?}", s.prediction);
    }

    #[test]
    fn unknown_pixels_and_errors() {
        // Zero disparity (unknown) and NaN depth are skipped; the mask restricts.
        let d = Raster::from_vec(4, 1, vec![0.0f32, 10.0, 20.0, 30.0]).unwrap();
        let z = Raster::from_vec(4, 1, vec![1.0f32, 0.1, f32::NAN, 1.0 / 30.0]).unwrap();
        let s = disparity_scores(&z, &d, None).unwrap();
        assert_eq!(s.prediction.count, 2);
        assert!(s.prediction.rmse < 1e-4);
        let m = Raster::from_vec(4, 1, vec![true, true, false, false]).unwrap();
        assert_eq!(disparity_scores(&z, &d, Some(&m)).unwrap().prediction.count, 1);
        let none = Raster::from_vec(4, 1, vec![0.0f32; 4]).unwrap();
        assert_eq!(disparity_scores(&z, &none, None), Err(MetricError::NoValidPixels));
        let small = Raster::filled(2, 1, 1.0f32);
        assert!(matches!(disparity_scores(&small, &d, None), Err(MetricError::SizeMismatch(..))));
    }
}
