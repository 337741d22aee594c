//! The object list and the ray caster.

use crate::material::Material;
use dens3r_geom::{PinholeCamera, Raster};
use dens3r_mesh::primitives::{cuboid, uv_sphere};
use dens3r_mesh::TriMesh;
use glam::{Quat, Vec3};
use image::RgbImage;
use parry3d::query::{Ray, RayCast};
use parry3d::shape::{Ball, Cuboid};
use rayon::prelude::*;
use std::sync::Arc;

/// Geometry of an object, in its own frame.
#[derive(Debug, Clone)]
pub enum Shape {
    /// Analytic sphere centred at the origin.
    Sphere {
        /// Radius.
        radius: f32,
    },
    /// Analytic box centred at the origin.
    Cuboid {
        /// Half extents.
        half: Vec3,
    },
    /// Triangle mesh.
    Mesh(Arc<TriMesh>),
}

/// One object of a [`World`]; its instance id is its index + 1 (0 = background).
#[derive(Debug, Clone)]
pub struct Object {
    /// Human-readable name.
    pub name: String,
    /// Geometry in the object frame.
    pub shape: Shape,
    /// Object-to-world rotation.
    pub rotation: Quat,
    /// Object-to-world translation.
    pub translation: Vec3,
    /// Semantic class id (0 = background).
    pub class_id: u16,
    /// Appearance.
    pub material: Material,
}

enum Caster {
    Ball(Ball),
    Cuboid(Cuboid),
    Mesh(Box<parry3d::shape::TriMesh>),
}

struct Part {
    caster: Caster,
    inv_rotation: Quat,
    lo: Vec3,
    hi: Vec3,
}

/// Everything one camera sees.
#[derive(Debug, Clone)]
pub struct RenderedView {
    /// Shaded, textured colour (background light grey).
    pub rgb: RgbImage,
    /// z-depth; 0 where no object is hit.
    pub depth: Raster<f32>,
    /// Unit normals in the OpenCV camera frame, facing the camera; zero on background.
    pub normals: Raster<Vec3>,
    /// Semantic class ids; 0 on background.
    pub labels: Raster<u16>,
    /// Instance ids (object index + 1); 0 on background.
    pub instances: Raster<u16>,
}

/// A renderable set of objects with a directional light.
pub struct World {
    objects: Vec<Object>,
    parts: Vec<Part>,
    /// Unit direction *towards* the light, world frame.
    pub light: Vec3,
    /// Ambient light fraction, 0..1.
    pub ambient: f32,
    /// Strength of a Blinn-Phong highlight (0 = matte, the default).
    pub specular: f32,
    /// Blinn-Phong exponent of the highlight.
    pub shininess: f32,
    /// Colour where no object is hit (its depth is invalid).
    pub background: [u8; 3],
}

/// A world that cannot be rendered (no objects, too many, a broken mesh or a non-positive
/// size), saying which object.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct WorldError(pub String);

impl World {
    /// Builds acceleration structures; fails on an empty world or a broken mesh.
    pub fn new(objects: Vec<Object>) -> Result<Self, WorldError> {
        if objects.is_empty() {
            return Err(WorldError("the scene has no objects".into()));
        }
        if objects.len() >= u16::MAX as usize {
            return Err(WorldError("too many objects for 16-bit instance ids".into()));
        }
        let parts = objects
            .iter()
            .map(|o| {
                let caster = match &o.shape {
                    Shape::Sphere { radius } if *radius > 0.0 => Caster::Ball(Ball::new(*radius)),
                    Shape::Cuboid { half } if half.min_element() > 0.0 => Caster::Cuboid(Cuboid::new(*half)),
                    Shape::Mesh(m) => {
                        Caster::Mesh(Box::new(m.to_parry().map_err(|e| format!("object '{}': {e}", o.name))?))
                    }
                    _ => return Err(format!("object '{}' has a non-positive size", o.name)),
                };
                let (lo, hi) = world_bounds(o);
                Ok(Part { caster, inv_rotation: o.rotation.inverse(), lo, hi })
            })
            .collect::<Result<Vec<_>, String>>()
            .map_err(WorldError)?;
        Ok(Self {
            objects,
            parts,
            light: Vec3::new(0.4, -0.3, 0.85).normalize(),
            ambient: 0.3,
            specular: 0.0,
            shininess: 32.0,
            background: BACKGROUND,
        })
    }

    /// The objects.
    pub fn objects(&self) -> &[Object] {
        &self.objects
    }

    /// World-space bounds of all objects.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.parts.iter().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| (lo.min(p.lo), hi.max(p.hi)))
    }

    /// The whole world as one triangle mesh in world coordinates (spheres tessellated with
    /// 64 x 128 facets, within 3e-4 of the radius; vertex colours = base colours): the
    /// ground truth for mesh metrics.
    pub fn gt_mesh(&self) -> TriMesh {
        let mut out = TriMesh::default();
        for o in &self.objects {
            let mut m = match &o.shape {
                Shape::Sphere { radius } => uv_sphere(*radius, 64, 128),
                Shape::Cuboid { half } => cuboid(*half),
                Shape::Mesh(m) => {
                    let mut m = (**m).clone();
                    if m.normals.is_none() {
                        m.compute_vertex_normals();
                    }
                    m
                }
            };
            m.transform(&glam::Mat4::from_rotation_translation(o.rotation, o.translation));
            let c = o.material.color.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8);
            m.colors = Some(vec![c; m.positions.len()]);
            out.append(&m);
        }
        out
    }

    /// First hit along a world ray: `(t, object index, world normal facing the ray)`.
    pub fn cast(&self, origin: Vec3, dir: Vec3, max_t: f32) -> Option<(f32, usize, Vec3)> {
        let inv = dir.recip();
        let mut best: Option<(f32, usize, Vec3)> = None;
        for (k, part) in self.parts.iter().enumerate() {
            let limit = best.map_or(max_t, |b| b.0);
            if !slab_hit(origin, inv, part.lo, part.hi, limit) {
                continue;
            }
            let o = &self.objects[k];
            let local = Ray::new(part.inv_rotation * (origin - o.translation), part.inv_rotation * dir);
            let hit = match &part.caster {
                Caster::Ball(s) => s.cast_local_ray_and_get_normal(&local, limit, false),
                Caster::Cuboid(s) => s.cast_local_ray_and_get_normal(&local, limit, false),
                Caster::Mesh(s) => s.cast_local_ray_and_get_normal(&local, limit, false),
            };
            if let Some(h) = hit {
                if h.time_of_impact > 0.0 && h.time_of_impact < limit {
                    let mut n = (o.rotation * h.normal).normalize_or_zero();
                    if n.dot(dir) > 0.0 {
                        n = -n;
                    }
                    best = Some((h.time_of_impact, k, n));
                }
            }
        }
        best
    }

    /// Renders one camera.
    pub fn render(&self, cam: &PinholeCamera) -> RenderedView {
        let (w, h) = (cam.width, cam.height);
        let r_c2w = glam::DMat3::from_mat4(cam.cam_to_world);
        let origin = cam.center().as_vec3();
        let px: Vec<Sample> = (0..w * h)
            .into_par_iter()
            .with_min_len(w)
            .map(|i| {
                let d_cam = cam.intrinsics.unproject((i % w) as f64, (i / w) as f64).normalize();
                let dir = (r_c2w * d_cam).as_vec3();
                match self.cast(origin, dir, f32::MAX) {
                    Some((t, k, n_world)) => Sample {
                        depth: (t as f64 * d_cam.z) as f32,
                        normal: (r_c2w.transpose() * n_world.as_dvec3()).as_vec3().normalize(),
                        label: self.objects[k].class_id,
                        instance: k as u16 + 1,
                        rgb: self.shade(k, origin + dir * t, n_world, dir),
                    },
                    None => Sample { depth: 0.0, normal: Vec3::ZERO, label: 0, instance: 0, rgb: self.background },
                }
            })
            .collect();
        let rgb = RgbImage::from_raw(w as u32, h as u32, px.iter().flat_map(|p| p.rgb).collect()).expect("w*h*3 bytes");
        fn raster<T>(w: usize, h: usize, px: &[Sample], f: impl Fn(&Sample) -> T) -> Raster<T> {
            Raster::from_vec(w, h, px.iter().map(f).collect()).expect("w*h values")
        }
        RenderedView {
            rgb,
            depth: raster(w, h, &px, |p| p.depth),
            normals: raster(w, h, &px, |p| p.normal),
            labels: raster(w, h, &px, |p| p.label),
            instances: raster(w, h, &px, |p| p.instance),
        }
    }

    fn shade(&self, k: usize, p: Vec3, n: Vec3, view: Vec3) -> [u8; 3] {
        let o = &self.objects[k];
        let inv = self.parts[k].inv_rotation;
        let albedo = o.material.albedo(inv * (p - o.translation), inv * n);
        let diffuse = n.dot(self.light).max(0.0);
        let head = (-n.dot(view)).max(0.0);
        let light = self.ambient + (1.0 - self.ambient) * (0.75 * diffuse + 0.25 * head);
        let highlight = if self.specular > 0.0 && diffuse > 0.0 {
            self.specular * n.dot((self.light - view).normalize_or_zero()).max(0.0).powf(self.shininess)
        } else {
            0.0
        };
        // Linear to sRGB-ish display values.
        albedo.map(|a| ((a * light + highlight).clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0).round() as u8)
    }
}

/// Background colour (light grey).
const BACKGROUND: [u8; 3] = [200, 205, 210];

/// What one pixel sees.
struct Sample {
    depth: f32,
    normal: Vec3,
    label: u16,
    instance: u16,
    rgb: [u8; 3],
}

fn world_bounds(o: &Object) -> (Vec3, Vec3) {
    let corners: Vec<Vec3> = match &o.shape {
        Shape::Sphere { radius } => {
            return (o.translation - Vec3::splat(*radius), o.translation + Vec3::splat(*radius))
        }
        Shape::Cuboid { half } => (0..8)
            .map(|i| {
                Vec3::new(
                    if i & 1 == 0 { -half.x } else { half.x },
                    if i & 2 == 0 { -half.y } else { half.y },
                    if i & 4 == 0 { -half.z } else { half.z },
                )
            })
            .collect(),
        Shape::Mesh(m) => m.positions.clone(),
    };
    corners
        .iter()
        .map(|c| o.rotation * *c + o.translation)
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| (lo.min(p), hi.max(p)))
}

/// Ray / axis-aligned box overlap within `[0, max_t]` (slab test, slightly padded).
fn slab_hit(o: Vec3, inv: Vec3, lo: Vec3, hi: Vec3, max_t: f32) -> bool {
    let pad = Vec3::splat(1e-4);
    let t1 = (lo - pad - o) * inv;
    let t2 = (hi + pad - o) * inv;
    let tmin = t1.min(t2).max_element().max(0.0);
    let tmax = t1.max(t2).min_element().min(max_t);
    // NaN (ray parallel to a slab and on its plane) counts as a hit: parry decides.
    tmin <= tmax || tmin.is_nan() || tmax.is_nan()
}
