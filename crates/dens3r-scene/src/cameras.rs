//! `cameras.json`: the camera list of a scene folder.

use dens3r_geom::camera::{mat4_from_rows, mat4_to_rows};
use dens3r_geom::transform::is_rotation;
use dens3r_geom::{DMat3, DMat4, Intrinsics, PinholeCamera};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// Largest accepted image side, in pixels (a guard against corrupt or absurd sizes).
pub const MAX_IMAGE_SIDE: usize = 16384;

/// One view: its image and camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// Unique name; also the stem of every per-frame layer file.
    pub name: String,
    /// Image path relative to the scene folder, e.g. `images/000.png`.
    pub image: String,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Intrinsics `K`, row-major 3x3 (OpenCV, pixel centres at integers).
    #[serde(rename = "K")]
    pub k: [[f64; 3]; 3],
    /// Camera-to-world pose, row-major 4x4 (OpenCV camera frame).
    pub cam_to_world: [[f64; 4]; 4],
    /// Any further keys, kept as they are.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// A frame entry that cannot be used (a bad name, size, intrinsics, pose or image path); one
/// line saying which frame and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidFrame(pub String);

impl Frame {
    /// A frame for `name` whose image is `images/<name>.png`.
    pub fn new(name: &str, camera: &PinholeCamera) -> Self {
        Self {
            name: name.to_string(),
            image: format!("images/{name}.png"),
            width: camera.width,
            height: camera.height,
            k: camera.intrinsics.to_rows(),
            cam_to_world: mat4_to_rows(&camera.cam_to_world),
            extra: Map::new(),
        }
    }

    /// The camera-to-world pose as a matrix.
    pub fn pose(&self) -> DMat4 {
        mat4_from_rows(&self.cam_to_world)
    }

    /// The camera (valid once the frame passed [`Frame::check`]).
    pub fn camera(&self) -> PinholeCamera {
        PinholeCamera {
            intrinsics: Intrinsics::from_rows(&self.k).unwrap_or(Intrinsics { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0 }),
            width: self.width,
            height: self.height,
            cam_to_world: self.pose(),
        }
    }

    /// Checks name, size, intrinsics and pose; the message says what is wrong.
    pub fn check(&self) -> Result<(), InvalidFrame> {
        let name_ok =
            !self.name.is_empty() && self.name != "." && self.name != ".." && !self.name.contains(['/', '\\', '\0']);
        if !name_ok {
            return Err(InvalidFrame(format!("frame name {:?} must be a plain file stem (no slashes)", self.name)));
        }
        let who = format!("frame '{}'", self.name);
        if self.width == 0 || self.height == 0 || self.width > MAX_IMAGE_SIDE || self.height > MAX_IMAGE_SIDE {
            return Err(InvalidFrame(format!(
                "{who}: size {}x{} is outside 1..={MAX_IMAGE_SIDE}",
                self.width, self.height
            )));
        }
        if Intrinsics::from_rows(&self.k).is_none() {
            return Err(InvalidFrame(format!(
                "{who}: K must be finite [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, got {:?}",
                self.k
            )));
        }
        let p = &self.cam_to_world;
        if p.iter().flatten().any(|v| !v.is_finite()) {
            return Err(InvalidFrame(format!("{who}: cam_to_world has a NaN or infinite entry")));
        }
        if p[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(InvalidFrame(format!("{who}: cam_to_world's last row must be [0, 0, 0, 1], got {:?}", p[3])));
        }
        let r = DMat3::from_mat4(self.pose());
        if !is_rotation(&r, 1e-4) {
            return Err(InvalidFrame(format!(
                "{who}: cam_to_world's 3x3 block is not a rotation (orthonormal, det +1); scale or mirror it out"
            )));
        }
        let img = std::path::Path::new(&self.image);
        if self.image.is_empty()
            || img.is_absolute()
            || img.components().any(|c| matches!(c, std::path::Component::ParentDir))
        {
            return Err(InvalidFrame(format!(
                "{who}: image path {:?} must be relative and inside the scene folder",
                self.image
            )));
        }
        Ok(())
    }
}

/// The whole `cameras.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CamerasFile {
    /// Always `"opencv"`.
    pub convention: String,
    /// The views, in order.
    pub frames: Vec<Frame>,
    /// Any further keys, kept as they are.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}
