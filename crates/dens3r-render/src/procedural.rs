//! Procedural scenes: a furnished room, and a smooth "blob" object for orbits.

use crate::material::{Material, Texture};
use crate::world::{Object, Shape};
use dens3r_mesh::primitives::{icosphere, quad, torus};
use dens3r_mesh::TriMesh;
use glam::{Quat, Vec3};
use rand::{Rng, SeedableRng};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Semantic classes of procedural scenes (written to `classes.json`).
pub fn classes() -> BTreeMap<u16, String> {
    ["background", "floor", "wall", "ceiling", "box", "sphere", "torus", "object"]
        .iter()
        .enumerate()
        .map(|(i, n)| (i as u16, n.to_string()))
        .collect()
}

/// Class id of an object loaded from a mesh file.
pub const CLASS_OBJECT: u16 = 7;

/// Interior bounds of [`room`]: 4 m x 4 m, 2.6 m high, floor at z = 0.
pub const ROOM_LO: Vec3 = Vec3::new(-2.0, -2.0, 0.0);
/// See [`ROOM_LO`].
pub const ROOM_HI: Vec3 = Vec3::new(2.0, 2.0, 2.6);

/// A closed room (floor, ceiling, four walls as inward-facing quads) furnished with boxes,
/// spheres and a torus placed from `seed`.
pub fn room(seed: u64) -> Vec<Object> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let (lo, hi) = (ROOM_LO, ROOM_HI);
    let size = hi - lo;
    let mut objs = Vec::new();
    let mat = |rng: &mut rand_chacha::ChaCha8Rng, texture: Texture| Material {
        color: [rng.gen_range(0.35..1.0), rng.gen_range(0.35..1.0), rng.gen_range(0.35..1.0)],
        texture,
        seed: rng.gen(),
    };
    let mut add = |name: &str, shape: Shape, rotation: Quat, translation: Vec3, class_id: u16, material: Material| {
        objs.push(Object { name: name.into(), shape, rotation, translation, class_id, material });
    };
    let surface = |m: TriMesh| Shape::Mesh(Arc::new(m));
    let floor = quad(lo, Vec3::Y * size.y, Vec3::X * size.x); // normal +z
    add("floor", surface(floor), Quat::IDENTITY, Vec3::ZERO, 1, mat(&mut rng, Texture::Checker { size: 0.25 }));
    let ceiling = quad(Vec3::new(lo.x, lo.y, hi.z), Vec3::X * size.x, Vec3::Y * size.y); // normal -z
    add("ceiling", surface(ceiling), Quat::IDENTITY, Vec3::ZERO, 3, mat(&mut rng, Texture::Noise { scale: 0.5 }));
    let walls = [
        ("wall_south", quad(lo, Vec3::X * size.x, Vec3::Z * size.z)), // +y
        ("wall_north", quad(Vec3::new(hi.x, hi.y, lo.z), Vec3::NEG_X * size.x, Vec3::Z * size.z)), // -y
        ("wall_west", quad(Vec3::new(lo.x, hi.y, lo.z), Vec3::NEG_Y * size.y, Vec3::Z * size.z)), // +x
        ("wall_east", quad(Vec3::new(hi.x, lo.y, lo.z), Vec3::Y * size.y, Vec3::Z * size.z)), // -x
    ];
    for (name, m) in walls {
        let texture = Texture::Noise { scale: rng.gen_range(0.15..0.4) };
        add(name, surface(m), Quat::IDENTITY, Vec3::ZERO, 2, mat(&mut rng, texture));
    }
    // Furniture on a ring around the centre, leaving the middle free for the cameras.
    let n_items = 6;
    for i in 0..n_items {
        let a = std::f32::consts::TAU * (i as f32 + rng.gen_range(-0.2..0.2)) / n_items as f32;
        let r = rng.gen_range(1.15..1.45);
        let at = Vec3::new(r * a.cos(), r * a.sin(), 0.0);
        let spin = Quat::from_rotation_z(rng.gen_range(0.0..std::f32::consts::PI));
        match i % 3 {
            0 => {
                let half = Vec3::new(rng.gen_range(0.15..0.3), rng.gen_range(0.15..0.3), rng.gen_range(0.15..0.45));
                let t = mat(&mut rng, Texture::Checker { size: 0.08 });
                add(&format!("box_{i}"), Shape::Cuboid { half }, spin, at + Vec3::Z * half.z, 4, t);
            }
            1 => {
                let radius = rng.gen_range(0.15..0.3);
                let height = rng.gen_range(0.0..0.5);
                let t = mat(&mut rng, Texture::Noise { scale: 0.06 });
                add(&format!("sphere_{i}"), Shape::Sphere { radius }, spin, at + Vec3::Z * (radius + height), 5, t);
                if height > 0.05 {
                    // A pedestal under a raised sphere.
                    let half = Vec3::new(0.1, 0.1, height / 2.0);
                    let t = mat(&mut rng, Texture::Checker { size: 0.05 });
                    add(&format!("pedestal_{i}"), Shape::Cuboid { half }, spin, at + Vec3::Z * (height / 2.0), 4, t);
                }
            }
            _ => {
                let (major, minor) = (rng.gen_range(0.18..0.26), rng.gen_range(0.05..0.09));
                let tilt = spin * Quat::from_rotation_x(std::f32::consts::FRAC_PI_2);
                let t = mat(&mut rng, Texture::Noise { scale: 0.05 });
                add(
                    &format!("torus_{i}"),
                    Shape::Mesh(Arc::new(torus(major, minor, 96, 48))),
                    tilt,
                    at + Vec3::Z * (major + minor),
                    6,
                    t,
                );
            }
        }
    }
    objs
}

/// A smooth closed "blob": an icosphere of radius 1 with seeded Gaussian bumps and dents,
/// so its normals vary everywhere (a good normal-estimation and meshing target).
pub fn blob_mesh(seed: u64, subdivisions: u32) -> TriMesh {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let bumps: Vec<(Vec3, f32, f32)> = (0..9)
        .map(|_| {
            let dir = Vec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0))
                .normalize_or(Vec3::Z);
            (dir, rng.gen_range(-0.18..0.28), rng.gen_range(0.15..0.5))
        })
        .collect();
    let mut m = icosphere(1.0, subdivisions);
    for p in &mut m.positions {
        let u = p.normalize();
        let r = 1.0 + bumps.iter().map(|(c, a, w)| a * (-(1.0 - u.dot(*c)) / (w * w)).exp()).sum::<f32>();
        *p = u * r;
    }
    m.compute_vertex_normals();
    m
}

/// A single mesh object (class "object") at the origin with a noise texture sized to it.
pub fn single_object(mesh: TriMesh, seed: u32) -> Vec<Object> {
    single_object_with(mesh, seed, ObjectTexture::Noise)
}

/// The surface pattern of [`single_object_with`], sized to the object.
#[derive(Debug, Clone, PartialEq)]
pub enum ObjectTexture {
    /// Smooth value noise, 12 features across the object (low contrast at small scales).
    Noise,
    /// A 3-D checkerboard, 8 cells across the object.
    Checker,
    /// Flat colour.
    Plain,
    /// A photograph (sRGB), its width spanning the object once, each side of the object
    /// showing its own part of it (tri-planar projection).
    Photo(Arc<image::RgbImage>),
}

/// A single mesh object (class "object") at the origin with the given texture.
pub fn single_object_with(mesh: TriMesh, seed: u32, texture: ObjectTexture) -> Vec<Object> {
    let (lo, hi) = mesh.bounds().unwrap_or((Vec3::ZERO, Vec3::ONE));
    let scale = (hi - lo).max_element().max(1e-6);
    let (color, texture) = match texture {
        ObjectTexture::Noise => ([0.85, 0.7, 0.55], Texture::Noise { scale: scale / 12.0 }),
        ObjectTexture::Checker => ([0.85, 0.7, 0.55], Texture::Checker { size: scale / 8.0 }),
        ObjectTexture::Plain => ([0.85, 0.7, 0.55], Texture::Plain),
        ObjectTexture::Photo(image) => ([1.0; 3], Texture::Photo { image, size: scale, per_face: true }),
    };
    vec![Object {
        name: "object".into(),
        shape: Shape::Mesh(Arc::new(mesh)),
        rotation: Quat::IDENTITY,
        translation: Vec3::ZERO,
        class_id: CLASS_OBJECT,
        material: Material { color, texture, seed },
    }]
}
