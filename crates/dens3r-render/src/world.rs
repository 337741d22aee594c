//! The object list and the ray caster.

use crate::material::Material;
use dens3r_geom::{PinholeCamera, Raster};
use dens3r_mesh::primitives::{cuboid, uv_sphere};
use dens3r_mesh::TriMesh;
use glam::{Quat, Vec3};
use image::RgbImage;
use parry3d::query::{Ray, RayCast, RayIntersection};
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

/// An object's shape in its own frame. An enum, not a `dyn RayCast`: the analytic shapes'
/// casts inline (a trait object made plain rendering ~9% slower).
enum Caster {
    Ball(Ball),
    Cuboid(Cuboid),
    Mesh(Box<parry3d::shape::TriMesh>),
}

impl Caster {
    /// First hit within `max_t` with the shape's normal there (parry's `solid = false`).
    fn hit(&self, ray: &Ray, max_t: f32) -> Option<RayIntersection> {
        match self {
            Caster::Ball(s) => s.cast_local_ray_and_get_normal(ray, max_t, false),
            Caster::Cuboid(s) => s.cast_local_ray_and_get_normal(ray, max_t, false),
            Caster::Mesh(s) => s.cast_local_ray_and_get_normal(ray, max_t, false),
        }
    }

    /// Time of the first hit within `max_t`, without the normal.
    fn toi(&self, ray: &Ray, max_t: f32) -> Option<f32> {
        match self {
            Caster::Ball(s) => s.cast_local_ray(ray, max_t, false),
            Caster::Cuboid(s) => s.cast_local_ray(ray, max_t, false),
            Caster::Mesh(s) => s.cast_local_ray(ray, max_t, false),
        }
    }
}

struct Part {
    caster: Caster,
    inv_rotation: Quat,
    lo: Vec3,
    hi: Vec3,
    /// Whether it casts shadows of the light.
    casts_shadow: bool,
}

impl Part {
    /// A world ray in the frame of `o`, this part's object.
    fn local_ray(&self, o: &Object, origin: Vec3, dir: Vec3) -> Ray {
        Ray::new(self.inv_rotation * (origin - o.translation), self.inv_rotation * dir)
    }
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
    /// Cast shadows and ambient occlusion; off by default.
    pub occlusion: Occlusion,
}

/// Light blocked by other geometry, which local shading alone lacks and photographs show:
/// shadows of the directional light and darkened creases and contacts (ambient occlusion).
/// The default, everything off, renders exactly as before these existed.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Occlusion {
    /// Points the light cannot reach (a ray towards it hits an object that casts shadows, see
    /// [`World::set_casts_shadow`]) keep only the ambient and camera-side terms.
    pub shadows: bool,
    /// Ambient occlusion rays per pixel (0 = off): the ambient and camera-side terms are
    /// scaled by the fraction of cosine-weighted hemisphere rays that hit nothing within
    /// `ao_radius`.
    pub ao_rays: u32,
    /// Reach of the ambient occlusion rays, world units.
    pub ao_radius: f32,
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
                Ok(Part { caster, inv_rotation: o.rotation.inverse(), lo, hi, casts_shadow: true })
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
            occlusion: Occlusion::default(),
        })
    }

    /// Whether object `k` casts shadows of the light (default: yes). An enclosure (a room's
    /// ceiling and walls) usually should not: the light stands for one inside it. Panics
    /// when `k` is not an object's index.
    pub fn set_casts_shadow(&mut self, k: usize, casts: bool) {
        self.parts[k].casts_shadow = casts;
    }

    /// Replaces object `k`'s material (its shape and place stay). Panics when `k` is not an
    /// object's index.
    pub fn set_material(&mut self, k: usize, material: Material) {
        self.objects[k].material = material;
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
            let hit = part.caster.hit(&part.local_ray(o, origin, dir), limit);
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

    /// Whether a ray hits, within `(min_t, max_t)`, any part with `keep(part)`.
    fn any_hit(&self, origin: Vec3, dir: Vec3, (min_t, max_t): (f32, f32), keep: impl Fn(&Part) -> bool) -> bool {
        let inv = dir.recip();
        self.parts.iter().zip(&self.objects).any(|(part, o)| {
            keep(part)
                && slab_hit(origin, inv, part.lo, part.hi, max_t)
                && part.caster.toi(&part.local_ray(o, origin, dir), max_t).is_some_and(|t| t > min_t && t < max_t)
        })
    }

    /// `(light visibility, ambient visibility)` at surface point `p` with normal `n` (facing
    /// the viewer), both 1 when [`Occlusion`] is off.
    fn occlusion_at(&self, p: Vec3, n: Vec3, diffuse: f32) -> (f32, f32) {
        let occ = self.occlusion;
        // Off the surface by a little more than f32 rounding at this distance.
        let eps = 1e-4 * (1.0 + p.abs().max_element());
        let start = p + n * eps;
        let blocked =
            occ.shadows && diffuse > 0.0 && self.any_hit(start, self.light, (eps, f32::MAX), |part| part.casts_shadow);
        let lit = if blocked { 0.0 } else { 1.0 };
        let ambient = if occ.ao_rays > 0 && occ.ao_radius > 0.0 {
            // Stratified cosine-weighted directions on a golden-angle spiral, turned by an angle
            // hashed from the point's cell: one surface point gets the same rays in every view.
            let cell = (p / (occ.ao_radius * 0.125)).floor().as_ivec3();
            let turn = crate::material::hash(cell.x, cell.y, cell.z, 0) * std::f32::consts::TAU;
            let (t1, t2) = n.any_orthonormal_pair();
            let rays = occ.ao_rays;
            let open = (0..rays)
                .filter(|&i| {
                    let u = (i as f32 + 0.5) / rays as f32;
                    let phi = turn + i as f32 * 2.399_963;
                    let r = u.sqrt();
                    let d = t1 * (r * phi.cos()) + t2 * (r * phi.sin()) + n * (1.0 - u).sqrt();
                    !self.any_hit(start, d, (eps, occ.ao_radius), |_| true)
                })
                .count();
            open as f32 / rays as f32
        } else {
            1.0
        };
        (lit, ambient)
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
        let (lit, open) = self.occlusion_at(p, n, diffuse);
        let diffuse = diffuse * lit;
        let light = self.ambient * open + (1.0 - self.ambient) * (0.75 * diffuse + 0.25 * head * open);
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

/// An object's axis-aligned bounds in the world.
pub(crate) fn world_bounds(o: &Object) -> (Vec3, Vec3) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_mesh::primitives::quad;

    fn object(name: &str, shape: Shape, translation: Vec3) -> Object {
        Object {
            name: name.into(),
            shape,
            rotation: Quat::IDENTITY,
            translation,
            class_id: 1,
            material: Material { color: [0.5; 3], texture: crate::material::Texture::Plain, seed: 0 },
        }
    }

    /// A floor z = 0 over [-5, 5]^2 and a wall x = 0 facing -x, up to z = 5.
    fn corner() -> World {
        let floor = quad(Vec3::new(-5.0, -5.0, 0.0), Vec3::Y * 10.0, Vec3::X * 10.0);
        let wall = quad(Vec3::new(0.0, -5.0, 0.0), Vec3::Z * 5.0, Vec3::Y * 10.0);
        World::new(vec![
            object("floor", Shape::Mesh(Arc::new(floor)), Vec3::ZERO),
            object("wall_0", Shape::Mesh(Arc::new(wall)), Vec3::ZERO),
        ])
        .unwrap()
    }

    #[test]
    fn ambient_occlusion_near_a_wall_matches_the_analytic_fraction() {
        // Cosine-weighted directions project uniformly onto the unit disk, so a ray from the
        // floor at distance d from the wall reaches it within R iff its disk x exceeds d / R:
        // the blocked fraction is the disk segment beyond a = d / R, (acos a - a sqrt(1 - a^2)) / pi.
        let mut w = corner();
        let radius = 0.5;
        w.occlusion = Occlusion { shadows: false, ao_rays: 8, ao_radius: radius };
        for d in [0.01f32, 0.1, 0.25, 0.4] {
            let a = d / radius;
            let want = 1.0 - (a.acos() - a * (1.0 - a * a).sqrt()) / std::f32::consts::PI;
            // Mean over 400 points along the wall: each cell turns the ray pattern differently.
            let n = 400;
            let mean = (0..n)
                .map(|i| w.occlusion_at(Vec3::new(-d, -4.0 + 8.0 * i as f32 / n as f32, 0.0), Vec3::Z, 1.0).1)
                .sum::<f32>()
                / n as f32;
            assert!((mean - want).abs() < 0.03, "d = {d}: open fraction {mean}, analytic {want}");
        }
        // Beyond the reach nothing is occluded, exactly.
        assert_eq!(w.occlusion_at(Vec3::new(-0.6, 0.0, 0.0), Vec3::Z, 1.0), (1.0, 1.0));
        // Off, everything is open.
        w.occlusion = Occlusion::default();
        assert_eq!(w.occlusion_at(Vec3::new(-0.01, 0.0, 0.0), Vec3::Z, 1.0), (1.0, 1.0));
    }

    #[test]
    fn shadows_fall_where_the_light_is_blocked() {
        let mut objects = corner().objects;
        // A slab over x -2.5..-1.5, y -0.5..0.5, z 0.9..1.1.
        objects.push(object("box", Shape::Cuboid { half: Vec3::new(0.5, 0.5, 0.1) }, Vec3::new(-2.0, 0.0, 1.0)));
        let mut w = World::new(objects).unwrap();
        // Light from -x, 45 degrees up: the ray from floor point (x, y, 0) is at x - z when at
        // height z, so the slab shades x in -1.6..-0.4 (|y| <= 0.5), and the wall at x = 0
        // shades every floor point with 0 < x < 5.
        w.light = Vec3::new(-1.0, 0.0, 1.0).normalize();
        w.occlusion = Occlusion { shadows: true, ao_rays: 0, ao_radius: 0.0 };
        let lit = |w: &World, x: f32, y: f32| w.occlusion_at(Vec3::new(x, y, 0.0), Vec3::Z, 1.0).0;
        for (x, y, want) in [
            (-1.0, 0.0, 0.0),
            (-1.55, 0.45, 0.0),
            (-0.45, -0.45, 0.0),
            (-1.0, 0.55, 1.0),
            (-1.65, 0.0, 1.0),
            (-0.35, 0.0, 1.0),
            (-2.0, 0.0, 1.0),
            (1.0, 2.0, 0.0),
            (4.9, 0.0, 0.0),
        ] {
            assert_eq!(lit(&w, x, y), want, "floor point ({x}, {y})");
        }
        // An enclosure set not to cast leaves the light through.
        w.set_casts_shadow(1, false);
        assert_eq!(lit(&w, 1.0, 2.0), 1.0);
        assert_eq!(lit(&w, -1.0, 0.0), 0.0);
        // A surface turned away from the light casts no ray (its diffuse term is 0 anyway).
        assert_eq!(w.occlusion_at(Vec3::new(-1.0, 0.0, 0.0), Vec3::Z, 0.0).0, 1.0);
        // Off, nothing is shaded.
        w.occlusion = Occlusion::default();
        assert_eq!(lit(&w, -1.0, 0.0), 1.0);
    }
}
