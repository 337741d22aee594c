//! Reconstruction (Open3D's split: integration, then extraction): [`tsdf`] fuses per-view
//! depth (+ colour and per-pixel weights from confidence or normals) into a sparse voxel-block
//! TSDF; [`extract`] runs marching cubes over it into an indexed mesh with normals and colours;
//! [`scene`] drives both from a scene folder.

pub mod extract;
pub mod scene;
pub mod tsdf;

pub use extract::{extract_mesh, ExtractOptions};
pub use tsdf::{FrameInput, FusionError, SparseTsdf, TsdfParams};
