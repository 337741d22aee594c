//! Sparse voxel-block TSDF integration (Open3D's `VoxelBlockGrid` / KinectFusion scheme):
//! a hash map of 8^3-voxel blocks allocated only around observed surfaces, projective
//! truncated signed distances averaged with weights, optional colour. Integration of one frame
//! is rayon-parallel over the blocks it touches.

pub use crate::error::FusionError;
pub use crate::grid::{block_voxel, Block, IntHasher, IntMap, BLOCK, BLOCK_VOXELS};
use crate::grid::{GridSpec, VoxelBlockGrid};
use dens3r_geom::{PinholeCamera, Raster, Vec3};
use glam::{IVec3, Mat4};
use rayon::prelude::*;
use std::collections::HashSet;

/// Fusion parameters (lengths in scene units, metres for our rendered scenes).
#[derive(Debug, Clone, PartialEq)]
pub struct TsdfParams {
    /// Voxel edge length.
    pub voxel: f32,
    /// Truncation distance (Open3D's `sdf_trunc`); default 4 voxels.
    pub trunc: f32,
    /// Largest accumulated weight per voxel (running-average window).
    pub max_weight: f32,
    /// Depth range kept, `[min, max]`; pixels outside are ignored.
    pub depth_range: (f32, f32),
    /// Integrate colour.
    pub color: bool,
    /// Memory budget for the grid, bytes; `None` = unlimited.
    pub budget_bytes: Option<usize>,
}

impl TsdfParams {
    /// Defaults for a voxel size: truncation 4 voxels, max weight 1000 (effectively a plain
    /// average), depth in `[0.05, 10]`, colour on, no budget.
    pub fn new(voxel: f32) -> Self {
        Self {
            voxel,
            trunc: 4.0 * voxel,
            max_weight: 1000.0,
            depth_range: (0.05, 10.0),
            color: true,
            budget_bytes: None,
        }
    }

    fn check(&self) -> Result<(), FusionError> {
        let bad = |m: String| Err(FusionError::Param(m));
        if !(self.voxel.is_finite() && self.voxel > 0.0) {
            return bad(format!("voxel size {} must be a positive length", self.voxel));
        }
        if !(self.trunc.is_finite() && self.trunc >= self.voxel) {
            return bad(format!("truncation {} must be at least one voxel ({})", self.trunc, self.voxel));
        }
        if self.max_weight.is_nan() || self.max_weight <= 0.0 {
            return bad(format!("max weight {} must be positive", self.max_weight));
        }
        let (a, b) = self.depth_range;
        if !(a.is_finite() && b.is_finite() && 0.0 <= a && a < b) {
            return bad(format!("depth range [{a}, {b}] must satisfy 0 <= min < max"));
        }
        Ok(())
    }

    /// Whether a depth is used: finite and inside `depth_range`.
    #[inline]
    pub fn depth_valid(&self, d: f32) -> bool {
        d.is_finite() && d >= self.depth_range.0 && d <= self.depth_range.1
    }

    /// Bytes one block takes.
    pub fn block_bytes(&self) -> usize {
        self.grid_spec().block_bytes()
    }

    /// The grid these parameters fill.
    pub fn grid_spec(&self) -> GridSpec {
        GridSpec { voxel: self.voxel, trunc: self.trunc, color: self.color }
    }
}

/// One frame to integrate: depth (z, 0 or NaN = invalid) with its camera, and optional colour
/// and per-pixel weights (e.g. from confidence or the angle between normal and ray).
pub struct FrameInput<'a> {
    /// Frame name (for errors).
    pub name: &'a str,
    /// Camera (OpenCV frame, camera-to-world pose).
    pub camera: &'a PinholeCamera,
    /// Depth map.
    pub depth: &'a Raster<f32>,
    /// Colour image of the same size.
    pub color: Option<&'a image::RgbImage>,
    /// Per-pixel observation weights in `[0, inf)`; 0 skips the pixel.
    pub weight: Option<&'a Raster<f32>>,
}

/// TSDF integration into a [`VoxelBlockGrid`]: the grid with the parameters that fill it and
/// the number of frames integrated.
pub struct SparseTsdf {
    params: TsdfParams,
    grid: VoxelBlockGrid,
    frames: usize,
}

/// Per-pixel weights that favour surfaces seen head-on: `cos^2` of the angle between the
/// camera-frame normal and the viewing ray (0 where the normal is invalid). The projective
/// distance `depth - z` overstates the true distance by `1 / cos` at grazing angles, which
/// biases the fused surface and its normals; on a fused sphere this weighting takes the median
/// vertex-normal error from 4.4 to 1.6 deg and the mean position error from 0.08 to 0.03 voxels
/// (`tests/it/fusion.rs`).
pub fn angle_weights(normals: &Raster<Vec3>, camera: &PinholeCamera) -> Raster<f32> {
    let k = camera.intrinsics;
    Raster::from_fn(normals.width(), normals.height(), |x, y| {
        let n = *normals.get(x, y);
        if !n.is_finite() || n.length_squared() < 0.5 {
            return 0.0;
        }
        let ray = Vec3::new(((x as f64 - k.cx) / k.fx) as f32, ((y as f64 - k.cy) / k.fy) as f32, 1.0).normalize();
        n.dot(ray).powi(2)
    })
}

/// Camera-frame centre of the first voxel of block `key`, the start of the incremental voxel
/// positions; one expression for the CPU update and the GPU upload, so both start identically.
#[inline]
pub(crate) fn block_base(key: IVec3, w2c: &Mat4, voxel: f32) -> Vec3 {
    w2c.transform_point3(((key * BLOCK).as_vec3() + 0.5) * voxel)
}

impl SparseTsdf {
    /// An empty volume.
    pub fn new(params: TsdfParams) -> Result<Self, FusionError> {
        params.check()?;
        let grid = VoxelBlockGrid::new(params.grid_spec())?;
        Ok(Self { params, grid, frames: 0 })
    }

    /// The parameters.
    pub fn params(&self) -> &TsdfParams {
        &self.params
    }

    /// The grid integrated into (what extraction meshes).
    pub fn grid(&self) -> &VoxelBlockGrid {
        &self.grid
    }

    /// Allocated blocks.
    pub fn block_count(&self) -> usize {
        self.grid.block_count()
    }

    /// Frames integrated.
    pub fn frame_count(&self) -> usize {
        self.frames
    }

    /// Bytes held by the blocks.
    pub fn memory_bytes(&self) -> usize {
        self.grid.memory_bytes()
    }

    /// The block at a block coordinate.
    pub fn block(&self, key: IVec3) -> Option<&Block> {
        self.grid.block(key)
    }

    /// All blocks with their block coordinates.
    pub fn blocks(&self) -> impl Iterator<Item = (IVec3, &Block)> {
        self.grid.blocks()
    }

    /// World position of the centre of global voxel `v`.
    pub fn voxel_center(&self, v: IVec3) -> Vec3 {
        self.grid.voxel_center(v)
    }

    /// Normalised TSDF, weight and colour of global voxel `v`, if its block exists.
    pub fn voxel(&self, v: IVec3) -> Option<(f32, f32, [f32; 3])> {
        self.grid.voxel(v)
    }

    /// Integrates one frame.
    pub fn integrate(&mut self, f: &FrameInput) -> Result<(), FusionError> {
        let Some(touched) = self.allocate_frame(f)? else {
            return Ok(()); // nothing valid in this frame
        };
        let mut mask = vec![false; self.grid.block_count()];
        for &slot in &touched {
            mask[slot as usize] = true;
        }
        let p = &self.params;
        let k = f.camera.intrinsics;
        let (fx, fy, cx, cy) = (k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32);
        let w2c: Mat4 = dens3r_geom::camera::rigid_inverse(&f.camera.cam_to_world).as_mat4();
        let valid = |d: f32| p.depth_valid(d);
        let (w, h) = (f.depth.width(), f.depth.height());

        // Update every voxel of the touched blocks.
        let (voxel, trunc, max_w) = (p.voxel, p.trunc, p.max_weight);
        let depth = f.depth.data();
        let weights = f.weight.map(|wt| wt.data());
        let colors = f.color.map(|c| c.as_raw().as_slice());
        // Camera-frame steps of one voxel along x, y, z: positions are updated incrementally.
        let (ax, ay, az) = (
            w2c.transform_vector3(Vec3::X * voxel),
            w2c.transform_vector3(Vec3::Y * voxel),
            w2c.transform_vector3(Vec3::Z * voxel),
        );
        let (wf, hf) = (w as f32 - 0.5, h as f32 - 0.5);
        let (keys, blocks) = self.grid.slots_mut();
        blocks.par_iter_mut().zip(keys).zip(&mask).filter(|(_, &m)| m).for_each(|((block, key), _)| {
            let base = block_base(*key, &w2c, voxel);
            let mut i = 0;
            for z in 0..BLOCK {
                for y in 0..BLOCK {
                    let row = base + az * z as f32 + ay * y as f32;
                    for x in 0..BLOCK {
                        let vi = i;
                        i += 1;
                        let pc = row + ax * x as f32;
                        if pc.z <= 0.0 {
                            continue;
                        }
                        let inv_z = 1.0 / pc.z;
                        let u = fx * pc.x * inv_z + cx;
                        let v = fy * pc.y * inv_z + cy;
                        // Nearest pixel; the range test keeps the truncating casts exact rounding.
                        if !(u >= -0.5 && v >= -0.5 && u < wf && v < hf) {
                            continue;
                        }
                        let idx = (v + 0.5) as usize * w + (u + 0.5) as usize;
                        let d = depth[idx];
                        if !valid(d) {
                            continue;
                        }
                        let sdf = d - pc.z;
                        if sdf < -trunc {
                            continue;
                        }
                        let obs_w = weights.map_or(1.0, |wt| wt[idx]);
                        if !(obs_w > 0.0 && obs_w.is_finite()) {
                            continue;
                        }
                        let obs = (sdf / trunc).min(1.0);
                        let w0 = block.weight[vi];
                        let wn = w0 + obs_w;
                        let inv = 1.0 / wn;
                        block.tsdf[vi] = (block.tsdf[vi] * w0 + obs * obs_w) * inv;
                        if let (Some(px), false) = (colors, block.color.is_empty()) {
                            let c = &px[3 * idx..3 * idx + 3];
                            let bc = &mut block.color[vi];
                            for ch in 0..3 {
                                bc[ch] = (bc[ch] * w0 + c[ch] as f32 * obs_w) * inv;
                            }
                        }
                        block.weight[vi] = wn.min(max_w);
                    }
                }
            }
        });
        self.frames += 1;
        Ok(())
    }

    /// Checks that a frame's layers fit its camera.
    fn check_frame(f: &FrameInput) -> Result<(), FusionError> {
        let (w, h) = (f.depth.width(), f.depth.height());
        let ferr = |m: String| FusionError::Frame(f.name.to_string(), m);
        if (w, h) != (f.camera.width, f.camera.height) {
            return Err(ferr(format!("depth is {w}x{h} but the camera is {}x{}", f.camera.width, f.camera.height)));
        }
        if let Some(c) = f.color {
            if c.dimensions() != (w as u32, h as u32) {
                return Err(ferr(format!("colour image is {}x{}, depth {w}x{h}", c.width(), c.height())));
            }
        }
        if let Some(wt) = f.weight {
            if (wt.width(), wt.height()) != (w, h) {
                return Err(ferr("weight map size differs from the depth".into()));
            }
        }
        Ok(())
    }

    /// Validates a frame, allocates (within the budget) every block its truncation band
    /// touches, and returns the touched blocks' slots in ascending order; `None` when the frame
    /// has no valid depth. Shared by the CPU update and the GPU path.
    pub(crate) fn allocate_frame(&mut self, f: &FrameInput) -> Result<Option<Vec<u32>>, FusionError> {
        Self::check_frame(f)?;
        let (w, h) = (f.depth.width(), f.depth.height());
        let p = &self.params;
        let k = f.camera.intrinsics;
        let (fx, fy, cx, cy) = (k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32);
        let c2w = f.camera.cam_to_world.as_mat4();
        let valid = |d: f32| p.depth_valid(d);

        // 1. Blocks touched by the truncation band of every (sub-sampled) valid pixel.
        let block_len = p.voxel * BLOCK as f32;
        let far = f.depth.data().iter().copied().filter(|&d| valid(d)).fold(0.0f32, f32::max);
        if far == 0.0 {
            return Ok(None);
        }
        // A pixel step that keeps neighbouring samples under half a block apart at the
        // farthest depth, so no block crossed by the band is missed.
        let stride = ((0.5 * block_len * fx.min(fy) / far).floor() as usize).clamp(1, 8);
        let step = p.trunc.min(0.25 * block_len);
        let n_steps = (2.0 * p.trunc / step).ceil() as i32;
        let inv_block = 1.0 / block_len;
        // With a budget, counting stops as soon as one worker has touched more blocks than the
        // whole grid may hold (the union, old blocks included, can only be larger), so a huge
        // truncation band or depth range costs neither the memory nor the time of its full set.
        let max_blocks = p.budget_bytes.map_or(usize::MAX, |b| b / p.block_bytes().max(1));
        let over = std::sync::atomic::AtomicBool::new(false);
        type IntSet = HashSet<IVec3, std::hash::BuildHasherDefault<IntHasher>>;
        let touched: IntSet = (0..h)
            .into_par_iter()
            .step_by(stride)
            .fold(IntSet::default, |mut set, y| {
                if over.load(std::sync::atomic::Ordering::Relaxed) {
                    return set;
                }
                for x in (0..w).step_by(stride) {
                    let d = *f.depth.get(x, y);
                    if !valid(d) || f.weight.is_some_and(|wt| *wt.get(x, y) <= 0.0) {
                        continue;
                    }
                    let ray = Vec3::new((x as f32 - cx) / fx, (y as f32 - cy) / fy, 1.0);
                    for s in 0..=n_steps {
                        let z = d - p.trunc + s as f32 * step;
                        if z <= 0.0 {
                            continue;
                        }
                        let pw = c2w.transform_point3(ray * z);
                        if set.insert((pw * inv_block).floor().as_ivec3()) && set.len() > max_blocks {
                            over.store(true, std::sync::atomic::Ordering::Relaxed);
                            return set;
                        }
                    }
                }
                set
            })
            .reduce(IntSet::default, |mut a, mut b| {
                // Insert the smaller set into the larger.
                if a.len() < b.len() {
                    std::mem::swap(&mut a, &mut b);
                }
                a.extend(b);
                a
            });

        // 2. Allocate, within the budget.
        // In a fixed order (the set's own order follows how the threads split the work), so a
        // grid's block order, which consumers sample by, does not depend on the machine's load.
        let mut new: Vec<IVec3> = touched.iter().copied().filter(|k| !self.grid.contains(*k)).collect();
        new.sort_unstable_by_key(|k| (k.z, k.y, k.x));
        if let Some(budget) = p.budget_bytes {
            let blocks = self.grid.block_count() + new.len();
            let needed = blocks * p.block_bytes();
            if needed > budget || over.load(std::sync::atomic::Ordering::Relaxed) {
                return Err(FusionError::Budget {
                    blocks,
                    needed_mb: needed as f64 / 1e6,
                    budget_mb: budget as f64 / 1e6,
                    at_least: over.load(std::sync::atomic::Ordering::Relaxed),
                });
            }
        }
        for key in new {
            self.grid.slot_or_insert(key);
        }
        let mut slots: Vec<u32> = touched.iter().map(|key| self.grid.slot(*key).expect("allocated")).collect();
        slots.sort_unstable();
        Ok(Some(slots))
    }

    /// Counts a frame integrated elsewhere (the GPU path).
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn count_frame(&mut self) {
        self.frames += 1;
    }

    /// Block coordinate of a slot (the GPU path's upload).
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn key(&self, slot: u32) -> IVec3 {
        self.grid.key(slot)
    }

    /// Mutable blocks (the GPU path's download).
    #[cfg_attr(not(feature = "gpu"), allow(dead_code))]
    pub(crate) fn blocks_mut(&mut self) -> &mut [Block] {
        self.grid.slots_mut().1
    }
}
