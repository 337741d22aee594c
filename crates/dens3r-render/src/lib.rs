//! Ground-truth renderer for dens3r.
//!
//! A [`World`] holds objects (analytic spheres and boxes, or triangle meshes) with materials,
//! semantic classes and instance ids. [`World::render`] ray-casts one pinhole camera with
//! parry3d (rayon over rows) and returns RGB with simple shading and a per-object procedural
//! texture, z-depth, camera-frame normals (OpenCV, facing the camera), semantic labels and
//! instance ids. [`path`] makes camera paths (orbit an object, walk inside a room),
//! [`procedural`] makes scenes, [`synth`] draws varied training scenes from a seed, and [`render_to_scene`] writes a whole scene folder.
//!
//! Pixel `(j, i)` is sampled at its centre, the ray through `K^-1 (j, i, 1)`: exactly the
//! convention of `dens3r-geom`, so `depth_to_pointmap` of a rendered depth lies on the
//! surface.

pub mod material;
pub mod noise;
pub mod path;
pub mod procedural;
pub mod synth;
mod to_scene;
mod world;

pub use material::{Material, Texture};
pub use to_scene::{render_cameras_to_scene, render_to_scene, RenderSummary};
pub use world::{Object, Occlusion, RenderedView, Shape, World, WorldError};
