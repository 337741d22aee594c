//! Evaluation metrics for depth, disparity and normal maps and cameras (mesh metrics live in `dens3r-mesh`).

pub mod baselines;
pub mod cameras;
pub mod depth;
pub mod disparity;
pub mod normals;

pub use baselines::{constant_baseline, plane_baseline, Baseline};
pub use cameras::{camera_metrics, CameraMetrics};
pub use depth::{depth_metrics, DepthAlign, DepthMetrics};
pub use disparity::{disparity_scores, DisparityMetrics, DisparityScores};
pub use normals::{normal_metrics, NormalMetrics};

use crate::raster::Raster;

/// Why a metric could not be computed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricError {
    /// The two maps differ in size.
    #[error("maps differ in size: {0}x{1} vs {2}x{3}")]
    SizeMismatch(usize, usize, usize, usize),
    /// No pixel is valid in both maps (and the mask).
    #[error("no pixel is valid in both maps")]
    NoValidPixels,
}

/// `pred`, `gt` and `mask` (if given) must be one size.
fn check_sizes<A, B>(pred: &Raster<A>, gt: &Raster<B>, mask: Option<&Raster<bool>>) -> Result<(), MetricError> {
    if !pred.same_size(gt) || mask.is_some_and(|m| !m.same_size(gt)) {
        return Err(MetricError::SizeMismatch(pred.width(), pred.height(), gt.width(), gt.height()));
    }
    Ok(())
}
