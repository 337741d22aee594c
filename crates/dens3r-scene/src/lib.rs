//! The scene folder, the one interchange format every dens3r crate reads and writes
//! (specified in `docs/scene-format.md`):
//!
//! ```text
//! scene/
//!   cameras.json          {"convention": "opencv", "frames": [{name, image, width, height, K, cam_to_world}]}
//!   images/<name>.png     RGB
//!   depth/<name>.npy      float32 HxW z-depth (0 or NaN = invalid)
//!   normals/<name>.npy    float32 HxWx3 unit, OpenCV camera frame, facing the camera (0 = invalid)
//!   conf/<name>.npy       float32 HxW (optional)
//!   masks/<name>.png      8-bit, 0 = ignore (optional)
//!   labels/<name>.png     semantic ids, 8- or 16-bit (optional)
//!   instances/<name>.png  instance ids, 16-bit (optional)
//!   classes.json          {"<id>": "<name>"} (optional)
//!   gt_mesh.ply           ground-truth surface in world coordinates (optional)
//! ```
//!
//! [`Scene::open`] validates `cameras.json` and the presence of every image; layers are
//! read lazily and checked against the frame size. [`SceneWriter`] writes every file to a
//! temporary name and renames it, and writes `cameras.json` last, so an interrupted write
//! never looks like a complete scene.

mod cameras;
mod classes;
mod error;
pub mod eval;
pub mod export;
pub mod npy;
pub mod pfm;
mod reader;
pub mod visibility;
pub mod viz;
mod writer;

pub use cameras::{CamerasFile, Frame, InvalidFrame, MAX_IMAGE_SIDE};
pub use classes::{read_classes, write_classes};
pub use error::SceneError;
pub use reader::{Layer, Scene};
pub use writer::{begin_output, holds_scene, write_id_png, write_rgb_png, SceneWriter};
