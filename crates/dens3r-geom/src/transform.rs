//! Similarity (and rigid) transforms in f64.

use glam::{DMat3, DMat4, DQuat, DVec3};
use glamx::DSvd3;

/// `x -> scale * rotation * x + translation`. A rigid transform has `scale == 1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3 {
    /// Uniform scale (> 0).
    pub scale: f64,
    /// Rotation matrix (orthonormal, det +1).
    pub rotation: DMat3,
    /// Translation.
    pub translation: DVec3,
}

impl Default for Sim3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Sim3 {
    /// The identity.
    pub const IDENTITY: Sim3 = Sim3 { scale: 1.0, rotation: DMat3::IDENTITY, translation: DVec3::ZERO };

    /// A rigid transform.
    pub fn rigid(rotation: DMat3, translation: DVec3) -> Self {
        Self { scale: 1.0, rotation, translation }
    }

    /// Applies the transform to a point.
    #[inline]
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.rotation * p * self.scale + self.translation
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        let s = 1.0 / self.scale;
        Self { scale: s, rotation: rt, translation: -(rt * self.translation) * s }
    }

    /// `self * other` (apply `other` first).
    pub fn compose(&self, other: &Sim3) -> Self {
        Self {
            scale: self.scale * other.scale,
            rotation: self.rotation * other.rotation,
            translation: self.apply(other.translation),
        }
    }

    /// As a 4x4 matrix.
    pub fn to_mat4(&self) -> DMat4 {
        DMat4::from_mat3_translation(self.rotation * self.scale, self.translation)
    }

    /// Decomposes a 4x4 similarity matrix (uniform scale, no shear); `None` otherwise.
    pub fn from_mat4(m: &DMat4) -> Option<Self> {
        let a = DMat3::from_mat4(*m);
        let det = a.determinant();
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        let scale = det.cbrt();
        let rotation = a * (1.0 / scale);
        is_rotation(&rotation, 1e-6).then_some(Self { scale, rotation, translation: m.w_axis.truncate() })
    }

    /// Rotation angle of `self.rotation^T * other.rotation`, in degrees.
    pub fn rotation_angle_deg(&self, other: &Sim3) -> f64 {
        rotation_angle_deg(&(self.rotation.transpose() * other.rotation))
    }
}

/// True when `r` is orthonormal with determinant +1 within `tol`.
pub fn is_rotation(r: &DMat3, tol: f64) -> bool {
    (*r * r.transpose()).abs_diff_eq(DMat3::IDENTITY, tol) && (r.determinant() - 1.0).abs() < tol
}

/// The rotation nearest to `m` in the Frobenius norm (`U V^T` of its SVD, with the sign of
/// the smallest singular direction flipped when that would be a reflection).
pub fn nearest_rotation(m: DMat3) -> DMat3 {
    let svd = DSvd3::from_matrix(m);
    let d = if (svd.u.determinant() * svd.vt.determinant()) < 0.0 { -1.0 } else { 1.0 };
    svd.u * DMat3::from_diagonal(DVec3::new(1.0, 1.0, d)) * svd.vt
}

/// Rotation angle of a rotation matrix, degrees.
pub fn rotation_angle_deg(r: &DMat3) -> f64 {
    ((r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Rotation from a unit axis and an angle in radians.
pub fn axis_angle(axis: DVec3, angle: f64) -> DMat3 {
    DMat3::from_quat(DQuat::from_axis_angle(axis.normalize(), angle))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rotation_projects_onto_rotations() {
        let r = axis_angle(DVec3::new(1.0, -2.0, 0.5), 1.1);
        // A rotation is its own nearest rotation; a scaled, slightly sheared one comes back.
        assert!(nearest_rotation(r).abs_diff_eq(r, 1e-12));
        let m = r * 3.0 + DMat3::from_cols(DVec3::new(1e-3, 0.0, 0.0), DVec3::ZERO, DVec3::ZERO);
        let n = nearest_rotation(m);
        assert!(is_rotation(&n, 1e-12) && rotation_angle_deg(&(n.transpose() * r)) < 0.05);
        // A reflection maps to a proper rotation (det +1), never a mirror.
        let mirror = r * DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0));
        assert!(is_rotation(&nearest_rotation(mirror), 1e-12));
    }

    #[test]
    fn inverse_and_compose() {
        let a = Sim3 {
            scale: 2.5,
            rotation: axis_angle(DVec3::new(1.0, 2.0, 3.0), 0.7),
            translation: DVec3::new(1.0, -2.0, 0.5),
        };
        let p = DVec3::new(0.3, 0.1, -4.0);
        assert!((a.inverse().apply(a.apply(p)) - p).length() < 1e-12);
        let m = a.to_mat4();
        assert!((m.transform_point3(p) - a.apply(p)).length() < 1e-12);
        let b = Sim3::from_mat4(&m).unwrap();
        assert!((b.scale - 2.5).abs() < 1e-12 && a.rotation_angle_deg(&b) < 1e-6);
        let c = a.compose(&a.inverse());
        assert!((c.apply(p) - p).length() < 1e-12);
    }
}
