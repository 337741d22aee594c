//! Reconstruction (Open3D's split: storage, integration, extraction): [`grid`] stores sparse
//! 8^3-voxel blocks ([`VoxelBlockGrid`]); [`tsdf`] fuses per-view depth (+ colour and per-pixel
//! weights from confidence or normals) into one; [`extract`] runs marching cubes over a grid
//! into an indexed mesh with normals and colours;
//! [`scene`] drives both from a scene folder. With the `gpu` feature, `gpu::GpuTsdf` runs the
//! integration as a WGSL compute pass through wgpu.

mod error;
pub mod extract;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod grid;
pub mod scene;
pub mod tsdf;

pub use extract::{extract_mesh, ExtractOptions};
#[cfg(feature = "gpu")]
pub use gpu::GpuTsdf;
pub use grid::{GridSpec, VoxelBlockGrid};
pub use tsdf::{FrameInput, FusionError, SparseTsdf, TsdfParams};
