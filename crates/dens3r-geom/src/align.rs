//! Weighted Umeyama / Procrustes alignment.

use crate::transform::Sim3;
use glam::{DMat3, DVec3};
use glamx::DSvd3;
use thiserror::Error;

/// Why an alignment could not be computed.
#[derive(Debug, Error, PartialEq)]
pub enum AlignError {
    /// The point lists (or weights) have different lengths.
    #[error("alignment needs as many source as target points and weights ({0} vs {1} vs {2})")]
    LengthMismatch(usize, usize, usize),
    /// A point or weight is NaN/inf, or a weight is negative.
    #[error("alignment input has a non-finite point or a negative / non-finite weight at index {0}")]
    BadValue(usize),
    /// Fewer than three weighted points, or all of them (nearly) collinear.
    #[error("alignment is degenerate: it needs at least 3 non-collinear points with positive weight")]
    Degenerate,
}

/// Weighted least-squares similarity (or rigid, `with_scale = false`) transform `T`
/// minimising `sum_i w_i |T(src_i) - dst_i|^2` (Umeyama 1991). `weights = None` means all 1.
pub fn umeyama(src: &[DVec3], dst: &[DVec3], weights: Option<&[f64]>, with_scale: bool) -> Result<Sim3, AlignError> {
    let n = src.len();
    let wlen = weights.map_or(n, <[f64]>::len);
    if dst.len() != n || wlen != n {
        return Err(AlignError::LengthMismatch(n, dst.len(), wlen));
    }
    let w = |i: usize| weights.map_or(1.0, |w| w[i]);
    let mut wsum = 0.0;
    let (mut mx, mut my) = (DVec3::ZERO, DVec3::ZERO);
    let mut count = 0;
    for i in 0..n {
        let wi = w(i);
        if !(wi.is_finite() && wi >= 0.0 && src[i].is_finite() && dst[i].is_finite()) {
            return Err(AlignError::BadValue(i));
        }
        if wi > 0.0 {
            count += 1;
        }
        wsum += wi;
        mx += src[i] * wi;
        my += dst[i] * wi;
    }
    if count < 3 || wsum <= 0.0 {
        return Err(AlignError::Degenerate);
    }
    mx /= wsum;
    my /= wsum;
    let mut cov = DMat3::ZERO;
    let mut var_x = 0.0;
    for i in 0..n {
        let (dx, dy) = (src[i] - mx, dst[i] - my);
        let wi = w(i) / wsum;
        // cov += wi * dy * dx^T
        cov += DMat3::from_cols(dy * dx.x, dy * dx.y, dy * dx.z) * wi;
        var_x += wi * dx.length_squared();
    }
    let svd = DSvd3::from_matrix(cov);
    if var_x <= 0.0 || svd.s.y <= 1e-12 * svd.s.x.max(1e-300) {
        return Err(AlignError::Degenerate);
    }
    let d = if (svd.u.determinant() * svd.vt.determinant()) < 0.0 { -1.0 } else { 1.0 };
    let sdiag = DMat3::from_diagonal(DVec3::new(1.0, 1.0, d));
    let rotation = svd.u * sdiag * svd.vt;
    let scale = if with_scale { (svd.s.x + svd.s.y + d * svd.s.z) / var_x } else { 1.0 };
    let translation = my - rotation * mx * scale;
    Ok(Sim3 { scale, rotation, translation })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transform::axis_angle;
    use rand::{Rng, SeedableRng};

    #[test]
    fn recovers_random_similarities() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..50 {
            let axis = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
            let truth = Sim3 {
                scale: rng.gen_range(0.01..100.0),
                rotation: axis_angle(axis, rng.gen_range(-3.1..3.1)),
                translation: DVec3::new(
                    rng.gen_range(-50.0..50.0),
                    rng.gen_range(-50.0..50.0),
                    rng.gen_range(-50.0..50.0),
                ),
            };
            let src: Vec<DVec3> = (0..40)
                .map(|_| DVec3::new(rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0)))
                .collect();
            let dst: Vec<DVec3> = src.iter().map(|p| truth.apply(*p)).collect();
            let wts: Vec<f64> = (0..40).map(|_| rng.gen_range(0.1..3.0)).collect();
            let est = umeyama(&src, &dst, Some(&wts), true).unwrap();
            assert!((est.scale / truth.scale - 1.0).abs() < 1e-6, "{} vs {}", est.scale, truth.scale);
            assert!((est.rotation - truth.rotation).to_cols_array().iter().all(|v| v.abs() < 1e-6));
            assert!((est.translation - truth.translation).length() < 1e-6 * (1.0 + truth.translation.length()));
        }
    }

    #[test]
    fn weights_ignore_outliers_and_reflection_is_avoided() {
        let src = [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ZERO, DVec3::ONE];
        let truth = Sim3::rigid(axis_angle(DVec3::Z, 0.5), DVec3::new(1.0, 2.0, 3.0));
        let mut dst: Vec<DVec3> = src.iter().map(|p| truth.apply(*p)).collect();
        dst[4] = DVec3::splat(100.0);
        let est = umeyama(&src, &dst, Some(&[1.0, 1.0, 1.0, 1.0, 0.0]), false).unwrap();
        assert!(est.rotation_angle_deg(&truth) < 1e-6);
        // A mirrored target still yields a proper rotation (det +1).
        let mirrored: Vec<DVec3> = src.iter().map(|p| DVec3::new(-p.x, p.y, p.z)).collect();
        let r = umeyama(&src, &mirrored, None, true).unwrap();
        assert!((r.rotation.determinant() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let line = [DVec3::ZERO, DVec3::X, DVec3::X * 2.0, DVec3::X * 3.0];
        assert_eq!(umeyama(&line, &line, None, true), Err(AlignError::Degenerate));
        assert_eq!(umeyama(&line[..2], &line[..2], None, true), Err(AlignError::Degenerate));
        assert!(matches!(umeyama(&line, &line[..3], None, true), Err(AlignError::LengthMismatch(..))));
        let bad = [DVec3::NAN, DVec3::X, DVec3::Y];
        assert_eq!(umeyama(&bad, &bad, None, true), Err(AlignError::BadValue(0)));
    }
}
