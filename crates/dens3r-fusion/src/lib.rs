//! Reconstruction (Open3D's split: integration, then extraction): [`tsdf`] fuses per-view
//! depth (+ colour and per-pixel weights from confidence or normals) into a sparse voxel-block
//! TSDF; [`extract`] runs marching cubes over it into an indexed mesh with normals and colours;
//! [`scene`] drives both from a scene folder. With the `gpu` feature, `gpu::GpuTsdf` runs the
//! integration as a WGSL compute pass through wgpu.

pub mod extract;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod scene;
pub mod tsdf;

pub use extract::{extract_mesh, ExtractOptions};
#[cfg(feature = "gpu")]
pub use gpu::GpuTsdf;
pub use tsdf::{FrameInput, FusionError, SparseTsdf, TsdfParams};
