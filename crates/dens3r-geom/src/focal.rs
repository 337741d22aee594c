//! Focal length from a camera-frame pointmap (DUSt3R `estimate_focal_knowing_depth`,
//! spec section 6.1).

use crate::pointmap::point_valid;
use crate::raster::Raster;
use glam::Vec3;

/// How to estimate the focal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FocalMode {
    /// Least-squares start, then 10 IRLS (Weiszfeld) iterations on the reprojection residual.
    Weiszfeld,
    /// `nanmedian` of `u z / x` and `v z / y` over all pixels.
    Median,
}

/// Single focal `f` (pixels, `fx = fy`) that best explains a camera-frame pointmap seen from
/// principal point `pp` (DUSt3R uses `(W/2, H/2)`). Pixel `(j, i)` sits at coordinate
/// `(j, i)`. Invalid points are skipped. `None` when no point is usable.
pub fn focal_from_pointmap(points: &Raster<Vec3>, pp: (f64, f64), mode: FocalMode) -> Option<f64> {
    let mut samples = Vec::with_capacity(points.data().len());
    for y in 0..points.height() {
        for x in 0..points.width() {
            let p = *points.get(x, y);
            if point_valid(p) {
                let uv = (x as f64 - pp.0, y as f64 - pp.1);
                samples.push((p.x as f64 / p.z as f64, p.y as f64 / p.z as f64, uv.0, uv.1));
            }
        }
    }
    if samples.is_empty() {
        return None;
    }
    match mode {
        FocalMode::Median => {
            let mut r: Vec<f64> = Vec::with_capacity(samples.len() * 2);
            for &(a, b, u, v) in &samples {
                for (num, den) in [(u, a), (v, b)] {
                    let q = num / den;
                    if q.is_finite() {
                        r.push(q);
                    }
                }
            }
            median(&mut r)
        }
        FocalMode::Weiszfeld => {
            let ratio = |wt: &dyn Fn(f64, f64, f64, f64) -> f64| {
                let (mut num, mut den) = (0.0, 0.0);
                for &(a, b, u, v) in &samples {
                    let w = wt(a, b, u, v);
                    num += w * (a * u + b * v);
                    den += w * (a * a + b * b);
                }
                num / den
            };
            let mut f = ratio(&|_, _, _, _| 1.0);
            for _ in 0..10 {
                let fk = f;
                f = ratio(&|a, b, u, v| 1.0 / ((u - fk * a).hypot(v - fk * b)).max(1e-8));
            }
            f.is_finite().then_some(f)
        }
    }
}

/// The field of view a camera starts from when its pointmap gives no focal (untrained weights).
pub const FALLBACK_HFOV_DEG: f64 = 60.0;

/// The focal (pixels) of a `width` x `height` image whose camera-frame pointmap is `points`,
/// principal point at the image centre: the pointmap's Weiszfeld focal when it gives a positive
/// finite one (`Ok`), else (`Err`) the focal of a [`FALLBACK_HFOV_DEG`] horizontal field of
/// view, which callers report as a warning.
pub fn focal_or_fallback(points: &Raster<Vec3>, width: usize, height: usize) -> Result<f64, f64> {
    let pp = (width as f64 / 2.0, height as f64 / 2.0);
    match focal_from_pointmap(points, pp, FocalMode::Weiszfeld).filter(|f| f.is_finite() && *f > 0.0) {
        Some(f) => Ok(f),
        None => Err(crate::Intrinsics::from_hfov(width, height, FALLBACK_HFOV_DEG).fx),
    }
}

/// Median of finite values (mean of the two middle ones for even counts); `None` if empty.
pub fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 { values[n / 2] } else { 0.5 * (values[n / 2 - 1] + values[n / 2]) })
}
