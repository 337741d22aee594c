//! Two views from one pair prediction (DUSt3R's `PairViewer`): both cameras resected by
//! PnP-RANSAC in the pair's frame, giving the second camera's pose relative to the first and
//! both focals, without global optimisation.

use crate::global::{ConfTransform, PairPrediction};
use crate::resection::{pointmap_samples, resect_ransac, RansacOptions, Resection};
use glam::{DMat3, DMat4};

/// The relative pose of a pair.
#[derive(Debug, Clone, PartialEq)]
pub struct RelativePose {
    /// Camera `j` to camera `i` (OpenCV frames; rigid; translation in the pair's units).
    pub j_to_i: DMat4,
    /// Focal of camera `i`, pixels (principal point at the image centre).
    pub focal_i: f64,
    /// Focal of camera `j`.
    pub focal_j: f64,
    /// Fraction of the sampled pixels that are RANSAC inliers, per view.
    pub inliers: (f64, f64),
}

fn camera(r: &Resection) -> DMat4 {
    DMat4::from_mat3_translation(r.rotation, r.translation) // pair frame -> camera
}

/// Resects both views of `p` (confidence weights `log(conf)`); `None` when either view has
/// too few confident points or no camera explains it.
pub fn relative_pose(p: &PairPrediction) -> Option<RelativePose> {
    let side = |pts: &dens3r_geom::Raster<dens3r_geom::Vec3>, conf: &dens3r_geom::Raster<f32>| {
        let samples = pointmap_samples(pts, |k| ConfTransform::Log.weight(conf.data()[k]), 20_000);
        let (r, mask) = resect_ransac(&samples, &RansacOptions::for_image(pts.width(), pts.height()))?;
        Some((r, mask.iter().filter(|&&m| m).count() as f64 / mask.len().max(1) as f64))
    };
    let (ri, fi) = side(&p.pts_i, &p.conf_i)?;
    let (rj, fj) = side(&p.pts_j, &p.conf_j)?;
    // x_i = T_i X and x_j = T_j X, so x_i = T_i T_j^-1 x_j.
    let j_to_i = camera(&ri) * dens3r_geom::camera::rigid_inverse(&camera(&rj));
    let r = DMat3::from_mat4(j_to_i);
    debug_assert!((r.determinant() - 1.0).abs() < 1e-6);
    Some(RelativePose { j_to_i, focal_i: ri.focal, focal_j: rj.focal, inliers: (fi, fj) })
}
