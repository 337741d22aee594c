//! Storage of a sparse voxel grid, apart from how it is filled (Open3D's `VoxelBlockGrid`):
//! 8^3-voxel blocks of truncated signed distance, weight and optional colour, allocated only
//! where something is stored and found through a hash of their block coordinates. TSDF
//! integration ([`crate::tsdf`]) fills one from depth maps, the neural SDF fills one from its
//! field; marching cubes ([`crate::extract`]) meshes either.

use crate::error::FusionError;
use glam::{IVec3, Vec3};
use std::collections::HashMap;

/// A fast hasher for integer keys (block coordinates, grid-edge keys): a multiply-rotate per
/// word and a splitmix64 finish instead of SipHash, which dominated block lookups and vertex
/// de-duplication.
#[derive(Default, Clone, Copy)]
pub struct IntHasher(u64);

impl std::hash::Hasher for IntHasher {
    fn finish(&self) -> u64 {
        // splitmix64's finaliser: every input bit reaches the low bits the table indexes by.
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
    fn write_u32(&mut self, v: u32) {
        self.write_u64(v as u64);
    }
    fn write_i32(&mut self, v: i32) {
        self.write_u64(v as u32 as u64);
    }
}

/// `HashMap` with [`IntHasher`].
pub type IntMap<K, V> = HashMap<K, V, std::hash::BuildHasherDefault<IntHasher>>;

/// Voxels per block side.
pub const BLOCK: i32 = 8;
/// Voxels per block.
pub const BLOCK_VOXELS: usize = (BLOCK * BLOCK * BLOCK) as usize;

/// One 8^3 block: TSDF in `[-1, 1]` (units of `trunc`), weights and colours (0..255 floats),
/// voxel `(x, y, z)` at index `x + 8 y + 64 z`.
#[derive(Debug, Clone)]
pub struct Block {
    /// Normalised truncated signed distance (positive in front of the surface).
    pub tsdf: Vec<f32>,
    /// Accumulated weight; 0 = never observed.
    pub weight: Vec<f32>,
    /// Average colour, empty when colour is off.
    pub color: Vec<[f32; 3]>,
}

impl Block {
    /// An unobserved block (TSDF 1, weight 0, black if `color`).
    pub fn new(color: bool) -> Self {
        Self {
            tsdf: vec![1.0; BLOCK_VOXELS],
            weight: vec![0.0; BLOCK_VOXELS],
            color: if color { vec![[0.0; 3]; BLOCK_VOXELS] } else { Vec::new() },
        }
    }
}

/// Global voxel coordinate of entry `i` of the block at `key` (layout `x + 8 y + 64 z`).
pub fn block_voxel(key: IVec3, i: usize) -> IVec3 {
    let i = i as i32;
    key * BLOCK + IVec3::new(i % BLOCK, (i / BLOCK) % BLOCK, i / (BLOCK * BLOCK))
}

/// A grid's layout and what it stores.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridSpec {
    /// Voxel edge length.
    pub voxel: f32,
    /// The distance one unit of stored TSDF stands for (values are in `[-1, 1]` of it).
    pub trunc: f32,
    /// Whether blocks hold colour.
    pub color: bool,
}

impl GridSpec {
    /// Bytes one block takes.
    pub fn block_bytes(&self) -> usize {
        BLOCK_VOXELS * (8 + if self.color { 12 } else { 0 }) + 64
    }
}

/// Sparse voxel blocks under their block coordinates, in insertion order.
#[derive(Debug, Clone)]
pub struct VoxelBlockGrid {
    spec: GridSpec,
    blocks: Vec<Block>,
    keys: Vec<IVec3>,
    index: IntMap<IVec3, u32>,
}

impl VoxelBlockGrid {
    /// An empty grid; the voxel must be a positive length and `trunc` at least one voxel.
    pub fn new(spec: GridSpec) -> Result<Self, FusionError> {
        if !(spec.voxel.is_finite() && spec.voxel > 0.0) {
            return Err(FusionError::Param(format!("voxel size {} must be a positive length", spec.voxel)));
        }
        if !(spec.trunc.is_finite() && spec.trunc >= spec.voxel) {
            return Err(FusionError::Param(format!(
                "truncation {} must be at least one voxel ({})",
                spec.trunc, spec.voxel
            )));
        }
        Ok(Self { spec, blocks: Vec::new(), keys: Vec::new(), index: IntMap::default() })
    }

    /// Layout and contents.
    pub fn spec(&self) -> &GridSpec {
        &self.spec
    }

    /// Allocated blocks.
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Bytes held by the blocks.
    pub fn memory_bytes(&self) -> usize {
        self.blocks.len() * self.spec.block_bytes()
    }

    /// The block at a block coordinate.
    pub fn block(&self, key: IVec3) -> Option<&Block> {
        self.index.get(&key).map(|&i| &self.blocks[i as usize])
    }

    /// All blocks with their block coordinates, in the order they were added.
    pub fn blocks(&self) -> impl Iterator<Item = (IVec3, &Block)> {
        self.keys.iter().copied().zip(&self.blocks)
    }

    /// Whether a block exists at `key`.
    pub fn contains(&self, key: IVec3) -> bool {
        self.index.contains_key(&key)
    }

    /// The slot of the block at `key`, allocating an unobserved one at the end if needed.
    pub fn slot_or_insert(&mut self, key: IVec3) -> u32 {
        let (blocks, keys, color) = (&mut self.blocks, &mut self.keys, self.spec.color);
        *self.index.entry(key).or_insert_with(|| {
            keys.push(key);
            blocks.push(Block::new(color));
            (blocks.len() - 1) as u32
        })
    }

    /// The slot of the block at `key`, if allocated.
    pub fn slot(&self, key: IVec3) -> Option<u32> {
        self.index.get(&key).copied()
    }

    /// Block coordinate of a slot.
    pub fn key(&self, slot: u32) -> IVec3 {
        self.keys[slot as usize]
    }

    /// Blocks by slot with their coordinates, for in-place updates.
    pub fn slots_mut(&mut self) -> (&[IVec3], &mut [Block]) {
        (&self.keys, &mut self.blocks)
    }

    /// Puts a block filled by other means than integration (e.g. an SDF sampled from a neural
    /// field) at block coordinate `key`, replacing any block there. Its layers must hold
    /// [`BLOCK_VOXELS`] entries (colour: that many, or none when the grid has no colour).
    pub fn insert_block(&mut self, key: IVec3, block: Block) -> Result<(), FusionError> {
        let colors = if self.spec.color { BLOCK_VOXELS } else { 0 };
        if block.tsdf.len() != BLOCK_VOXELS || block.weight.len() != BLOCK_VOXELS || block.color.len() != colors {
            return Err(FusionError::Param(format!(
                "block {key} has {} / {} / {} tsdf / weight / colour entries, expected {BLOCK_VOXELS} / {BLOCK_VOXELS} / {colors}",
                block.tsdf.len(),
                block.weight.len(),
                block.color.len()
            )));
        }
        match self.index.get(&key) {
            Some(&slot) => self.blocks[slot as usize] = block,
            None => {
                self.index.insert(key, self.blocks.len() as u32);
                self.keys.push(key);
                self.blocks.push(block);
            }
        }
        Ok(())
    }

    /// World position of the centre of global voxel `v`.
    pub fn voxel_center(&self, v: IVec3) -> Vec3 {
        (v.as_vec3() + 0.5) * self.spec.voxel
    }

    /// Normalised TSDF, weight and colour of global voxel `v`, if its block exists.
    pub fn voxel(&self, v: IVec3) -> Option<(f32, f32, [f32; 3])> {
        let key = v.div_euclid(IVec3::splat(BLOCK));
        let b = self.block(key)?;
        let l = v - key * BLOCK;
        let i = (l.x + BLOCK * (l.y + BLOCK * l.z)) as usize;
        Some((b.tsdf[i], b.weight[i], b.color.get(i).copied().unwrap_or([0.0; 3])))
    }
}
