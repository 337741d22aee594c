//! Multi-view stereo for dens3r, staged as COLMAP's `mvs/` and OpenMVS's `DepthMap`: options
//! apart ([`options`]), which views each reference matches ([`views`]), the per-view
//! PatchMatch problem ([`patch_match`]: planes per pixel, checkerboard propagation, bilateral
//! NCC over the best source views, ACMM's geometric consistency, the network's depth and
//! normals as a confidence-weighted prior), fusion by multi-view agreement ([`fusion`]), and
//! the stage over a set of views read on demand ([`pipeline`]).
//!
//! Conventions: OpenCV camera frames, camera-to-world poses, pixel centres at integers,
//! z-depth, camera-frame normals facing the camera.

pub mod fusion;
pub mod image;
pub mod options;
pub mod output;
pub mod patch_match;
pub mod pipeline;
pub mod scene;
mod simd;
pub mod views;

pub use fusion::{DepthNormalMap, FusedPoint};
pub use options::{FusionOptions, MvsOptions, PatchMatchOptions};
pub use pipeline::{run_mvs, MvsError, MvsResult, PriorMaps, Stage, ViewResult, ViewSource};
