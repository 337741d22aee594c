//! Geometry core of dens3r: cameras and their conventions, depth <-> pointmap <-> normals,
//! rigid and similarity transforms, weighted Umeyama alignment, focal estimation from a
//! pointmap, and depth / normal metrics. No ML and no I/O.
//!
//! Conventions (explicit everywhere in this workspace):
//! - Camera frame: **OpenCV** (x right, y down, z forward). Pixel `(u, v)` = (column, row);
//!   integer coordinates are pixel centres, so pixel `(j, i)` looks along `K^-1 (j, i, 1)`.
//! - Poses: **camera-to-world** 4x4 matrices (`world = c2w * cam`).
//! - Normals: unit vectors in the OpenCV camera frame, **facing the camera** (`n . ray < 0`).
//!   [`convention`] converts to the Dens3R raw / saved and OpenGL conventions.
//! - Depth: z-depth (distance along the optical axis); `0` or NaN marks an invalid pixel.

pub mod align;
pub mod camera;
pub mod convention;
pub mod focal;
pub mod metrics;
pub mod normals;
pub mod pointmap;
pub mod raster;
pub mod transform;

pub use align::{umeyama, AlignError};
pub use camera::{look_at, Intrinsics, PinholeCamera};
pub use convention::NormalConvention;
pub use focal::{focal_from_pointmap, focal_or_fallback, FocalMode, FALLBACK_HFOV_DEG};
pub use raster::{Raster, RasterError};
pub use transform::Sim3;

/// Re-exported vector types so downstream crates use the same glam version.
pub use glam::{DMat3, DMat4, DVec3, Mat3, Mat4, Vec2, Vec3};
