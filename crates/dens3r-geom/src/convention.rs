//! Camera-frame normal conventions and converters.
//!
//! Every variant is a sign flip of the OpenCV facing-camera normal `n_cv` (see the model
//! spec, section 3.4), so each conversion is exact and its own inverse:
//!
//! | convention | vector | camera-facing wall |
//! |---|---|---|
//! | [`NormalConvention::OpenCv`] | `( x,  y,  z)` | `(0, 0, -1)` |
//! | [`NormalConvention::Dens3rRaw`] (model output, training GT) | `( x, -y,  z)` | `(0, 0, -1)` |
//! | [`NormalConvention::Dens3rSaved`] (`_normal.npz`, viz PNG, eval `.npy`) | `(-x, -y,  z)` | `(0, 0, -1)` |
//! | [`NormalConvention::OpenGl`] (x right, y up, z backward) | `( x, -y, -z)` | `(0, 0,  1)` |

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// A camera-frame normal convention.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormalConvention {
    /// OpenCV camera frame (x right, y down, z forward), facing the camera. Our native one.
    OpenCv,
    /// Dens3R network output: `(x, -y, z)` of OpenCV.
    Dens3rRaw,
    /// Dens3R saved files: `(-x, -y, z)` of OpenCV.
    Dens3rSaved,
    /// OpenGL / Blender / nerfstudio camera frame: `(x, -y, -z)` of OpenCV.
    OpenGl,
}

impl NormalConvention {
    /// All conventions, for iteration.
    pub const ALL: [NormalConvention; 4] = [Self::OpenCv, Self::Dens3rRaw, Self::Dens3rSaved, Self::OpenGl];

    /// The per-axis signs `s` with `n_self = s * n_opencv`.
    pub fn signs(self) -> Vec3 {
        match self {
            Self::OpenCv => Vec3::new(1.0, 1.0, 1.0),
            Self::Dens3rRaw => Vec3::new(1.0, -1.0, 1.0),
            Self::Dens3rSaved => Vec3::new(-1.0, -1.0, 1.0),
            Self::OpenGl => Vec3::new(1.0, -1.0, -1.0),
        }
    }

    /// Converts a normal given in `self` to the OpenCV convention.
    #[inline]
    pub fn to_opencv(self, n: Vec3) -> Vec3 {
        n * self.signs()
    }

    /// Converts an OpenCV normal to `self`.
    #[inline]
    pub fn from_opencv(self, n: Vec3) -> Vec3 {
        n * self.signs()
    }

    /// Converts a normal from `self` to `to`.
    #[inline]
    pub fn convert(self, n: Vec3, to: NormalConvention) -> Vec3 {
        n * self.signs() * to.signs()
    }

    /// Parses `opencv`, `dens3r-raw`, `dens3r-saved` or `opengl` (also with underscores).
    pub fn parse(s: &str) -> Option<Self> {
        match s.to_ascii_lowercase().replace('_', "-").as_str() {
            "opencv" => Some(Self::OpenCv),
            "dens3r-raw" | "raw" => Some(Self::Dens3rRaw),
            "dens3r-saved" | "saved" => Some(Self::Dens3rSaved),
            "opengl" | "blender" | "nerfstudio" => Some(Self::OpenGl),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_wall() {
        let n = Vec3::new(0.3, -0.5, -0.81).normalize();
        let wall = Vec3::new(0.0, 0.0, -1.0);
        for a in NormalConvention::ALL {
            assert_eq!(a.to_opencv(a.from_opencv(n)), n);
            for b in NormalConvention::ALL {
                assert_eq!(b.convert(a.convert(n, b), a), n);
            }
        }
        assert_eq!(NormalConvention::Dens3rRaw.from_opencv(wall), Vec3::new(0.0, 0.0, -1.0));
        assert_eq!(NormalConvention::Dens3rSaved.from_opencv(wall), Vec3::new(0.0, 0.0, -1.0));
        assert_eq!(NormalConvention::OpenGl.from_opencv(wall), Vec3::new(0.0, 0.0, 1.0));
        // A floor seen from above in OpenCV points up = -y; the raw model output has +y.
        let floor = Vec3::new(0.0, -1.0, 0.0);
        assert_eq!(NormalConvention::Dens3rRaw.from_opencv(floor).y, 1.0);
        assert_eq!(NormalConvention::Dens3rSaved.from_opencv(Vec3::X).x, -1.0);
        assert_eq!(NormalConvention::parse("dens3r_saved"), Some(NormalConvention::Dens3rSaved));
    }
}
