//! Varied procedural scenes for training: rooms of random size furnished with primitives and
//! scanned meshes, assemblies of objects seen from orbits, clutter seen from above (tabletops)
//! totes seen close from above (bins) and shelves of books seen head-on, with textures cut from real
//! photographs (or procedural ones), random materials, lights and shading, random intrinsics
//! (40-100 degree horizontal field of view, landscape or portrait) and camera paths whose
//! baselines range from a few centimetres to a large part of the scene. Everything is drawn
//! from one seed: the same seed and assets give the same scene.

use crate::material::{Material, Texture};
use crate::procedural::{blob_mesh, CLASS_OBJECT};
use crate::world::{Object, Shape, World, WorldError};
use dens3r_geom::camera::look_at;
use dens3r_geom::{Intrinsics, PinholeCamera};
use dens3r_io::IoError;
use dens3r_mesh::primitives::{quad, torus};
use dens3r_mesh::TriMesh;
use glam::{DMat4, DVec3, Quat, Vec3};
use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::Path;
use std::sync::Arc;

/// Which scenes to draw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SynthKind {
    /// Furnished rooms, cameras walking inside.
    Rooms,
    /// Object assemblies on a ground plane, cameras orbiting.
    Objects,
    /// Each scene a room or an object set, by a coin flip of its seed.
    Mixed,
    /// Clutter in a tote, on a table or on the floor, seen from above (55-90 degrees down),
    /// as a robot's bin-picking camera or a phone held over a desk sees it.
    Tabletop,
    /// A deep tote seen close from above, filling most of the frame (its rim near, the floor
    /// around it far), many small items and flat packages piled in it: a bin-picking camera's
    /// view.
    Bin,
    /// The same tote packed full and seen closer: 20-45 items up to 0.6 of its half-size,
    /// thick boxes among the packages, piled up to its rim, the camera 0.9-2 half-sizes above
    /// the rim so the tote's walls often leave the frame (a picking cell's full bin).
    PackedBin,
    /// A shelf unit of books and objects against a wall, seen nearly head-on from 0.7-3 m
    /// (furniture facing the camera, the wall behind it a little farther): a photo of a
    /// bookshelf, a cupboard or a desk against a wall.
    Shelf,
}

impl SynthKind {
    /// `rooms`, `objects`, `mixed`, `tabletop`, `bin`, `packed-bin` or `shelf`.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "rooms" => Some(Self::Rooms),
            "objects" => Some(Self::Objects),
            "mixed" => Some(Self::Mixed),
            "tabletop" => Some(Self::Tabletop),
            "bin" => Some(Self::Bin),
            "packed-bin" => Some(Self::PackedBin),
            "shelf" => Some(Self::Shelf),
            _ => None,
        }
    }
}

/// Real material the scenes are built from (all optional: without it, textures are
/// procedural and objects primitives or blobs).
#[derive(Debug, Clone, Default)]
pub struct Assets {
    /// Photographs used as textures.
    pub photos: Vec<Arc<RgbImage>>,
    /// Scanned meshes, each centred with its largest extent 1.
    pub meshes: Vec<Arc<TriMesh>>,
    /// File names of the photographs and meshes, in order (for the dataset manifest).
    pub names: Vec<String>,
}

impl Assets {
    /// Reads every `.png` / `.jpg` of `photos` and `.off` / `.ply` / `.obj` of `meshes`
    /// (folders that do not exist are skipped), in file-name order.
    pub fn load(photos: Option<&Path>, meshes: Option<&Path>) -> Result<Self, IoError> {
        let list = |dir: Option<&Path>, exts: &[&str]| -> Result<Vec<std::path::PathBuf>, IoError> {
            let Some(dir) = dir.filter(|d| d.is_dir()) else { return Ok(Vec::new()) };
            let mut v: Vec<_> = std::fs::read_dir(dir)
                .map_err(|e| IoError::new(dir, format!("cannot list ({e})")))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension()
                        .and_then(|e| e.to_str())
                        .is_some_and(|e| exts.contains(&e.to_ascii_lowercase().as_str()))
                })
                .collect();
            v.sort();
            Ok(v)
        };
        let mut out = Self::default();
        for p in list(photos, &["png", "jpg", "jpeg"])? {
            let img = image::open(&p).map_err(|e| IoError::new(&p, format!("cannot read the photograph ({e})")))?;
            out.photos.push(Arc::new(img.to_rgb8()));
            out.names.push(file_name(&p));
        }
        for p in list(meshes, &["off", "ply", "obj"])? {
            let mut m = dens3r_mesh::io::read_mesh(&p).map_err(|e| IoError::new(&e.path, e.message))?;
            let (lo, hi) = m.bounds().ok_or_else(|| IoError::new(&p, "the mesh is empty"))?;
            let s = 1.0 / (hi - lo).max_element().max(1e-9);
            let c = (lo + hi) * 0.5;
            m.transform(&(glam::Mat4::from_scale(Vec3::splat(s)) * glam::Mat4::from_translation(-c)));
            m.normals = None;
            m.compute_vertex_normals();
            out.meshes.push(Arc::new(m));
            out.names.push(file_name(&p));
        }
        Ok(out)
    }
}

fn file_name(p: &Path) -> String {
    p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

/// A drawn scene: the world and its cameras.
pub struct SynthScene {
    /// Objects, light and shading.
    pub world: World,
    /// One camera per view (OpenCV, camera-to-world).
    pub cameras: Vec<PinholeCamera>,
    /// `room`, `objects`, `tabletop` or `bin`.
    pub kind: &'static str,
}

/// The seed of scene `index` of a dataset seeded with `seed` (SplitMix64).
pub fn scene_seed(seed: u64, index: usize) -> u64 {
    let mut z = seed ^ (index as u64).wrapping_add(1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Draws one scene of `kind` from `seed` with `views` cameras of `size` (W, H; swapped for
/// portrait scenes).
pub fn synth_scene(
    kind: SynthKind,
    seed: u64,
    size: (usize, usize),
    views: usize,
    assets: &Assets,
) -> Result<SynthScene, WorldError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // (Mixed draws its coin first, as it always has: the sets made before Tabletop existed
    // stay the same.)
    let name = match kind {
        SynthKind::Rooms => "room",
        SynthKind::Objects => "objects",
        SynthKind::Mixed if rng.gen_bool(0.5) => "room",
        SynthKind::Mixed => "objects",
        SynthKind::Tabletop => "tabletop",
        SynthKind::Bin => "bin",
        SynthKind::PackedBin => "packed-bin",
        SynthKind::Shelf => "shelf",
    };
    let (objects, poses) = match name {
        "room" => room_scene(&mut rng, views, assets),
        "objects" => object_scene(&mut rng, views, assets),
        "bin" => bin_scene(&mut rng, views, assets, &BinFill::SPARSE),
        "packed-bin" => bin_scene(&mut rng, views, assets, &BinFill::PACKED),
        "shelf" => shelf_scene(&mut rng, views, assets),
        _ => tabletop_scene(&mut rng, views, assets),
    };
    let mut world = World::new(objects)?;
    // Light from above at a random azimuth, random ambient and gloss.
    let (az, el) = (rng.gen_range(0.0..std::f32::consts::TAU), rng.gen_range(0.3..1.4f32));
    world.light = Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()).normalize();
    world.ambient = rng.gen_range(0.15..0.5);
    world.specular = if rng.gen_bool(0.5) { rng.gen_range(0.0..0.35) } else { 0.0 };
    world.shininess = rng.gen_range(8.0..64.0);
    world.background = [rng.gen(), rng.gen(), rng.gen()];
    // Intrinsics: one field of view per scene, a little zoom per view; portrait sometimes.
    let (w, h) = if rng.gen_bool(0.3) { (size.1, size.0) } else { size };
    let hfov = rng.gen_range(40.0..100.0f64);
    let cameras = poses
        .into_iter()
        .map(|pose| {
            let f = Intrinsics::from_hfov(w, h, hfov).fx * rng.gen_range(0.92..1.08);
            let intrinsics = Intrinsics { fx: f, fy: f, cx: w as f64 / 2.0, cy: h as f64 / 2.0 };
            PinholeCamera { intrinsics, width: w, height: h, cam_to_world: pose }
        })
        .collect();
    Ok(SynthScene { world, cameras, kind: name })
}

/// With probability `p` (a draw of its own from `seed`, so the scene's geometry, cameras and
/// other materials stay those of its seed), paints the scene's enclosure (walls and ceiling,
/// named `wall_*` / `ceiling`) one flat, light colour, as most real rooms' walls are: no
/// texture to read depth from, only shading.
pub fn plain_enclosure(scene: &mut SynthScene, seed: u64, p: f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x706c_6169_6e5f_7761);
    if !rng.gen_bool(p.clamp(0.0, 1.0)) {
        return;
    }
    let grey: f32 = rng.gen_range(0.65..0.95);
    let color = [0.0; 3].map(|_| (grey * rng.gen_range(0.92..1.08f32)).min(1.0));
    for k in 0..scene.world.objects().len() {
        if is_enclosure(&scene.world.objects()[k].name) {
            scene.world.set_material(k, Material { color, texture: Texture::Plain, seed: 0 });
        }
    }
}

/// Whether an object of a synthetic scene is part of its enclosure (a wall or the ceiling).
fn is_enclosure(name: &str) -> bool {
    name == "ceiling" || name.starts_with("wall_")
}

/// Turns on shadows of the scene's light and ambient occlusion (8 rays, reaching about a
/// tenth of the scene's scale: 0.5 in rooms, 0.3 among object sets, 0.1 over tabletops, 0.08
/// in bins). Enclosures (ceilings and walls, named `ceiling` / `wall_*`) cast no shadows: the
/// light stands for one inside them. Draws nothing at random, so the scene's geometry,
/// cameras and materials stay those of its seed.
pub fn add_occlusion(scene: &mut SynthScene) {
    let radius = match scene.kind {
        "room" => 0.5,
        "objects" => 0.3,
        "tabletop" => 0.1,
        "shelf" => 0.15,
        _ => 0.08,
    };
    for k in 0..scene.world.objects().len() {
        let enclosure = is_enclosure(&scene.world.objects()[k].name);
        scene.world.set_casts_shadow(k, !enclosure);
    }
    scene.world.occlusion = crate::world::Occlusion { shadows: true, ao_rays: 8, ao_radius: radius };
}

fn material(rng: &mut ChaCha8Rng, assets: &Assets, scale: f32) -> Material {
    let tint: f32 = rng.gen_range(0.6..1.0);
    let mut color = [0.0; 3].map(|_| rng.gen_range(0.3..1.0f32));
    let texture = match rng.gen_range(0..10) {
        0..=4 if !assets.photos.is_empty() => {
            color = [0.0; 3].map(|_| (tint * rng.gen_range(0.85..1.15f32)).min(1.0));
            let image = assets.photos[rng.gen_range(0..assets.photos.len())].clone();
            Texture::Photo { image, size: scale * rng.gen_range(0.5..3.0), per_face: false }
        }
        0..=5 => Texture::Checker { size: scale * rng.gen_range(0.08..0.5) },
        6..=8 => Texture::Noise { scale: scale * rng.gen_range(0.03..0.4) },
        _ => Texture::Plain,
    };
    Material { color, texture, seed: rng.gen() }
}

fn spin(rng: &mut ChaCha8Rng) -> Quat {
    Quat::from_rotation_z(rng.gen_range(0.0..std::f32::consts::TAU))
}

/// One random object of largest extent about `s`, standing on `z = base` at `(x, y)`:
/// `(name, shape, rotation, translation, class)`.
fn random_object(rng: &mut ChaCha8Rng, assets: &Assets, s: f32, at: Vec3) -> (String, Shape, Quat, Vec3, u16) {
    let pick = rng.gen_range(0..if assets.meshes.is_empty() { 4 } else { 6 });
    match pick {
        0 => {
            let half = Vec3::new(rng.gen_range(0.2..0.5), rng.gen_range(0.2..0.5), rng.gen_range(0.15..0.6)) * s;
            ("box".into(), Shape::Cuboid { half }, spin(rng), at + Vec3::Z * half.z, 4)
        }
        1 => {
            let r = rng.gen_range(0.2..0.5) * s;
            let lift = if rng.gen_bool(0.3) { rng.gen_range(0.0..1.0) * s } else { 0.0 };
            ("sphere".into(), Shape::Sphere { radius: r }, Quat::IDENTITY, at + Vec3::Z * (r + lift), 5)
        }
        2 => {
            let (major, minor) = (rng.gen_range(0.25..0.4) * s, rng.gen_range(0.05..0.15) * s);
            let upright = rng.gen_bool(0.5);
            let tilt = if upright { spin(rng) * Quat::from_rotation_x(std::f32::consts::FRAC_PI_2) } else { spin(rng) };
            let lift = if upright { major + minor } else { minor };
            ("torus".into(), Shape::Mesh(Arc::new(torus(major, minor, 64, 32))), tilt, at + Vec3::Z * lift, 6)
        }
        3 => {
            let m = blob_mesh(rng.gen(), 4);
            let r = rng.gen_range(0.2..0.45) * s;
            let mut m = m;
            m.transform(&glam::Mat4::from_scale(Vec3::splat(r)));
            m.compute_vertex_normals();
            let lo = m.bounds().map_or(-r, |(lo, _)| lo.z);
            ("blob".into(), Shape::Mesh(Arc::new(m)), spin(rng), at - Vec3::Z * lo, CLASS_OBJECT)
        }
        _ => {
            let k = rng.gen_range(0..assets.meshes.len());
            let scale = rng.gen_range(0.5..1.0) * s;
            // Stand the (z-up or y-up) scan on a random face.
            let up = match rng.gen_range(0..3) {
                0 => Quat::IDENTITY,
                1 => Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
                _ => Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
            };
            let mut m = (*assets.meshes[k]).clone();
            m.transform(&glam::Mat4::from_scale_rotation_translation(Vec3::splat(scale), up, Vec3::ZERO));
            m.compute_vertex_normals();
            let lo = m.bounds().map_or(0.0, |(lo, _)| lo.z);
            (format!("scan_{k}"), Shape::Mesh(Arc::new(m)), spin(rng), at - Vec3::Z * lo, CLASS_OBJECT)
        }
    }
}

fn room_scene(rng: &mut ChaCha8Rng, views: usize, assets: &Assets) -> (Vec<Object>, Vec<DMat4>) {
    let size = Vec3::new(rng.gen_range(3.0..8.0), rng.gen_range(3.0..8.0), rng.gen_range(2.4..3.5));
    let (lo, hi) = (Vec3::new(-size.x / 2.0, -size.y / 2.0, 0.0), Vec3::new(size.x / 2.0, size.y / 2.0, size.z));
    let mut objs = Vec::new();
    let add = |objs: &mut Vec<Object>,
               name: String,
               shape: Shape,
               rotation: Quat,
               translation: Vec3,
               class_id: u16,
               material: Material| {
        objs.push(Object { name, shape, rotation, translation, class_id, material });
    };
    let surf = |m: TriMesh| Shape::Mesh(Arc::new(m));
    let floor_mat = material(rng, assets, 1.0);
    add(
        &mut objs,
        "floor".into(),
        surf(quad(lo, Vec3::Y * size.y, Vec3::X * size.x)),
        Quat::IDENTITY,
        Vec3::ZERO,
        1,
        floor_mat,
    );
    let ceil = quad(Vec3::new(lo.x, lo.y, hi.z), Vec3::X * size.x, Vec3::Y * size.y);
    let ceil_mat = material(rng, assets, 1.0);
    add(&mut objs, "ceiling".into(), surf(ceil), Quat::IDENTITY, Vec3::ZERO, 3, ceil_mat);
    let walls = walls(lo, hi);
    let shared_walls = rng.gen_bool(0.5).then(|| material(rng, assets, 1.0));
    for (i, m) in walls.into_iter().enumerate() {
        let mat = shared_walls.clone().unwrap_or_else(|| material(rng, assets, 1.0));
        add(&mut objs, format!("wall_{i}"), surf(m), Quat::IDENTITY, Vec3::ZERO, 2, mat);
    }
    // Furniture in the outer band of the room; the cameras stay in the inner ellipse.
    let half = Vec3::new(size.x / 2.0, size.y / 2.0, 0.0);
    let n = rng.gen_range(6..=16);
    let mut spots = Vec::with_capacity(n);
    for i in 0..n {
        let a = rng.gen_range(0.0..std::f32::consts::TAU);
        let r = rng.gen_range(0.55..0.88);
        let at = Vec3::new(half.x * r * a.cos(), half.y * r * a.sin(), 0.0);
        spots.push(at);
        let s = rng.gen_range(0.7..2.0);
        let (name, shape, rot, t, class) = random_object(rng, assets, s, at);
        let mat = material(rng, assets, s);
        add(&mut objs, format!("{name}_{i}"), shape, rot, t, class, mat);
    }
    // A walk in the inner ellipse: steps of a per-scene baseline, each view looking at a
    // point across the room that drifts from view to view.
    let step = rng.gen_range(0.05..0.6f64);
    let inner = |p: DVec3| {
        let (ex, ey) = (p.x / (0.4 * half.x as f64), p.y / (0.4 * half.y as f64));
        let k = (ex * ex + ey * ey).sqrt();
        if k > 1.0 {
            DVec3::new(p.x / k, p.y / k, p.z)
        } else {
            p
        }
    };
    let mut eye = inner(DVec3::new(
        rng.gen_range(-0.4..0.4) * half.x as f64,
        rng.gen_range(-0.4..0.4) * half.y as f64,
        rng.gen_range(0.8..2.0f64).min(size.z as f64 - 0.4),
    ));
    // Start looking at a piece of furniture.
    let look = spots[rng.gen_range(0..spots.len())].as_dvec3() - eye;
    let mut heading = look.y.atan2(look.x) + rng.gen_range(-0.3..0.3);
    let pitch0 = rng.gen_range(-0.5..0.2f64);
    let mut poses = Vec::with_capacity(views);
    for _ in 0..views {
        let dir = DVec3::new(heading.cos(), heading.sin(), pitch0 + rng.gen_range(-0.15..0.15));
        poses.push(camera(rng, eye, eye + dir, DVec3::Z));
        heading += rng.gen_range(-0.5..0.5) * step.sqrt();
        let walk = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-0.2..0.2));
        eye = inner(eye + walk.normalize_or_zero() * step);
        eye.z = eye.z.clamp(0.5, size.z as f64 - 0.3);
    }
    (objs, poses)
}

fn object_scene(rng: &mut ChaCha8Rng, views: usize, assets: &Assets) -> (Vec<Object>, Vec<DMat4>) {
    let mut objs = Vec::new();
    if rng.gen_bool(0.8) {
        let g = rng.gen_range(4.0..12.0);
        let ground = quad(Vec3::new(-g, -g, 0.0), Vec3::Y * 2.0 * g, Vec3::X * 2.0 * g);
        let material = material(rng, assets, 1.0);
        objs.push(Object {
            name: "ground".into(),
            shape: Shape::Mesh(Arc::new(ground)),
            rotation: Quat::IDENTITY,
            translation: Vec3::ZERO,
            class_id: 1,
            material,
        });
    }
    let n = rng.gen_range(1..=5);
    let spread = if n == 1 { 0.0 } else { rng.gen_range(0.4..1.0f32) };
    for i in 0..n {
        let a = rng.gen_range(0.0..std::f32::consts::TAU);
        let at = Vec3::new(a.cos(), a.sin(), 0.0) * spread * rng.gen_range(0.3..1.0);
        let s = rng.gen_range(0.5..1.2);
        let (name, shape, rotation, translation, class_id) = random_object(rng, assets, s, at);
        let material = material(rng, assets, s);
        objs.push(Object { name: format!("{name}_{i}"), shape, rotation, translation, class_id, material });
    }
    let center = DVec3::new(0.0, 0.0, rng.gen_range(0.2..0.6));
    let radius = rng.gen_range(1.6..4.5f64);
    let el0 = rng.gen_range(10.0..60.0f64);
    let span = rng.gen_range(30.0..200.0f64).to_radians();
    let a0 = rng.gen_range(0.0..std::f64::consts::TAU);
    let poses = (0..views)
        .map(|k| {
            let (eye, _) = orbit_eye(rng, center, (a0, span, k, views), (el0, 8.0, 5.0, 80.0), radius);
            let target =
                center + DVec3::new(rng.gen_range(-0.2..0.2), rng.gen_range(-0.2..0.2), rng.gen_range(-0.1..0.1));
            camera(rng, eye, target, DVec3::Z)
        })
        .collect();
    (objs, poses)
}

fn tabletop_scene(rng: &mut ChaCha8Rng, views: usize, assets: &Assets) -> (Vec<Object>, Vec<DMat4>) {
    let mut objs = Vec::new();
    let floor = quad(Vec3::new(-6.0, -6.0, 0.0), Vec3::Y * 12.0, Vec3::X * 12.0);
    let m = material(rng, assets, 1.0);
    objs.push(object("floor", Shape::Mesh(Arc::new(floor)), Quat::IDENTITY, Vec3::ZERO, 1, m));
    // The surface the clutter lies on: a table top (a solid block) or the floor, with a tote on
    // it or not.
    let half = Vec3::new(rng.gen_range(0.25..0.6), rng.gen_range(0.2..0.45), 0.0);
    let base = if rng.gen_bool(0.5) { rng.gen_range(0.4..0.9f32) } else { 0.0 };
    if base > 0.0 {
        let grow = rng.gen_range(1.0..2.0f32);
        let top = Vec3::new(half.x * grow, half.y * grow, base / 2.0);
        let m = material(rng, assets, 1.0);
        objs.push(object("table", Shape::Cuboid { half: top }, Quat::IDENTITY, Vec3::Z * top.z, 4, m));
    }
    if rng.gen_bool(0.6) {
        let (depth, flare) = (rng.gen_range(0.1..0.3f32), rng.gen_range(0.0..0.08f32));
        let m = material(rng, assets, 0.5);
        // A few millimetres up: its floor is not coplanar with the one it stands on.
        let at = Vec3::Z * (base + 0.003);
        objs.push(object("tote", Shape::Mesh(Arc::new(tote(half, depth, flare, 0.0))), Quat::IDENTITY, at, 2, m));
    }
    // Clutter: flat packages, books and the usual objects, piled a little.
    let n = rng.gen_range(4..=16);
    for i in 0..n {
        let at = Vec3::new(
            rng.gen_range(-0.8..0.8) * half.x,
            rng.gen_range(-0.8..0.8) * half.y,
            base + 0.003 + if rng.gen_bool(0.3) { rng.gen_range(0.0..0.06) } else { 0.0 },
        );
        let s = rng.gen_range(0.15..0.5) * half.x.max(half.y) / 0.4;
        objs.push(clutter_item(rng, assets, i, s, at, (0.45, 0.1, 0.25)));
    }
    // Things on the floor around it.
    for i in 0..rng.gen_range(0..=4) {
        objs.push(floor_object(rng, assets, i, (half.x.max(half.y) * 2.2, 0.0..1.5), 0.2..0.6));
    }
    // Cameras above, looking down at the clutter from 55-90 degrees, a small arc apart; near
    // straight down the image's up is a direction of the scene, not the world's up.
    let centre = DVec3::new(0.0, 0.0, base as f64);
    let dist = half.x.max(half.y) as f64 * rng.gen_range(1.3..3.2);
    let el0 = rng.gen_range(55.0..90.0f64);
    let span = rng.gen_range(5.0..90.0f64).to_radians();
    let a0 = rng.gen_range(0.0..std::f64::consts::TAU);
    let yaw = rng.gen_range(0.0..std::f64::consts::TAU);
    let poses = (0..views)
        .map(|k| {
            let (eye, el) = orbit_eye(rng, centre, (a0, span, k, views), (el0, 6.0, 50.0, 89.5), dist);
            let j = half.as_dvec3() * 0.3;
            let target = centre + DVec3::new(rng.gen_range(-j.x..j.x), rng.gen_range(-j.y..j.y), 0.0);
            let up = if el > 80f64.to_radians() {
                let y = yaw + rng.gen_range(-0.1..0.1);
                DVec3::new(y.cos(), y.sin(), 0.0)
            } else {
                DVec3::Z
            };
            camera(rng, eye, target, up)
        })
        .collect();
    (objs, poses)
}

/// A bin-picking view: a deep tote (walls 0.12-0.35 high with a lip, on the floor or on a
/// stand) holding 6-24 small items, most of them flat packages, some piled; boxes standing
/// beside it and objects on the floor around, walls a few metres off; cameras 1.2-2.4 tote
/// half-sizes above its rim,
/// looking at points of its floor (up to 35 degrees off vertical), so the tote fills most of
/// the frame and its rim is the nearest thing in view.
fn bin_scene(rng: &mut ChaCha8Rng, views: usize, assets: &Assets, fill: &BinFill) -> (Vec<Object>, Vec<DMat4>) {
    let mut objs = Vec::new();
    // A cell 5-11 across, walls 4 high: a camera tilted 35 degrees with a wide lens sees its
    // walls near the horizon, never the sky.
    let r = rng.gen_range(2.5..5.5f32);
    let (lo, hi) = (Vec3::new(-r, -r, 0.0), Vec3::new(r, r, 4.0));
    let m = material(rng, assets, 1.0);
    objs.push(object(
        "floor",
        Shape::Mesh(Arc::new(quad(lo, Vec3::Y * 2.0 * r, Vec3::X * 2.0 * r))),
        Quat::IDENTITY,
        Vec3::ZERO,
        1,
        m,
    ));
    let m = material(rng, assets, 1.0);
    for (i, w) in walls(lo, hi).into_iter().enumerate() {
        objs.push(object(format!("wall_{i}"), Shape::Mesh(Arc::new(w)), Quat::IDENTITY, Vec3::ZERO, 2, m.clone()));
    }
    let half = Vec3::new(rng.gen_range(0.25..0.45), rng.gen_range(0.17..0.32), 0.0);
    let (depth, flare, lip) = (rng.gen_range(0.12..0.35f32), rng.gen_range(0.0..0.05f32), rng.gen_range(0.01..0.05f32));
    let base = if rng.gen_bool(0.4) { rng.gen_range(0.2..0.8f32) } else { 0.0 };
    if base > 0.0 {
        let grow = rng.gen_range(1.0..1.3);
        let top = Vec3::new((half.x + flare + lip) * grow, (half.y + flare + lip) * grow, base / 2.0);
        let m = material(rng, assets, 1.0);
        objs.push(object("stand", Shape::Cuboid { half: top }, Quat::IDENTITY, Vec3::Z * top.z, 4, m));
    }
    let m = material(rng, assets, 0.5);
    let at = Vec3::Z * (base + 0.003);
    objs.push(object("tote", Shape::Mesh(Arc::new(tote(half, depth, flare, lip))), Quat::IDENTITY, at, 2, m));
    // The items: flat packages and small objects on its floor, some on top of others.
    let size = half.x.max(half.y);
    let first_item = objs.len();
    for i in 0..rng.gen_range(fill.items.clone()) {
        let at = Vec3::new(
            rng.gen_range(-0.75..0.75) * half.x,
            rng.gen_range(-0.75..0.75) * half.y,
            base + 0.003 + if rng.gen_bool(fill.piled) { rng.gen_range(0.0..fill.pile_height) * depth } else { 0.0 },
        );
        let s = size * rng.gen_range(fill.item_size.clone());
        objs.push(clutter_item(rng, assets, i, s, at, fill.packages));
    }
    let items_top = objs[first_item..].iter().map(|o| crate::world::world_bounds(o).1.z as f64).fold(0.0, f64::max);
    // Around it: boxes standing beside it (a robot cell's machinery) and things on the floor.
    for i in 0..rng.gen_range(0..=3) {
        let a = rng.gen_range(0.0..std::f32::consts::TAU);
        let h = Vec3::new(rng.gen_range(0.05..0.2), rng.gen_range(0.05..0.2), rng.gen_range(0.1..0.6));
        // Never under a camera (those stay within half the tote's half-size of its centre).
        let at = Vec3::new(a.cos(), a.sin(), 0.0) * (size + flare + lip + rng.gen_range(0.3..0.8));
        let material = material(rng, assets, 0.3);
        objs.push(object(format!("beside_{i}"), Shape::Cuboid { half: h }, spin(rng), at + Vec3::Z * h.z, 4, material));
    }
    for i in 0..rng.gen_range(0..=4) {
        objs.push(floor_object(rng, assets, i, (size * 1.5, 0.1..1.2), 0.15..0.5));
    }
    // Cameras hovering over the tote, each looking at a point of its floor; the image's up is
    // a direction of the scene (one per scene, jittered).
    // The fill's clearance above the rim (1.2-2.4 half-sizes for bins), and at least its
    // margin above the highest item.
    let (rim, clearance) = ((base + depth) as f64, size as f64 * rng.gen_range(fill.clearance.clone()));
    let yaw = rng.gen_range(0.0..std::f64::consts::TAU);
    let h = half.as_dvec3();
    let poses = (0..views)
        .map(|_| {
            let mut eye = DVec3::new(
                rng.gen_range(-0.5..0.5) * h.x,
                rng.gen_range(-0.5..0.5) * h.y,
                rim + clearance * rng.gen_range(0.9..1.1),
            );
            eye.z = eye.z.max(items_top + fill.above_items * size as f64);
            let mut target = DVec3::new(rng.gen_range(-0.7..0.7) * h.x, rng.gen_range(-0.7..0.7) * h.y, base as f64);
            // At most 35 degrees off vertical.
            let off = target - eye;
            let reach = (eye.z - target.z) * 35f64.to_radians().tan();
            let flat = DVec3::new(off.x, off.y, 0.0);
            if flat.length() > reach {
                target = eye + flat * (reach / flat.length()) - DVec3::Z * (eye.z - target.z);
            }
            let y = yaw + rng.gen_range(-0.15..0.15);
            camera(rng, eye, target, DVec3::new(y.cos(), y.sin(), 0.0))
        })
        .collect();
    (objs, poses)
}

/// How a bin scene's tote is filled and how near its cameras hover.
struct BinFill {
    /// How many items.
    items: std::ops::RangeInclusive<i32>,
    /// Item size as a fraction of the tote's larger half-size.
    item_size: std::ops::Range<f32>,
    /// Chance an item is lifted onto the others, and the highest lift as a fraction of the
    /// tote's depth.
    piled: f64,
    pile_height: f32,
    /// `clutter_item`'s (package chance, package thickness, tilt).
    packages: (f64, f32, f32),
    /// Camera height above the rim in tote half-sizes.
    clearance: std::ops::Range<f64>,
    /// Every camera at least this many half-sizes above the highest item (the packed fill's
    /// piles may reach over its clearance; the sparse fill's never do: a sphere lifted by its
    /// size stays under 1.1 half-sizes over the rim, so its cameras stay where they were).
    above_items: f64,
}

impl BinFill {
    const SPARSE: BinFill = BinFill {
        items: 6..=24,
        item_size: 0.25..0.55,
        piled: 0.35,
        pile_height: 0.5,
        packages: (0.65, 0.12, 0.3),
        clearance: 1.2..2.4,
        above_items: 0.0,
    };
    const PACKED: BinFill = BinFill {
        items: 20..=45,
        item_size: 0.25..0.6,
        piled: 0.6,
        pile_height: 0.8,
        packages: (0.7, 0.4, 0.3),
        clearance: 0.9..2.0,
        above_items: 0.3,
    };
}

/// A shelf unit (0.6-2 wide, 0.6-2.1 high, 0.22-0.45 deep, 2-5 boards, an upright in the
/// middle sometimes) against the back wall of a room, its compartments filled with rows of
/// books (standing, leaning, a lying stack now and then, gaps) and objects, things on top and
/// beside it, posters on the wall; cameras 0.6-1.8 of its size in front (0.6-3), looking at
/// points of its face within 40 degrees of head-on, a short walk apart.
fn shelf_scene(rng: &mut ChaCha8Rng, views: usize, assets: &Assets) -> (Vec<Object>, Vec<DMat4>) {
    let mut objs = Vec::new();
    // The room: its back wall at y = 0 (wall_0), the cameras in front of it.
    let size = Vec3::new(rng.gen_range(3.0..7.0), rng.gen_range(4.0..7.0), rng.gen_range(2.4..3.2));
    let (lo, hi) = (Vec3::new(-size.x / 2.0, 0.0, 0.0), Vec3::new(size.x / 2.0, size.y, size.z));
    let m = material(rng, assets, 1.0);
    objs.push(object(
        "floor",
        Shape::Mesh(Arc::new(quad(lo, Vec3::Y * size.y, Vec3::X * size.x))),
        Quat::IDENTITY,
        Vec3::ZERO,
        1,
        m,
    ));
    let m = material(rng, assets, 1.0);
    let ceil = quad(Vec3::new(lo.x, lo.y, hi.z), Vec3::X * size.x, Vec3::Y * size.y);
    objs.push(object("ceiling", Shape::Mesh(Arc::new(ceil)), Quat::IDENTITY, Vec3::ZERO, 3, m));
    let m = material(rng, assets, 1.0);
    for (i, w) in walls(lo, hi).into_iter().enumerate() {
        objs.push(object(format!("wall_{i}"), Shape::Mesh(Arc::new(w)), Quat::IDENTITY, Vec3::ZERO, 2, m.clone()));
    }
    // The unit: sides, boards (bottom and top included), a back panel and a middle upright
    // sometimes; the whole frame one material.
    let (w, h, d) = (rng.gen_range(0.6..2.0f32), rng.gen_range(0.6..2.1f32), rng.gen_range(0.22..0.45f32));
    let t = rng.gen_range(0.015..0.04f32);
    let sx = rng.gen_range(-0.3..0.3) * (size.x - w).max(0.0);
    let gap = rng.gen_range(0.0..0.08f32);
    let yc = gap + d / 2.0;
    let frame = material(rng, assets, 0.5);
    let part = |objs: &mut Vec<Object>, name: String, half: Vec3, at: Vec3| {
        objs.push(object(name, Shape::Cuboid { half }, Quat::IDENTITY, at, 4, frame.clone()));
    };
    for (i, x) in [sx - w / 2.0 + t / 2.0, sx + w / 2.0 - t / 2.0].into_iter().enumerate() {
        part(&mut objs, format!("shelf_side_{i}"), Vec3::new(t / 2.0, d / 2.0, h / 2.0), Vec3::new(x, yc, h / 2.0));
    }
    let boards = rng.gen_range(2..=5usize);
    let plinth = rng.gen_range(0.0..0.12f32);
    let levels: Vec<f32> =
        (0..boards).map(|k| plinth + t / 2.0 + (h - plinth - t) * k as f32 / (boards - 1) as f32).collect();
    for (k, z) in levels.iter().enumerate() {
        part(&mut objs, format!("shelf_board_{k}"), Vec3::new(w / 2.0 - t, d / 2.0, t / 2.0), Vec3::new(sx, yc, *z));
    }
    if rng.gen_bool(0.5) {
        part(&mut objs, "shelf_back".into(), Vec3::new(w / 2.0, 0.004, h / 2.0), Vec3::new(sx, gap + 0.004, h / 2.0));
    }
    let middle = w > 1.0 && rng.gen_bool(0.6);
    if middle {
        part(&mut objs, "shelf_upright".into(), Vec3::new(t / 2.0, d / 2.0, h / 2.0 - t), Vec3::new(sx, yc, h / 2.0));
    }
    // The compartments' contents, left to right: rows of books, gaps, objects.
    let spans: Vec<(f32, f32)> = if middle {
        vec![(sx - w / 2.0 + t, sx - t / 2.0), (sx + t / 2.0, sx + w / 2.0 - t)]
    } else {
        vec![(sx - w / 2.0 + t, sx + w / 2.0 - t)]
    };
    let mut n = 0;
    for pair in levels.windows(2) {
        let (floor, room) = (pair[0] + t / 2.0, pair[1] - pair[0] - t);
        for &(x0, x1) in &spans {
            if rng.gen_bool(0.1) {
                continue;
            }
            let mut x = x0 + rng.gen_range(0.0..0.05);
            let books = rng.gen_bool(0.75);
            while x < x1 - 0.02 && n < 140 {
                n += 1;
                if books && rng.gen_bool(0.9) {
                    let bw = rng.gen_range(0.012..0.06f32).min(x1 - x);
                    let bh = (room * rng.gen_range(0.55..0.95)).max(0.05);
                    let bd = d * rng.gen_range(0.6..0.95);
                    let front = gap + d - rng.gen_range(0.0..0.04f32).min(d - bd);
                    let m = material(rng, assets, 0.2);
                    let (half, lean) = if rng.gen_bool(0.08) {
                        // A lying stack of a few books.
                        let hh = rng.gen_range(0.015..0.035f32) * rng.gen_range(1..=4) as f32;
                        (Vec3::new(bh.min(x1 - x) / 2.0, bd / 2.0, hh.min(room) / 2.0), 0.0)
                    } else {
                        (
                            Vec3::new(bw / 2.0, bd / 2.0, bh / 2.0),
                            if rng.gen_bool(0.1) { rng.gen_range(-0.25..0.25f32) } else { 0.0 },
                        )
                    };
                    let at = Vec3::new(x + half.x, front - half.y, floor + half.z);
                    objs.push(object(
                        format!("book_{n}"),
                        Shape::Cuboid { half },
                        Quat::from_rotation_y(lean),
                        at,
                        4,
                        m,
                    ));
                    x += 2.0 * half.x + if rng.gen_bool(0.08) { rng.gen_range(0.02..0.15) } else { 0.002 };
                } else {
                    let s = (room * rng.gen_range(0.4..0.9)).min(d).min(x1 - x);
                    if s < 0.04 {
                        break;
                    }
                    let at = Vec3::new(x + s / 2.0, gap + d / 2.0, floor);
                    let (name, shape, rotation, translation, class_id) = random_object(rng, assets, s, at);
                    let material = material(rng, assets, s);
                    objs.push(Object { name: format!("{name}_{n}"), shape, rotation, translation, class_id, material });
                    x += s + rng.gen_range(0.01..0.1);
                }
            }
        }
    }
    // On top, beside it, on the wall and on the floor.
    for i in 0..rng.gen_range(0..=3) {
        let s = rng.gen_range(0.1..0.35f32).min(d * 1.5);
        let at = Vec3::new(sx + rng.gen_range(-0.4..0.4) * w, yc, h);
        objs.push(clutter_item(rng, assets, 200 + i, s, at, (0.3, 0.2, 0.2)));
    }
    for i in 0..rng.gen_range(0..=3) {
        let half = Vec3::new(rng.gen_range(0.15..0.6), rng.gen_range(0.005..0.01), rng.gen_range(0.15..0.5));
        let side = if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
        let x = sx + side * (w / 2.0 + half.x + rng.gen_range(0.05..1.0));
        let at = Vec3::new(x, half.y, rng.gen_range(0.8..1.9f32).min(size.z - half.z - 0.05));
        let m = material(rng, assets, 0.5);
        objs.push(object(format!("poster_{i}"), Shape::Cuboid { half }, Quat::IDENTITY, at, 2, m));
    }
    for i in 0..rng.gen_range(0..=2) {
        let half = Vec3::new(rng.gen_range(0.2..0.5), rng.gen_range(0.2..0.4), rng.gen_range(0.2..0.55));
        let side = if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
        let at = Vec3::new(sx + side * (w / 2.0 + half.x + rng.gen_range(0.02..0.5)), half.y + 0.01, half.z);
        let m = material(rng, assets, 0.5);
        objs.push(object(format!("cabinet_{i}"), Shape::Cuboid { half }, Quat::IDENTITY, at, 4, m));
    }
    for i in 0..rng.gen_range(0..=3) {
        objs.push(floor_object(rng, assets, i, (w.max(1.0) * 0.8, 0.6..2.0), 0.2..0.5));
    }
    // Cameras: a start 0.6-1.8 of the unit's size in front of a point of its face, within 40
    // degrees of head-on, 25 down to 10 up, then a short walk, each view looking at a
    // drifting point.
    let face = |rng: &mut ChaCha8Rng| {
        DVec3::new((sx + rng.gen_range(-0.4..0.4) * w) as f64, (gap + d) as f64, (h * rng.gen_range(0.15..0.85)) as f64)
    };
    let target0 = face(rng);
    let dist = (w.max(h) as f64 * rng.gen_range(0.6..1.8)).clamp(0.6, 3.0).min(size.y as f64 - 0.6);
    let (yaw, pitch) = (rng.gen_range(-40f64..40.0).to_radians(), rng.gen_range(-25f64..10.0).to_radians());
    let dir = DVec3::new(yaw.sin() * pitch.cos(), yaw.cos() * pitch.cos(), pitch.sin());
    let mut eye = target0 + dir * dist;
    let step = rng.gen_range(0.03..0.4f64);
    let inside = |p: DVec3| {
        DVec3::new(
            p.x.clamp(lo.x as f64 + 0.3, hi.x as f64 - 0.3),
            p.y.clamp((gap + d) as f64 + 0.4, hi.y as f64 - 0.3),
            p.z.clamp(0.3, hi.z as f64 - 0.2),
        )
    };
    eye = inside(eye);
    let mut target = target0;
    let mut poses = Vec::with_capacity(views);
    for _ in 0..views {
        poses.push(camera(rng, eye, target, DVec3::Z));
        let walk = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-0.5..0.5), rng.gen_range(-0.3..0.3));
        eye = inside(eye + walk.normalize_or_zero() * step);
        target = target.lerp(face(rng), 0.3);
    }
    (objs, poses)
}

/// An object of a scene.
fn object(
    name: impl Into<String>,
    shape: Shape,
    rotation: Quat,
    translation: Vec3,
    class_id: u16,
    material: Material,
) -> Object {
    Object { name: name.into(), shape, rotation, translation, class_id, material }
}

/// The four walls of the box `lo..hi` (its floor at `lo.z`), facing in.
fn walls(lo: Vec3, hi: Vec3) -> [TriMesh; 4] {
    let size = hi - lo;
    [
        quad(lo, Vec3::X * size.x, Vec3::Z * size.z),
        quad(Vec3::new(hi.x, hi.y, lo.z), Vec3::NEG_X * size.x, Vec3::Z * size.z),
        quad(Vec3::new(lo.x, hi.y, lo.z), Vec3::NEG_Y * size.y, Vec3::Z * size.z),
        quad(Vec3::new(hi.x, lo.y, lo.z), Vec3::Y * size.y, Vec3::Z * size.z),
    ]
}

/// Clutter item `i` of size about `s` standing at `at`: with probability `package` a
/// [`flat_package`] (at most `thick` thick, tilted up to `tilt`), else a [`random_object`].
/// (`i` is an `i32` because the callers draw their counts as `i32`: a `usize` draw takes
/// other random words and would change every scene.)
fn clutter_item(
    rng: &mut ChaCha8Rng,
    assets: &Assets,
    i: i32,
    s: f32,
    at: Vec3,
    (package, thick, tilt): (f64, f32, f32),
) -> Object {
    let material = material(rng, assets, s);
    if rng.gen_bool(package) {
        let (shape, rotation, lift) = flat_package(rng, s, thick, tilt);
        let translation = at + Vec3::Z * lift;
        Object { name: format!("package_{i}"), shape, rotation, translation, class_id: 4, material }
    } else {
        let (name, shape, rotation, translation, class_id) = random_object(rng, assets, s, at);
        Object { name: format!("{name}_{i}"), shape, rotation, translation, class_id, material }
    }
}

/// Object `i` on the floor around the origin: at a random azimuth, `r0` plus a draw from
/// `spread` away, of size drawn from `size`.
fn floor_object(
    rng: &mut ChaCha8Rng,
    assets: &Assets,
    i: i32,
    (r0, spread): (f32, std::ops::Range<f32>),
    size: std::ops::Range<f32>,
) -> Object {
    let a = rng.gen_range(0.0..std::f32::consts::TAU);
    let at = Vec3::new(a.cos(), a.sin(), 0.0) * (r0 + rng.gen_range(spread));
    let s = rng.gen_range(size);
    let material = material(rng, assets, s);
    let (name, shape, rotation, translation, class_id) = random_object(rng, assets, s, at);
    Object { name: format!("floor_{name}_{i}"), shape, rotation, translation, class_id, material }
}

/// A flat package (a book, a box of tea) of size about `s`, at most `thick * s` thick, lying
/// nearly flat (tilted up to `tilt` radians each way) at a random heading: its shape,
/// rotation and the lift of its centre above the surface it lies on.
fn flat_package(rng: &mut ChaCha8Rng, s: f32, thick: f32, tilt: f32) -> (Shape, Quat, f32) {
    let h = Vec3::new(rng.gen_range(0.2..0.5), rng.gen_range(0.12..0.35), rng.gen_range(0.02..thick)) * s;
    let tilt = Quat::from_rotation_x(rng.gen_range(-tilt..tilt)) * Quat::from_rotation_y(rng.gen_range(-tilt..tilt));
    (Shape::Cuboid { half: h }, spin(rng) * tilt, h.z)
}

/// View `k` of `views` on an arc around `centre`: azimuth from `a0` over `span` (radians),
/// elevation `el0` degrees +- `jitter`, clamped to `lo..hi`, distance `radius` +-15%, each
/// jittered. Returns the eye and its elevation (radians).
fn orbit_eye(
    rng: &mut ChaCha8Rng,
    centre: DVec3,
    (a0, span, k, views): (f64, f64, usize, usize),
    (el0, jitter, lo, hi): (f64, f64, f64, f64),
    radius: f64,
) -> (DVec3, f64) {
    let t = if views > 1 { k as f64 / (views - 1) as f64 } else { 0.0 };
    let a = a0 + span * t + rng.gen_range(-0.05..0.05);
    let el = (el0 + rng.gen_range(-jitter..jitter)).clamp(lo, hi).to_radians();
    let r = radius * rng.gen_range(0.85..1.15);
    (centre + DVec3::new(el.cos() * a.cos(), el.cos() * a.sin(), el.sin()) * r, el)
}

/// An open box (a tote): a floor `2 half.x` by `2 half.y` at z = 0 and walls `depth` high
/// that lean out by `flare`, with a flat lip `lip` wide around the top (none when 0); each
/// face its own vertices (sharp edges).
fn tote(half: Vec3, depth: f32, flare: f32, lip: f32) -> TriMesh {
    let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];
    let lo = corners.map(|(x, y)| Vec3::new(x * half.x, y * half.y, 0.0));
    let hi = corners.map(|(x, y)| Vec3::new(x * (half.x + flare), y * (half.y + flare), depth));
    let mut positions = lo.to_vec();
    let mut indices = vec![[0, 1, 2], [0, 2, 3]];
    // A band of four quads from one ring of corners to the next (the walls, then the lip).
    let mut band = |inner: [Vec3; 4], outer: [Vec3; 4]| {
        for i in 0..4 {
            let j = (i + 1) % 4;
            let k = positions.len() as u32;
            positions.extend([inner[i], inner[j], outer[j], outer[i]]);
            indices.extend([[k, k + 2, k + 1], [k, k + 3, k + 2]]);
        }
    };
    band(lo, hi);
    if lip > 0.0 {
        band(hi, corners.map(|(x, y)| Vec3::new(x * (half.x + flare + lip), y * (half.y + flare + lip), depth)));
    }
    let mut m = TriMesh::new(positions, indices);
    m.compute_vertex_normals();
    m
}

/// A camera at `eye` looking at `target` (the image's up towards `up`), rolled by a few
/// degrees sometimes.
fn camera(rng: &mut ChaCha8Rng, eye: DVec3, target: DVec3, up: DVec3) -> DMat4 {
    let pose = look_at(eye, target, up)
        .unwrap_or_else(|| look_at(eye, target + DVec3::X * 1e-3, up).unwrap_or(DMat4::from_translation(eye)));
    let roll = if rng.gen_bool(0.3) { rng.gen_range(-0.15..0.15f64) } else { 0.0 };
    pose * DMat4::from_rotation_z(roll)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::world_bounds;

    /// A fill whose clearance leaves the cameras among the piles puts them above every item
    /// instead: with 0.05-0.1 half-sizes over the rim (0.05 at most) cameras would sit inside
    /// the piles of most scenes, and every camera ends up above the highest item (its bounds
    /// taken from the scene's objects: those after the tote, before what stands beside it).
    #[test]
    fn bin_cameras_stay_above_the_piles() {
        let low = BinFill { clearance: 0.05..0.1, ..BinFill::PACKED };
        let mut lifted = 0;
        for seed in 0..20 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (objs, poses) = bin_scene(&mut rng, 4, &Assets::default(), &low);
            let tote = objs.iter().position(|o| o.name == "tote").unwrap();
            let rim = world_bounds(&objs[tote]).1.z as f64;
            let items =
                objs[tote + 1..].iter().take_while(|o| !o.name.starts_with("beside_") && !o.name.starts_with("floor_"));
            let top = items.map(|o| world_bounds(o).1.z as f64).fold(f64::MIN, f64::max);
            assert!(top > rim - 0.4, "seed {seed}: no item found in the tote");
            if top > rim + 0.05 {
                lifted += 1;
            }
            for p in &poses {
                let z = p.w_axis.z;
                assert!(z > top, "seed {seed}: a camera at {z:.3}, the piles up to {top:.3}");
            }
        }
        assert!(lifted > 10, "only {lifted} of 20 scenes' piles reach over the low clearance");
    }
}
