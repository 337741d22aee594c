//! OpenCV pinhole cameras with camera-to-world poses.

use glam::{DMat3, DMat4, DVec3, DVec4};

/// Pinhole intrinsics in pixels (OpenCV: pixel centres at integer coordinates).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// Intrinsics for a horizontal field of view (degrees) with the principal point at
    /// `(width / 2, height / 2)`, the DUSt3R / Dens3R convention.
    pub fn from_hfov(width: usize, height: usize, hfov_deg: f64) -> Self {
        let f = width as f64 / 2.0 / (hfov_deg.to_radians() / 2.0).tan();
        Self { fx: f, fy: f, cx: width as f64 / 2.0, cy: height as f64 / 2.0 }
    }

    /// The 3x3 matrix `K` as row-major nested arrays.
    pub fn to_rows(&self) -> [[f64; 3]; 3] {
        [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
    }

    /// Reads `K` from row-major nested arrays; `None` unless it is a finite pinhole matrix
    /// with positive focals, zero skew and last row `[0, 0, 1]`.
    pub fn from_rows(k: &[[f64; 3]; 3]) -> Option<Self> {
        let ok = k.iter().flatten().all(|v| v.is_finite())
            && k[0][0] > 0.0
            && k[1][1] > 0.0
            && k[0][1].abs() < 1e-9
            && k[1][0].abs() < 1e-9
            && k[2] == [0.0, 0.0, 1.0];
        ok.then_some(Self { fx: k[0][0], fy: k[1][1], cx: k[0][2], cy: k[1][2] })
    }

    /// Camera-frame direction through pixel `(u, v)`, with `z = 1` (not normalised).
    #[inline]
    pub fn unproject(&self, u: f64, v: f64) -> DVec3 {
        DVec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// Pixel `(u, v)` of a camera-frame point (any z > 0).
    #[inline]
    pub fn project(&self, p: DVec3) -> (f64, f64) {
        (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }

    /// Scales the intrinsics for an image resized by `sx`, `sy` (pixel-centre aware).
    pub fn scaled(&self, sx: f64, sy: f64) -> Self {
        Self { fx: self.fx * sx, fy: self.fy * sy, cx: (self.cx + 0.5) * sx - 0.5, cy: (self.cy + 0.5) * sy - 0.5 }
    }
}

/// A camera: intrinsics, image size and camera-to-world pose (OpenCV camera frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinholeCamera {
    /// Intrinsics in pixels.
    pub intrinsics: Intrinsics,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Camera-to-world rigid transform.
    pub cam_to_world: DMat4,
}

impl PinholeCamera {
    /// Camera centre in world coordinates.
    pub fn center(&self) -> DVec3 {
        self.cam_to_world.w_axis.truncate()
    }

    /// World-to-camera transform (the inverse of the rigid pose).
    pub fn world_to_cam(&self) -> DMat4 {
        rigid_inverse(&self.cam_to_world)
    }

    /// Unit world-space ray direction through pixel `(u, v)`.
    pub fn world_ray(&self, u: f64, v: f64) -> DVec3 {
        self.cam_to_world.transform_vector3(self.intrinsics.unproject(u, v)).normalize()
    }
}

/// A point triangulated from several views ([`triangulate`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulated {
    /// World position.
    pub xyz: DVec3,
    /// Largest angle between two of its rays, degrees (small angles leave the depth uncertain).
    pub max_angle_deg: f64,
    /// Mean reprojection error over its views, pixels.
    pub error_px: f64,
}

/// The point nearest (in least squares) to the rays through pixel `(u, v)` of each camera:
/// the multi-view midpoint. `None` for fewer than two views, rays too close to parallel to
/// cross (under 0.01 degrees apart), or a point behind any of the cameras.
pub fn triangulate(views: &[(PinholeCamera, (f64, f64))]) -> Option<Triangulated> {
    if views.len() < 2 {
        return None;
    }
    let rays: Vec<(DVec3, DVec3)> = views.iter().map(|(c, (u, v))| (c.center(), c.world_ray(*u, *v))).collect();
    let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
    for &(c, d) in &rays {
        let p = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * c;
    }
    let mut max_cos = 1.0f64;
    for (i, &(_, di)) in rays.iter().enumerate() {
        for &(_, dj) in &rays[i + 1..] {
            max_cos = max_cos.min(di.dot(dj));
        }
    }
    let max_angle_deg = max_cos.clamp(-1.0, 1.0).acos().to_degrees();
    if max_angle_deg < 0.01 || a.determinant().abs() < 1e-12 {
        return None;
    }
    let xyz = a.inverse() * b;
    let mut err = 0.0;
    for (c, (u, v)) in views {
        let q = c.world_to_cam().transform_point3(xyz);
        if q.z <= 0.0 {
            return None;
        }
        let (pu, pv) = c.intrinsics.project(q);
        err += (pu - u).hypot(pv - v);
    }
    xyz.is_finite().then_some(Triangulated { xyz, max_angle_deg, error_px: err / views.len() as f64 })
}

/// Inverse of a rigid 4x4 transform (rotation transposed), exact for orthonormal rotations.
pub fn rigid_inverse(m: &DMat4) -> DMat4 {
    let r = DMat3::from_mat4(*m);
    let rt = r.transpose();
    let t = m.w_axis.truncate();
    let ti = -(rt * t);
    DMat4::from_cols(
        rt.x_axis.extend(0.0),
        rt.y_axis.extend(0.0),
        rt.z_axis.extend(0.0),
        DVec4::new(ti.x, ti.y, ti.z, 1.0),
    )
}

/// OpenCV camera-to-world pose at `eye` looking at `target`; `up` is the world's up
/// direction (the camera's y axis points away from it). Returns `None` when `eye == target`
/// or the view direction is parallel to `up`.
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> Option<DMat4> {
    let z = (target - eye).try_normalize()?;
    let x = z.cross(up).try_normalize()?;
    let y = z.cross(x);
    Some(DMat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), eye.extend(1.0)))
}

/// Converts an OpenCV camera-to-world pose to the OpenGL / Blender / nerfstudio one
/// (camera x right, y up, looking down -z). The map is its own inverse.
pub fn opencv_to_opengl_pose(c2w: &DMat4) -> DMat4 {
    *c2w * DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0))
}

/// Row-major nested arrays of a 4x4 matrix (the scene-folder layout).
pub fn mat4_to_rows(m: &DMat4) -> [[f64; 4]; 4] {
    let c = m.to_cols_array_2d();
    std::array::from_fn(|r| std::array::from_fn(|k| c[k][r]))
}

/// 4x4 matrix from row-major nested arrays.
pub fn mat4_from_rows(rows: &[[f64; 4]; 4]) -> DMat4 {
    DMat4::from_cols_array_2d(&std::array::from_fn(|k| std::array::from_fn(|r| rows[r][k])))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_is_opencv() {
        // Looking along +x with z up: the camera's right is -y, its down is -z.
        let m = look_at(DVec3::ZERO, DVec3::X, DVec3::Z).unwrap();
        assert!((m.x_axis.truncate() - DVec3::NEG_Y).length() < 1e-12);
        assert!((m.y_axis.truncate() - DVec3::NEG_Z).length() < 1e-12);
        assert!((m.z_axis.truncate() - DVec3::X).length() < 1e-12);
        assert!(look_at(DVec3::ZERO, DVec3::Z, DVec3::Z).is_none());
    }

    #[test]
    fn rows_round_trip_and_inverse() {
        let m = look_at(DVec3::new(1.0, 2.0, 3.0), DVec3::new(-1.0, 0.5, 0.0), DVec3::Z).unwrap();
        let rows = mat4_to_rows(&m);
        assert_eq!(rows[0][3], 1.0);
        assert_eq!(rows[3], [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(mat4_from_rows(&rows), m);
        let id = m * rigid_inverse(&m);
        assert!(id.abs_diff_eq(DMat4::IDENTITY, 1e-12));
    }

    #[test]
    fn project_unproject() {
        let k = Intrinsics::from_hfov(640, 480, 60.0);
        let p = k.unproject(100.0, 300.0) * 2.5;
        let (u, v) = k.project(p);
        assert!((u - 100.0).abs() < 1e-9 && (v - 300.0).abs() < 1e-9);
        assert_eq!(Intrinsics::from_rows(&k.to_rows()), Some(k));
    }

    /// Three cameras 0.4 apart looking at a point 2 away: the rays through its projections
    /// (rounded to 0.1 px) meet within a millimetre of it, at the angle the geometry gives; a
    /// point behind a camera or a single view gives none.
    #[test]
    fn triangulate_meets_the_rays_at_the_point() {
        let k = Intrinsics::from_hfov(640, 480, 60.0);
        let cam = |x: f64| PinholeCamera {
            intrinsics: k,
            width: 640,
            height: 480,
            cam_to_world: look_at(DVec3::new(x, 0.0, 0.0), DVec3::new(0.0, 0.0, 2.0), DVec3::NEG_Y).unwrap(),
        };
        let p = DVec3::new(0.1, -0.2, 2.1);
        let obs = |c: PinholeCamera, p: DVec3| {
            let (u, v) = k.project(c.world_to_cam().transform_point3(p));
            (c, ((u * 10.0).round() / 10.0, (v * 10.0).round() / 10.0))
        };
        let views: Vec<_> = [-0.4, 0.0, 0.4].into_iter().map(|x| obs(cam(x), p)).collect();
        let t = triangulate(&views).unwrap();
        assert!((t.xyz - p).length() < 1e-3, "{:?}", t.xyz);
        let angle = (DVec3::new(-0.4, 0.0, 0.0) - p).angle_between(DVec3::new(0.4, 0.0, 0.0) - p).to_degrees();
        assert!((t.max_angle_deg - angle).abs() < 0.05, "{} vs {angle}", t.max_angle_deg);
        assert!(t.error_px < 0.1, "{}", t.error_px);
        assert!(triangulate(&views[..1]).is_none());
        // The same pixels seen by a camera turned away: the rays cross behind it.
        let behind = PinholeCamera {
            cam_to_world: look_at(DVec3::new(0.4, 0.0, 0.0), DVec3::new(0.8, 0.0, -2.0), DVec3::NEG_Y).unwrap(),
            ..cam(0.4)
        };
        assert!(triangulate(&[views[0], (behind, views[2].1)]).is_none());
    }
}
