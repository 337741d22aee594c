//! Multi-view (spec sections 3.5 and 6): [`pairs`] builds the image pairs the network runs on,
//! [`global`] aligns the pairwise pointmaps into one scene (cameras, focal, depth: DUSt3R's
//! `PointCloudOptimizer` with the minimum-spanning-tree initialisation, written natively), and
//! [`matching`] finds MASt3R fast reciprocal nearest-neighbour correspondences between
//! descriptor maps and joins them into tracks; [`two_view`] gives a pair's relative pose by
//! PnP-RANSAC ([`resection`]) without global optimisation; [`match_pose`] places a pair's
//! second view by its matches and its own-frame pointmap instead of the network's cross-view
//! pointmap; [`keypoints`] (SIFT) and [`epipolar`] (the essential matrix) place a pair by
//! classical matches when the network's descriptors do not match.

pub mod cycle_focal;
pub mod epipolar;
pub mod global;
pub mod homography;
pub mod keypoints;
pub mod match_pose;
pub mod matching;
pub mod pairs;
mod ransac;
pub mod resection;
pub mod retrieval;
pub mod rotations;
pub mod two_view;
pub mod union_find;

pub use global::{global_align, AlignOptions, AlignedView, Alignment, ConfTransform, GlobalAlignError, PairPrediction};
pub use pairs::{make_pairs, verified_subgraph, PairGraph};
pub use rotations::{average_rotations, consistent_rotations};
pub use two_view::{relative_pose, RelativePose};
