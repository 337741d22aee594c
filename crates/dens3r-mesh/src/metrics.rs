//! Mesh-to-mesh metrics, the usual surface-reconstruction protocol: points sampled uniformly
//! on each mesh are measured against the **surface** of the other (exact point-to-triangle
//! distance through parry3d's BVH, so no sampling noise on the target side).

use crate::sample::sample_surface;
use crate::{InvalidMesh, TriMesh};
use glam::Vec3;
use parry3d::query::PointQuery;
use rayon::prelude::*;

/// Options for [`mesh_metrics`].
#[derive(Debug, Clone)]
pub struct MeshMetricsOptions {
    /// Points sampled on each mesh.
    pub samples: usize,
    /// F-score distance thresholds, in mesh units.
    pub thresholds: Vec<f64>,
    /// Sampling seed.
    pub seed: u64,
}

impl Default for MeshMetricsOptions {
    fn default() -> Self {
        Self { samples: 100_000, thresholds: vec![0.01, 0.02], seed: 0 }
    }
}

/// Precision, recall and F-score at one threshold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FScore {
    /// Distance threshold.
    pub threshold: f64,
    /// Fraction of predicted samples within the threshold of the ground truth.
    pub precision: f64,
    /// Fraction of ground-truth samples within the threshold of the prediction.
    pub recall: f64,
    /// Harmonic mean of precision and recall (0 when both are 0).
    pub fscore: f64,
}

/// Result of [`mesh_metrics`].
#[derive(Debug, Clone, PartialEq)]
pub struct MeshMetrics {
    /// Mean distance from predicted samples to the ground-truth surface.
    pub accuracy: f64,
    /// Mean distance from ground-truth samples to the predicted surface.
    pub completeness: f64,
    /// `(accuracy + completeness) / 2`.
    pub chamfer_l1: f64,
    /// One entry per threshold.
    pub fscores: Vec<FScore>,
    /// Mean `|n_a . n_b|` between each sample's face normal and the normal of the closest
    /// triangle on the other mesh, averaged over both directions (1 = perfect).
    pub normal_consistency: f64,
}

/// Compares a predicted mesh with a ground-truth mesh.
pub fn mesh_metrics(pred: &TriMesh, gt: &TriMesh, opts: &MeshMetricsOptions) -> Result<MeshMetrics, InvalidMesh> {
    mesh_metrics_where(pred, gt, opts, &|_| true)
}

/// [`mesh_metrics`] with completeness and recall measured only from the ground-truth samples
/// for which `gt_counts` holds (e.g. the parts of the truth some camera saw, so a
/// reconstruction is not charged for surfaces nobody observed). Accuracy and precision still
/// measure against the whole ground truth.
pub fn mesh_metrics_where(
    pred: &TriMesh,
    gt: &TriMesh,
    opts: &MeshMetricsOptions,
    gt_counts: &(dyn Fn(Vec3) -> bool + Sync),
) -> Result<MeshMetrics, InvalidMesh> {
    if opts.samples == 0 {
        return Err("the number of samples must be positive".into());
    }
    // Distances are measured in single precision: a coordinate of size M carries errors of
    // about 6e-8 M, so distances under about 1e-6 M cannot be told apart (a mesh with
    // coordinates of 1e20 scored as perfect against a room). Refused where that exceeds the
    // finest threshold, or a thousandth of the ground truth's size where a threshold is finer
    // (such thresholds only ask whether a surface is the same).
    let size = gt.bounds().map_or(0.0, |(lo, hi)| f64::from((hi - lo).length()));
    let finest = opts.thresholds.iter().copied().fold(f64::INFINITY, f64::min).max(1e-3 * size);
    for (name, m) in [("predicted", pred), ("ground-truth", gt)] {
        if m.positions.iter().any(|p| !p.is_finite()) {
            return Err(format!("{name} mesh has non-finite vertex coordinates").into());
        }
        let big = m.positions.iter().map(|p| p.abs().max_element()).fold(0.0f32, f32::max);
        if f64::from(big) * 1e-6 > finest.min(1e30) {
            return Err(format!(
                "{name} mesh has coordinates up to {big:e}: distances there cannot resolve {finest} in single \
                 precision; move the meshes near the origin or score with a coarser threshold"
            )
            .into());
        }
    }
    let one_way = |from: &TriMesh,
                   to: &TriMesh,
                   seed: u64,
                   name: &str,
                   keep: &(dyn Fn(Vec3) -> bool + Sync)|
     -> Result<(Vec<f64>, f64), InvalidMesh> {
        let target = to.to_parry().map_err(|e| format!("{name} target mesh: {e}"))?;
        let (pts, nrm) = sample_surface(from, opts.samples, seed);
        let (pts, nrm): (Vec<_>, Vec<_>) = pts.into_iter().zip(nrm).filter(|(p, _)| keep(*p)).unzip();
        if pts.is_empty() {
            return Err(format!("{name} mesh has no (selected) surface area to sample").into());
        }
        let res: Vec<(f64, f64)> = pts
            .par_iter()
            .zip(nrm.par_iter())
            .map(|(p, n)| {
                let (proj, _) = target.project_local_point_and_get_feature(*p);
                let d = (proj.point - *p).length() as f64;
                let tn = to.face_normal(proj.subshape as usize);
                (d, n.dot(tn).abs() as f64)
            })
            .collect();
        let nc = res.iter().map(|r| r.1).sum::<f64>() / res.len() as f64;
        Ok((res.into_iter().map(|r| r.0).collect(), nc))
    };
    let (d_pg, nc_p) = one_way(pred, gt, opts.seed, "predicted", &|_| true)?;
    let (d_gp, nc_g) = one_way(gt, pred, opts.seed.wrapping_add(1), "ground-truth", gt_counts)?;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let frac = |v: &[f64], t: f64| v.iter().filter(|&&d| d < t).count() as f64 / v.len() as f64;
    let fscores = opts
        .thresholds
        .iter()
        .map(|&t| {
            let (p, r) = (frac(&d_pg, t), frac(&d_gp, t));
            let f = if p + r > 0.0 { 2.0 * p * r / (p + r) } else { 0.0 };
            FScore { threshold: t, precision: p, recall: r, fscore: f }
        })
        .collect();
    let (accuracy, completeness) = (mean(&d_pg), mean(&d_gp));
    Ok(MeshMetrics {
        accuracy,
        completeness,
        chamfer_l1: 0.5 * (accuracy + completeness),
        fscores,
        normal_consistency: 0.5 * (nc_p + nc_g),
    })
}
