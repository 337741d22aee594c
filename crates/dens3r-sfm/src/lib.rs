//! Global structure-from-motion, GLOMAP's pipeline one file per stage: [`view_graph`]
//! (keypoint matches verified by their epipolar geometry), [`tracks`] (union-find over the
//! verified matches), [`rotation_averaging`], [`global_positioning`] (centres and points
//! together, rotations fixed), [`bundle_adjustment`] (poses, points and focals on the
//! reprojection error) and [`pipeline`], which runs them with focal initialisation, filtering
//! and retriangulation. Cameras are camera-to-world, OpenCV frame; pixels have `(0, 0)` at the
//! first pixel's centre. The network plays no part here: `dens3r-recon` runs it for depth and
//! normals and fits them to the cameras and points this crate finds.

pub mod bundle_adjustment;
pub mod global_positioning;
mod linalg;
pub mod pipeline;
pub mod rotation_averaging;
pub mod tracks;
pub mod view_graph;

pub use pipeline::{run, run_matched, FocalSource, Sfm, SfmInput, SfmOptions, SfmPoint, SfmStats};
