//! GPU TSDF integration through wgpu (Vulkan, Metal, DX12): the voxel pool lives on the GPU and
//! one WGSL compute pass (`shaders/tsdf_integrate.wgsl`) updates the touched blocks of each
//! frame. Block allocation (the hash map, the budget) stays on the host in [`SparseTsdf`]'s grid, so
//! both paths allocate the same blocks; [`GpuTsdf::finish`] copies the pool back for extraction.
//! The result equals the CPU path's within float tolerance (`tests/it/gpu.rs`).

use crate::tsdf::{block_base, FrameInput, FusionError, SparseTsdf, TsdfParams, BLOCK_VOXELS};
use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3};
use wgpu::util::DeviceExt;

const SHADER: &str = include_str!("../../../shaders/tsdf_integrate.wgsl");
const WORKGROUP: u32 = 256;

/// The shader's `Params` uniform.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    ax: [f32; 4],
    ay: [f32; 4],
    az: [f32; 4],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
    n_blocks: u32,
    flags: u32,
    trunc: f32,
    max_weight: f32,
    dmin: f32,
    dmax: f32,
}

/// The voxel pool on the GPU: `(tsdf, weight)` and colour per voxel, slot-major.
struct Pool {
    vox: wgpu::Buffer,
    col: wgpu::Buffer,
    capacity: usize,
}

/// A TSDF volume integrated on the GPU.
pub struct GpuTsdf {
    grid: SparseTsdf,
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    pool: Pool,
    adapter: String,
    max_buffer: u64,
}

fn gpu_err(m: impl std::fmt::Display) -> FusionError {
    FusionError::Gpu(m.to_string())
}

/// Bytes per voxel of the pool's buffers.
fn voxel_bytes(color: bool) -> (u64, u64) {
    (8, if color { 12 } else { 4 })
}

impl GpuTsdf {
    /// An empty volume on the first GPU adapter wgpu finds (high-performance preferred; set
    /// `WGPU_ADAPTER_NAME` or `WGPU_BACKEND` to choose). Errors when there is none.
    pub fn new(params: TsdfParams) -> Result<Self, FusionError> {
        let grid = SparseTsdf::new(params)?;
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| {
            gpu_err(format!(
                "no GPU adapter found ({e}): install a Vulkan driver (e.g. Debian's mesa-vulkan-drivers for a software one) or fuse without --gpu"
            ))
        })?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let max_buffer = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("dens3r-tsdf"),
            required_limits: limits,
            ..Default::default()
        }))
        .map_err(|e| gpu_err(format!("could not open GPU '{}': {e}", info.name)))?;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("tsdf_integrate.wgsl"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("tsdf_integrate"),
            layout: None,
            module: &module,
            entry_point: Some("integrate"),
            compilation_options: Default::default(),
            cache: None,
        });
        let pool = Self::make_pool(&device, 0, grid.params().color);
        let adapter = format!("{} ({:?})", info.name, info.backend);
        Ok(Self { grid, device, queue, pipeline, pool, adapter, max_buffer })
    }

    /// The adapter in use, e.g. `"llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)"`.
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// The host-side grid (block index; voxel data is stale until [`GpuTsdf::finish`]).
    pub fn grid(&self) -> &SparseTsdf {
        &self.grid
    }

    fn make_pool(device: &wgpu::Device, capacity: usize, color: bool) -> Pool {
        let (vb, cb) = voxel_bytes(color);
        let n = (capacity.max(1) * BLOCK_VOXELS) as u64;
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        // Fresh buffers are zeroed: weight 0 marks a voxel never observed.
        let buf = |label, size| {
            device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size, usage, mapped_at_creation: false })
        };
        Pool { vox: buf("tsdf-vox", n * vb), col: buf("tsdf-col", n * cb), capacity }
    }

    /// Grows the pool to hold `blocks`, copying what it holds.
    fn reserve(&mut self, blocks: usize) -> Result<(), FusionError> {
        if blocks <= self.pool.capacity {
            return Ok(());
        }
        let color = self.grid.params().color;
        let (vb, cb) = voxel_bytes(color);
        let cap = blocks.max(self.pool.capacity * 3 / 2).max(1024);
        let limit_blocks = (self.max_buffer / (BLOCK_VOXELS as u64 * vb.max(cb))) as usize;
        if blocks > limit_blocks {
            return Err(gpu_err(format!(
                "the grid needs {blocks} blocks but this GPU's buffers hold at most {limit_blocks} ({} MB per buffer): use a larger --voxel or a smaller --max-depth, or fuse on the CPU (without --gpu)",
                self.max_buffer >> 20
            )));
        }
        let cap = cap.min(limit_blocks);
        let new = Self::make_pool(&self.device, cap, color);
        let used = (self.pool.capacity * BLOCK_VOXELS) as u64;
        if used > 0 {
            let mut enc = self.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&self.pool.vox, 0, &new.vox, 0, used * vb);
            enc.copy_buffer_to_buffer(&self.pool.col, 0, &new.col, 0, used * cb);
            self.queue.submit([enc.finish()]);
        }
        self.pool = new;
        Ok(())
    }

    /// Integrates one frame: blocks are allocated on the host, the update runs on the GPU
    /// (asynchronously; [`GpuTsdf::finish`] waits).
    pub fn integrate(&mut self, f: &FrameInput) -> Result<(), FusionError> {
        let Some(touched) = self.grid.allocate_frame(f)? else {
            return Ok(());
        };
        self.reserve(self.grid.block_count())?;
        let p = self.grid.params().clone();
        let (w, h) = (f.depth.width(), f.depth.height());
        let k = f.camera.intrinsics;
        let w2c: Mat4 = dens3r_geom::camera::rigid_inverse(&f.camera.cam_to_world).as_mat4();
        let step = |axis: Vec3| w2c.transform_vector3(axis * p.voxel).extend(0.0).to_array();

        // Per touched block: camera-frame centre of its first voxel and its slot.
        let blocks: Vec<[f32; 4]> = touched
            .iter()
            .map(|&slot| block_base(self.grid.key(slot), &w2c, p.voxel).extend(f32::from_bits(slot)).to_array())
            .collect();
        let depth: Vec<f32> = f.depth.data().iter().map(|&d| if p.depth_valid(d) { d } else { -1.0 }).collect();
        let weight: Vec<f32> = match f.weight {
            Some(wt) => wt.data().iter().map(|&x| if x.is_finite() && x > 0.0 { x } else { 0.0 }).collect(),
            None => vec![0.0],
        };
        let color = f.color.filter(|_| p.color);
        let rgb: Vec<u32> = match color {
            Some(c) => c.pixels().map(|px| px[0] as u32 | (px[1] as u32) << 8 | (px[2] as u32) << 16).collect(),
            None => vec![0],
        };
        let params = Params {
            ax: step(Vec3::X),
            ay: step(Vec3::Y),
            az: step(Vec3::Z),
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
            width: w as u32,
            height: h as u32,
            n_blocks: blocks.len() as u32,
            flags: f.weight.is_some() as u32 | (color.is_some() as u32) << 1,
            trunc: p.trunc,
            max_weight: p.max_weight,
            dmin: p.depth_range.0,
            dmax: p.depth_range.1,
        };

        let dev = &self.device;
        let init = |label, contents: &[u8], usage| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents, usage })
        };
        let storage = wgpu::BufferUsages::STORAGE;
        let uniform = init("params", bytemuck::bytes_of(&params), wgpu::BufferUsages::UNIFORM);
        let blocks_buf = init("blocks", bytemuck::cast_slice(&blocks), storage);
        let depth_buf = init("depth", bytemuck::cast_slice(&depth), storage);
        let weight_buf = init("weight", bytemuck::cast_slice(&weight), storage);
        let rgb_buf = init("rgb", bytemuck::cast_slice(&rgb), storage);
        let layout = self.pipeline.get_bind_group_layout(0);
        let entries: Vec<wgpu::BindGroupEntry> =
            [&uniform, &blocks_buf, &depth_buf, &weight_buf, &rgb_buf, &self.pool.vox, &self.pool.col]
                .iter()
                .enumerate()
                .map(|(i, b)| wgpu::BindGroupEntry { binding: i as u32, resource: b.as_entire_binding() })
                .collect();
        let bind =
            dev.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout: &layout, entries: &entries });
        let groups = (blocks.len() * BLOCK_VOXELS).div_ceil(WORKGROUP as usize) as u32;
        let max_dim = dev.limits().max_compute_workgroups_per_dimension;
        let (gx, gy) = (groups.min(max_dim), groups.div_ceil(max_dim));
        let mut enc = dev.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        self.queue.submit([enc.finish()]);
        self.grid.count_frame();
        Ok(())
    }

    /// Waits for the GPU, copies the voxel pool back into the host grid and returns it, ready
    /// for [`crate::extract_mesh`].
    pub fn finish(self) -> Result<SparseTsdf, FusionError> {
        let Self { mut grid, device, queue, pool, .. } = self;
        let n = (grid.block_count() * BLOCK_VOXELS) as u64;
        let color = grid.params().color;
        let (vb, cb) = voxel_bytes(color);
        let blocks = grid.blocks_mut();
        // Voxels arrive slot-major, so voxel v is voxel v % 512 of block v / 512.
        let mut v = 0;
        read(&device, &queue, &pool.vox, n * vb, |bytes| {
            for tw in bytes.chunks_exact(8) {
                let [t, w] = bytemuck::pod_read_unaligned::<[f32; 2]>(tw);
                let (b, j) = (&mut blocks[v / BLOCK_VOXELS], v % BLOCK_VOXELS);
                // Never-observed voxels keep the CPU path's initial distance (+1).
                b.tsdf[j] = if w > 0.0 { t } else { 1.0 };
                b.weight[j] = w;
                v += 1;
            }
        })?;
        if color {
            let mut v = 0;
            read(&device, &queue, &pool.col, n * cb, |bytes| {
                for c in bytes.chunks_exact(12) {
                    blocks[v / BLOCK_VOXELS].color[v % BLOCK_VOXELS] = bytemuck::pod_read_unaligned::<[f32; 3]>(c);
                    v += 1;
                }
            })?;
        }
        Ok(grid)
    }
}

/// Reads the first `bytes` of a pool buffer back in chunks (whole voxels each), handing each to
/// `sink`.
fn read(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    src: &wgpu::Buffer,
    bytes: u64,
    mut sink: impl FnMut(&[u8]),
) -> Result<(), FusionError> {
    const CHUNK: u64 = 48 << 20; // a multiple of both voxel sizes (8 and 12 bytes)
    let staging = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: CHUNK.min(bytes.max(4)),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut off = 0;
    while off < bytes {
        let len = CHUNK.min(bytes - off);
        let mut enc = device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, off, &staging, 0, len);
        queue.submit([enc.finish()]);
        let slice = staging.slice(..len);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        device.poll(wgpu::PollType::wait_indefinitely()).map_err(gpu_err)?;
        rx.recv().map_err(gpu_err)?.map_err(gpu_err)?;
        sink(&slice.get_mapped_range().map_err(gpu_err)?);
        staging.unmap();
        off += len;
    }
    Ok(())
}
