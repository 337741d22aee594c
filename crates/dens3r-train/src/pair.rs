//! Training pairs from scene folders: two frames cropped and resized to the network size, their
//! ground-truth pointmaps in view 1's camera frame, normals in the Dens3R raw convention, and
//! ground-truth correspondences from reprojecting depth through the poses with an occlusion
//! test.

use crate::loss::Matches;
use crate::TrainError;
use dens3r_geom::camera::{rigid_inverse, Intrinsics};
use dens3r_geom::pointmap::depth_valid;
use dens3r_geom::Raster;
use dens3r_scene::{Frame, Scene};
use glam::{DMat3, DMat4, DVec3, Vec3};
use image::RgbImage;
use std::path::Path;

/// One frame at network size: image, intrinsics, pose, depth and normals.
#[derive(Debug, Clone)]
pub struct View {
    /// Frame name.
    pub name: String,
    /// RGB at network size.
    pub image: RgbImage,
    /// Intrinsics at network size.
    pub k: Intrinsics,
    /// Camera-to-world pose (OpenCV frame).
    pub cam_to_world: DMat4,
    /// z-depth (0 = invalid).
    pub depth: Raster<f32>,
    /// Unit normals in the OpenCV camera frame facing the camera (zero = invalid).
    pub normals: Option<Raster<Vec3>>,
}

impl View {
    /// Reads frame `f` of `scene`, centre-cropped to the aspect of `(w, h)` and resized to it
    /// (depth and normals by nearest neighbour, so no value is invented at an edge). A frame
    /// without depth is an error naming its file and the fix.
    pub fn load(scene: &Scene, f: &Frame, (w, h): (usize, usize)) -> Result<Self, TrainError> {
        Self::load_window(scene, f, crop_window((f.width, f.height), (w, h), 1.0, (0.5, 0.5)), (w, h))
    }

    /// [`View::load`] of the window `(x0, y0, cw, ch)` (source pixels) resized to `(w, h)`.
    pub fn load_window(
        scene: &Scene,
        f: &Frame,
        (x0, y0, cw, ch): (usize, usize, usize, usize),
        (w, h): (usize, usize),
    ) -> Result<Self, TrainError> {
        let image = scene.image(f)?;
        let depth = scene.depth(f)?.ok_or_else(|| missing_depth(scene, f))?;
        let normals = scene.normals(f)?;
        let k = Intrinsics::from_rows(&f.k).ok_or_else(|| {
            TrainError::file(&scene.root().join("cameras.json"), format!("frame '{}' has no valid pinhole K", f.name))
        })?;
        let (fw, fh) = (f.width, f.height);
        if image.width() as usize != fw
            || image.height() as usize != fh
            || depth.width() != fw
            || depth.height() != fh
            || x0 + cw > fw
            || y0 + ch > fh
            || cw == 0
            || ch == 0
        {
            return Err(TrainError::file(scene.root(), format!("frame '{}': image or depth is not the {fw}x{fh} that cameras.json gives; re-render or fix the scene", f.name)));
        }
        let (sx, sy) = (w as f64 / cw as f64, h as f64 / ch as f64);
        let crop = image::imageops::crop_imm(&image, x0 as u32, y0 as u32, cw as u32, ch as u32).to_image();
        let image = image::imageops::resize(&crop, w as u32, h as u32, image::imageops::FilterType::Triangle);
        let src = |x: usize, y: usize| {
            let u = ((x as f64 + 0.5) / sx - 0.5).round().clamp(0.0, cw as f64 - 1.0) as usize + x0;
            let v = ((y as f64 + 0.5) / sy - 0.5).round().clamp(0.0, ch as f64 - 1.0) as usize + y0;
            (u, v)
        };
        let depth = Raster::from_fn(w, h, |x, y| {
            let (u, v) = src(x, y);
            let d = *depth.get(u, v);
            if depth_valid(d) {
                d
            } else {
                0.0
            }
        });
        let normals = normals.map(|n| {
            Raster::from_fn(w, h, |x, y| {
                let (u, v) = src(x, y);
                let v = *n.get(u, v);
                if v.is_finite() {
                    v
                } else {
                    Vec3::ZERO
                }
            })
        });
        let k = Intrinsics { cx: k.cx - x0 as f64, cy: k.cy - y0 as f64, ..k }.scaled(sx, sy);
        Ok(Self { name: f.name.clone(), image, k, cam_to_world: f.pose(), depth, normals })
    }

    /// The same view from the camera rolled 180 degrees about its optical axis: the image
    /// turned upside down, camera-frame x and y negated (so normals' too), the principal point
    /// mirrored, the pose turned so every pixel still sees the same world point.
    pub fn rotated_180(&self) -> Self {
        let (w, h) = (self.depth.width(), self.depth.height());
        let flip = |x: usize, y: usize| (w - 1 - x, h - 1 - y);
        let depth = Raster::from_fn(w, h, |x, y| {
            let (u, v) = flip(x, y);
            *self.depth.get(u, v)
        });
        let normals = self.normals.as_ref().map(|n| {
            Raster::from_fn(w, h, |x, y| {
                let (u, v) = flip(x, y);
                let n = *n.get(u, v);
                Vec3::new(-n.x, -n.y, n.z)
            })
        });
        let k = Intrinsics { cx: (w - 1) as f64 - self.k.cx, cy: (h - 1) as f64 - self.k.cy, ..self.k };
        let roll = DMat4::from_diagonal(glam::DVec4::new(-1.0, -1.0, 1.0, 1.0));
        Self {
            name: self.name.clone(),
            image: image::imageops::rotate180(&self.image),
            k,
            cam_to_world: self.cam_to_world * roll,
            depth,
            normals,
        }
    }

    /// Whether the camera looks down within `max_deg` of straight down (world z up, as
    /// `dens3r synth` and `render` place scenes): a view with no upright in its image.
    pub fn looks_down(&self, max_deg: f64) -> bool {
        let axis = self.cam_to_world.z_axis.truncate().normalize();
        -axis.z >= max_deg.to_radians().cos()
    }

    /// Camera-frame point of pixel `(x, y)`, if its depth is valid.
    pub fn point(&self, x: usize, y: usize) -> Option<DVec3> {
        let d = *self.depth.get(x, y);
        depth_valid(d).then(|| self.k.unproject(x as f64, y as f64) * d as f64)
    }
}

/// The error for a frame without depth.
pub fn missing_depth(scene: &Scene, f: &Frame) -> TrainError {
    TrainError::file(
        scene.root(),
        format!(
            "frame '{}' has no depth/{}.npy; training needs depth and poses (render or synthesise the scene with `dens3r render` / `dens3r synth`)",
            f.name, f.name
        ),
    )
}

/// A window of a `(fw, fh)` frame with the aspect of `(w, h)`: the largest such window scaled
/// by `scale` (0..1], placed at `at` (each 0..1: left / top to right / bottom of the room
/// left). Returns `(x0, y0, cw, ch)` in source pixels.
pub fn crop_window(
    (fw, fh): (usize, usize),
    (w, h): (usize, usize),
    scale: f64,
    at: (f64, f64),
) -> (usize, usize, usize, usize) {
    let (cw, ch) = if fw * h > fh * w { (fh * w / h, fh) } else { (fw, fw * h / w) };
    let s = scale.clamp(0.05, 1.0);
    let (cw, ch) = (((cw as f64 * s).round() as usize).clamp(1, fw), ((ch as f64 * s).round() as usize).clamp(1, fh));
    let x0 = ((fw - cw) as f64 * at.0.clamp(0.0, 1.0)).floor() as usize;
    let y0 = ((fh - ch) as f64 * at.1.clamp(0.0, 1.0)).floor() as usize;
    (x0.min(fw - cw), y0.min(fh - ch), cw, ch)
}

/// Dens3R's raw normal convention of an OpenCV normal: `(x, -y, z)`.
pub fn raw_normal(n: Vec3) -> Vec3 {
    Vec3::new(n.x, -n.y, n.z)
}

/// The ground truth of a pair at network size, row-major `(H, W)` per view.
#[derive(Debug, Clone)]
pub struct PairTarget {
    /// `(H, W)`.
    pub size: (usize, usize),
    /// Points in view 1's camera frame (view 2 transformed), zero where invalid.
    pub pts: [Vec<Vec3>; 2],
    /// Points of each view in its own camera frame.
    pub pts_own: [Vec<Vec3>; 2],
    /// Valid ground truth.
    pub valid: [Vec<bool>; 2],
    /// Raw-convention normals of each view in its own frame (zero where invalid or absent).
    pub normals: [Vec<Vec3>; 2],
    /// Raw-convention normals of view 1, and of view 2 rotated into view 1's frame
    /// (`normalmap_transformed`: `diag(1,-1,1) R_12 diag(1,-1,1)` of view 2's raw normals).
    pub normals_in1: [Vec<Vec3>; 2],
    /// Ground-truth correspondences (one to one).
    pub matches: Matches,
}

/// Relative depth tolerance of the occlusion test: a reprojected point matches a pixel whose
/// depth agrees within this fraction.
pub const OCCLUSION_TOL: f64 = 0.01;

/// Ground-truth correspondences of two views: every valid pixel of view 1 whose point,
/// moved into camera 2 and projected, lands inside view 2 on a pixel whose depth agrees within
/// [`OCCLUSION_TOL`] (so it is seen, not hidden), and whose own point projects back to within
/// one pixel of the start (reciprocal); each view-2 pixel is used once.
pub fn correspondences(v1: &View, v2: &View) -> Matches {
    let (w1, h1) = (v1.depth.width(), v1.depth.height());
    let (w2, h2) = (v2.depth.width(), v2.depth.height());
    let t21 = rigid_inverse(&v2.cam_to_world) * v1.cam_to_world;
    let t12 = rigid_inverse(&v1.cam_to_world) * v2.cam_to_world;
    let mut used = vec![false; w2 * h2];
    let mut m = Matches::default();
    for y in 0..h1 {
        for x in 0..w1 {
            let Some(p) = v1.point(x, y) else { continue };
            let q = t21.transform_point3(p);
            if q.z <= 0.0 {
                continue;
            }
            let (u, v) = v2.k.project(q);
            let (xu, yv) = (u.round(), v.round());
            if xu < 0.0 || yv < 0.0 || xu >= w2 as f64 || yv >= h2 as f64 {
                continue;
            }
            let (x2, y2) = (xu as usize, yv as usize);
            let Some(p2) = v2.point(x2, y2) else { continue };
            if (p2.z - q.z).abs() > OCCLUSION_TOL * q.z {
                continue;
            }
            let back = t12.transform_point3(p2);
            let (bu, bv) = v1.k.project(back);
            if back.z <= 0.0 || (bu - x as f64).abs() > 1.0 || (bv - y as f64).abs() > 1.0 {
                continue;
            }
            if std::mem::replace(&mut used[y2 * w2 + x2], true) {
                continue;
            }
            m.idx1.push((y * w1 + x) as u32);
            m.idx2.push((y2 * w2 + x2) as u32);
        }
    }
    m
}

/// The fraction of view 1's valid pixels that reproject, unoccluded, into view 2
/// (co-visibility, as used to draw training pairs).
pub fn covisibility(v1: &View, v2: &View) -> f64 {
    let valid = v1.depth.data().iter().filter(|d| depth_valid(**d)).count();
    if valid == 0 {
        return 0.0;
    }
    correspondences(v1, v2).idx1.len() as f64 / valid as f64
}

/// The ground truth of the pair `(v1, v2)`.
pub fn pair_target(v1: &View, v2: &View) -> PairTarget {
    let (w, h) = (v1.depth.width(), v1.depth.height());
    let t12 = rigid_inverse(&v1.cam_to_world) * v2.cam_to_world;
    let r12 = DMat3::from_mat4(t12);
    let own = |v: &View| -> (Vec<Vec3>, Vec<bool>) {
        let mut pts = Vec::with_capacity(w * h);
        let mut valid = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let p = v.point(x, y);
                valid.push(p.is_some());
                pts.push(p.map_or(Vec3::ZERO, |p| p.as_vec3()));
            }
        }
        (pts, valid)
    };
    let (p1, m1) = own(v1);
    let (p2, m2) = own(v2);
    let p2_in1: Vec<Vec3> = p2
        .iter()
        .zip(&m2)
        .map(|(p, &ok)| if ok { t12.transform_point3(p.as_dvec3()).as_vec3() } else { Vec3::ZERO })
        .collect();
    let normals = |v: &View, valid: &[bool]| -> Vec<Vec3> {
        match &v.normals {
            Some(n) => {
                n.data().iter().zip(valid).map(|(n, &ok)| if ok { raw_normal(*n) } else { Vec3::ZERO }).collect()
            }
            None => vec![Vec3::ZERO; w * h],
        }
    };
    let (n1, n2) = (normals(v1, &m1), normals(v2, &m2));
    // diag(1,-1,1) R diag(1,-1,1) applied to a raw normal = raw(R n_opencv).
    let n2_in1: Vec<Vec3> = n2
        .iter()
        .map(|n| if *n == Vec3::ZERO { *n } else { raw_normal((r12 * raw_normal(*n).as_dvec3()).as_vec3()) })
        .collect();
    PairTarget {
        size: (h, w),
        pts: [p1.clone(), p2_in1],
        pts_own: [p1, p2],
        valid: [m1, m2],
        normals_in1: [n1.clone(), n2_in1],
        normals: [n1, n2],
        matches: correspondences(v1, v2),
    }
}

/// The frames of a scene folder at network size `(w, h)`.
pub fn load_views(dir: &Path, size: (usize, usize)) -> Result<Vec<View>, TrainError> {
    let scene = Scene::open(dir)?;
    scene.frames().iter().map(|f| View::load(&scene, f, size)).collect()
}
