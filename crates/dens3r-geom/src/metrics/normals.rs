//! Normal-map metrics (the usual table protocol: mean, median, RMSE of the angular error and
//! the fraction of pixels under 11.25 / 22.5 / 30 degrees).

use super::MetricError;
use crate::raster::Raster;
use glam::Vec3;

/// Angular errors in degrees over pixels where both normals are valid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NormalMetrics {
    /// Mean angle.
    pub mean: f64,
    /// Median angle.
    pub median: f64,
    /// Root mean square angle.
    pub rmse: f64,
    /// Fraction (0..1) under 11.25, 22.5 and 30 degrees.
    pub within: [f64; 3],
    /// Pixels scored.
    pub count: usize,
}

/// The thresholds of [`NormalMetrics::within`], degrees.
pub const NORMAL_THRESHOLDS_DEG: [f64; 3] = [11.25, 22.5, 30.0];

/// Scores `pred` against `gt` (same convention). A normal is valid when finite and non-zero;
/// both are normalised first.
pub fn normal_metrics(
    pred: &Raster<Vec3>,
    gt: &Raster<Vec3>,
    mask: Option<&Raster<bool>>,
) -> Result<NormalMetrics, MetricError> {
    super::check_sizes(pred, gt, mask)?;
    let valid = |n: Vec3| n.is_finite() && n.length_squared() > 1e-12;
    let mut angles: Vec<f64> = (0..gt.data().len())
        .filter(|&i| mask.is_none_or(|m| m.data()[i]))
        .filter(|&i| valid(pred.data()[i]) && valid(gt.data()[i]))
        .map(|i| {
            let (a, b) = (pred.data()[i].as_dvec3().normalize(), gt.data()[i].as_dvec3().normalize());
            // atan2 of |a x b| and a.b is accurate for tiny angles, unlike acos.
            a.cross(b).length().atan2(a.dot(b)).to_degrees()
        })
        .collect();
    if angles.is_empty() {
        return Err(MetricError::NoValidPixels);
    }
    let n = angles.len() as f64;
    let mean = angles.iter().sum::<f64>() / n;
    let rmse = (angles.iter().map(|a| a * a).sum::<f64>() / n).sqrt();
    let within = NORMAL_THRESHOLDS_DEG.map(|t| angles.iter().filter(|&&a| a < t).count() as f64 / n);
    let count = angles.len();
    let median = crate::focal::median(&mut angles).unwrap();
    Ok(NormalMetrics { mean, median, rmse, within, count })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_angles() {
        let gt = Raster::filled(4, 1, Vec3::new(0.0, 0.0, -1.0));
        let deg = [0.0f32, 10.0, 20.0, 40.0];
        let pred = Raster::from_vec(
            4,
            1,
            deg.iter().map(|d| Vec3::new(d.to_radians().sin(), 0.0, -d.to_radians().cos()) * 3.0).collect(),
        )
        .unwrap();
        let m = normal_metrics(&pred, &gt, None).unwrap();
        assert!((m.mean - 17.5).abs() < 1e-4, "{}", m.mean);
        assert!((m.median - 15.0).abs() < 1e-4);
        assert_eq!(m.within, [0.5, 0.75, 0.75]);
        let zero = Raster::filled(4, 1, Vec3::ZERO);
        assert_eq!(normal_metrics(&zero, &gt, None), Err(MetricError::NoValidPixels));
    }
}
