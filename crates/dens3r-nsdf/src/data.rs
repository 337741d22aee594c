//! Training data from a scene folder: every pixel with a valid depth becomes a ray (origin,
//! unit direction, distance along the ray, world normal, colour), in a normalised frame where
//! the observed surface fits the cube `[-1, 1]^3`; plus a coarse occupancy grid of the observed
//! points that confines ray samples, eikonal points and mesh extraction to the space near the
//! surface.

use crate::NsdfError;
use dens3r_scene::Scene;
use glam::{DVec3, IVec3, Vec3};
use serde::{Deserialize, Serialize};

/// World <-> normalised frame: `x_n = (x - center) / scale`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    /// World centre.
    pub center: [f64; 3],
    /// World length of one normalised unit.
    pub scale: f64,
}

impl Bounds {
    /// World point to normalised.
    pub fn to_unit(&self, p: DVec3) -> Vec3 {
        ((p - DVec3::from(self.center)) / self.scale).as_vec3()
    }
    /// Normalised point to world.
    pub fn to_world(&self, p: Vec3) -> DVec3 {
        p.as_dvec3() * self.scale + DVec3::from(self.center)
    }
}

/// All training rays, normalised frame, struct of arrays.
#[derive(Debug, Clone, Default)]
pub struct Rays {
    /// Frame index per ray.
    pub frame: Vec<u32>,
    /// Origins.
    pub origin: Vec<Vec3>,
    /// Unit directions.
    pub dir: Vec<Vec3>,
    /// Observed distance along the ray (normalised units).
    pub dist: Vec<f32>,
    /// Observed world normal (unit, facing the camera), zero when the scene has none.
    pub normal: Vec<Vec3>,
    /// Colour in `[0, 1]`.
    pub color: Vec<[f32; 3]>,
}

impl Rays {
    /// Number of rays.
    pub fn len(&self) -> usize {
        self.dir.len()
    }
    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.dir.is_empty()
    }
}

/// Where a ray `o + t d` (`t >= 0`) is inside the cube `[-1, 1]^3` (slab test), if anywhere.
pub fn ray_cube(o: Vec3, d: Vec3) -> Option<(f32, f32)> {
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for a in 0..3 {
        let inv = 1.0 / d[a];
        let (ta, tb) = ((-1.0 - o[a]) * inv, (1.0 - o[a]) * inv);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t1 > t0).then_some((t0, t1))
}

/// A boolean grid of `res^3` cells over the normalised cube.
#[derive(Debug, Clone)]
pub struct Occupancy {
    /// Cells per axis.
    pub res: usize,
    cells: Vec<bool>,
}

impl Occupancy {
    /// Marks the cells holding `points`, then dilates by `dilate` cells.
    pub fn from_points(points: impl Iterator<Item = Vec3>, res: usize, dilate: i32) -> Self {
        let mut core = Self { res, cells: vec![false; res * res * res] };
        for p in points {
            if let Some(c) = core.cell_of(p) {
                let i = core.index(c);
                core.cells[i] = true;
            }
        }
        core.dilated(dilate)
    }

    /// This grid grown by `dilate` cells in every direction (a cube neighbourhood).
    pub fn dilated(&self, dilate: i32) -> Self {
        let res = self.res;
        let core = &self.cells;
        let mut occ = Self { res, cells: vec![false; res * res * res] };
        let r = res as i32;
        for z in 0..r {
            for y in 0..r {
                for x in 0..r {
                    if !core[occ.index(IVec3::new(x, y, z))] {
                        continue;
                    }
                    for dz in -dilate..=dilate {
                        for dy in -dilate..=dilate {
                            for dx in -dilate..=dilate {
                                let c = IVec3::new(x + dx, y + dy, z + dz);
                                if c.cmpge(IVec3::ZERO).all() && c.cmplt(IVec3::splat(r)).all() {
                                    let i = occ.index(c);
                                    occ.cells[i] = true;
                                }
                            }
                        }
                    }
                }
            }
        }
        occ
    }

    fn index(&self, c: IVec3) -> usize {
        (c.x as usize) + self.res * (c.y as usize + self.res * c.z as usize)
    }

    /// Edge of a cell in normalised units.
    pub fn cell(&self) -> f32 {
        2.0 / self.res as f32
    }

    /// The cell holding a normalised point, `None` outside the cube.
    pub fn cell_of(&self, p: Vec3) -> Option<IVec3> {
        let g = ((p + 1.0) * 0.5 * self.res as f32).floor();
        let c = g.as_ivec3();
        (g.is_finite() && c.cmpge(IVec3::ZERO).all() && c.cmplt(IVec3::splat(self.res as i32)).all()).then_some(c)
    }

    /// Whether a normalised point lies in an occupied cell.
    pub fn occupied(&self, p: Vec3) -> bool {
        self.cell_of(p).is_some_and(|c| self.cells[self.index(c)])
    }

    /// Whether cell `c` is occupied.
    pub fn occupied_cell(&self, c: IVec3) -> bool {
        c.cmpge(IVec3::ZERO).all() && c.cmplt(IVec3::splat(self.res as i32)).all() && self.cells[self.index(c)]
    }

    /// Occupied cells.
    pub fn cells(&self) -> impl Iterator<Item = IVec3> + '_ {
        let r = self.res as i32;
        (0..r * r * r).map(move |i| IVec3::new(i % r, (i / r) % r, i / (r * r))).filter(|&c| self.occupied_cell(c))
    }

    /// The occupied stretches `[t0, t1]` of a ray inside the cube, marched at half a cell.
    pub fn segments(&self, o: Vec3, d: Vec3) -> Vec<(f32, f32)> {
        let mut out: Vec<(f32, f32)> = Vec::new();
        let Some((t0, t1)) = ray_cube(o, d) else {
            return out;
        };
        let step = 0.5 * self.cell();
        let mut t = t0;
        while t < t1 {
            let te = (t + step).min(t1);
            if self.occupied(o + d * (0.5 * (t + te))) {
                match out.last_mut() {
                    Some(last) if last.1 >= t => last.1 = te,
                    _ => out.push((t, te)),
                }
            }
            t = te;
        }
        out
    }
}

/// A scene loaded for training.
#[derive(Debug, Clone)]
pub struct TrainData {
    /// The rays.
    pub rays: Rays,
    /// World <-> normalised.
    pub bounds: Bounds,
    /// Where the surface may be.
    pub occupancy: Occupancy,
    /// Frames read.
    pub frames: usize,
    /// Whether every frame had usable normals.
    pub has_normals: bool,
    /// Frames whose `normals/` file held no usable normal (NaN, infinite or zero wherever the
    /// depth is valid): they count as without normals.
    pub unusable_normals: Vec<String>,
}

impl TrainData {
    /// A hash of everything trained on (rays, bounds, frame count), so a checkpoint is resumed
    /// only with the input it was written for.
    pub fn fingerprint(&self) -> u64 {
        use dens3r_io::hash::{fnv1a, fnv1a_update};
        let r = &self.rays;
        let mut h = fnv1a(&(self.frames as u64).to_le_bytes(), r.len() as u64);
        // Streamed value by value: no copy of the arrays.
        for i in 0..r.len() {
            let (o, d, n, c) = (r.origin[i], r.dir[i], r.normal[i], r.color[i]);
            for v in [o.x, o.y, o.z, d.x, d.y, d.z, r.dist[i], n.x, n.y, n.z, c[0], c[1], c[2]] {
                h = fnv1a_update(h, &v.to_le_bytes());
            }
            h = fnv1a_update(h, &r.frame[i].to_le_bytes());
        }
        fnv1a_update(h, &serde_json::to_vec(&self.bounds).unwrap_or_default())
    }

    /// The default mesh voxel (also the TSDF start's): a quarter of an occupancy cell, in world
    /// units (1/256 of the bounding cube's side).
    pub fn default_voxel(&self) -> f32 {
        (self.occupancy.cell() as f64 * self.bounds.scale / 4.0) as f32
    }
}

/// Occupancy grid resolution over the normalised cube.
pub const OCCUPANCY_RES: usize = 128;

/// Reads every frame's depth (masked by `masks/`), normals and image into rays.
pub fn load_scene(scene: &Scene) -> Result<TrainData, NsdfError> {
    let root = scene.root().display().to_string();
    let mut world_pts: Vec<DVec3> = Vec::new();
    struct Raw {
        frame: u32,
        origin: DVec3,
        dir: DVec3,
        dist: f64,
        normal: DVec3,
        color: [f32; 3],
    }
    let mut raw: Vec<Raw> = Vec::new();
    let mut has_normals = true;
    let mut unusable_normals = Vec::new();
    for (fi, f) in scene.frames().iter().enumerate() {
        let cam = f.camera();
        let bad = |e: dens3r_scene::SceneError| NsdfError::Scene(format!("{root}: frame '{}': {e}", f.name));
        let Some(depth) = scene.depth(f).map_err(bad)? else {
            return Err(NsdfError::Scene(format!(
                "{root}: frame '{}' has no depth/{}.npy: the neural SDF needs depth (run dens3r predict or reconstruct first)",
                f.name, f.name
            )));
        };
        let normals = scene.normals(f).map_err(bad)?;
        has_normals &= normals.is_some();
        let before = raw.len();
        let mut usable = 0usize;
        let mask = scene.mask(f).map_err(bad)?;
        let image = scene.image(f).map_err(bad)?;
        let rot = glam::DMat3::from_mat4(cam.cam_to_world);
        let origin = cam.center();
        for y in 0..depth.height() {
            for x in 0..depth.width() {
                let z = *depth.get(x, y) as f64;
                if !(z.is_finite() && z > 0.0) || mask.as_ref().is_some_and(|m| !*m.get(x, y)) {
                    continue;
                }
                let ray_c = cam.intrinsics.unproject(x as f64, y as f64);
                let p_w = cam.cam_to_world.transform_point3(ray_c * z);
                let dir = (p_w - origin).normalize();
                let normal = match &normals {
                    Some(n) => {
                        let n = n.get(x, y).as_dvec3();
                        if n.length_squared() > 0.25 {
                            usable += 1;
                            (rot * n).normalize()
                        } else {
                            DVec3::ZERO
                        }
                    }
                    None => DVec3::ZERO,
                };
                let px = image.get_pixel(x as u32, y as u32).0;
                raw.push(Raw {
                    frame: fi as u32,
                    origin,
                    dir,
                    dist: (p_w - origin).length(),
                    normal,
                    color: px.map(|c| c as f32 / 255.0),
                });
                world_pts.push(p_w);
            }
        }
        if normals.is_some() && usable == 0 && raw.len() > before {
            has_normals = false;
            unusable_normals.push(f.name.clone());
        }
    }
    if raw.len() < 100 {
        return Err(NsdfError::Scene(format!(
            "{root}: only {} pixels with valid depth in {} frames: nothing to fit a surface to",
            raw.len(),
            scene.frames().len()
        )));
    }
    // Robust extent: 0.5 / 99.5 percentiles per axis, 10% margin, as a cube.
    let mut lo = DVec3::ZERO;
    let mut hi = DVec3::ZERO;
    for a in 0..3 {
        let mut v: Vec<f64> = world_pts.iter().map(|p| p[a]).collect();
        v.sort_by(f64::total_cmp);
        lo[a] = v[v.len() / 200];
        hi[a] = v[v.len() - 1 - v.len() / 200];
    }
    let center = 0.5 * (lo + hi);
    let scale = (0.5 * (hi - lo)).max_element().max(1e-6) * 1.1;
    let bounds = Bounds { center: center.to_array(), scale };
    let stride = (world_pts.len() / 2_000_000).max(1);
    let occupancy =
        Occupancy::from_points(world_pts.iter().step_by(stride).map(|p| bounds.to_unit(*p)), OCCUPANCY_RES, 1);
    let mut rays = Rays::default();
    for r in raw {
        rays.frame.push(r.frame);
        rays.origin.push(bounds.to_unit(r.origin));
        rays.dir.push(r.dir.as_vec3());
        rays.dist.push((r.dist / scale) as f32);
        rays.normal.push(r.normal.as_vec3());
        rays.color.push(r.color);
    }
    Ok(TrainData { rays, bounds, occupancy, frames: scene.frames().len(), has_normals, unusable_normals })
}
