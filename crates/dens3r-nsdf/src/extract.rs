//! Mesh extraction: the field's SDF sampled at voxel centres of 8^3 blocks covering the occupied
//! cells (the space near the observed surface), stored in a [`VoxelBlockGrid`] and meshed by
//! dens3r-fusion's crack-free marching cubes, with colours from the colour branch.

use crate::data::{Bounds, Occupancy};
use crate::field::{encode, FieldConfig, Params};
use crate::NsdfError;
use burn::tensor::activation::sigmoid;
use burn::tensor::Device;
use dens3r_fusion::extract::{component_filter, filter_triangles};
use dens3r_fusion::grid::{block_voxel, Block, GridSpec, VoxelBlockGrid, BLOCK, BLOCK_VOXELS};
use dens3r_fusion::{extract_mesh, ExtractOptions};
use dens3r_mesh::TriMesh;
use glam::{DVec3, IVec3, Vec3};
use std::collections::BTreeSet;

/// Points per field evaluation.
const CHUNK: usize = 1 << 16;

/// Samples the field into a sparse grid of world voxel size `voxel` (truncation 4 voxels).
pub fn sample_grid(
    table: &[f32],
    params: &Params,
    cfg: &FieldConfig,
    bounds: &Bounds,
    occupancy: &Occupancy,
    voxel: f32,
    budget_bytes: Option<usize>,
) -> Result<VoxelBlockGrid, NsdfError> {
    let spec = GridSpec { voxel, trunc: 4.0 * voxel, color: cfg.color };
    let mut grid = VoxelBlockGrid::new(spec).map_err(|e| NsdfError::Options(e.to_string()))?;
    let block = voxel as f64 * BLOCK as f64;
    let cell = occupancy.cell() as f64 * bounds.scale;
    let mut keys = BTreeSet::new();
    for c in occupancy.cells() {
        let lo = bounds.to_world(c.as_vec3() * occupancy.cell() - 1.0);
        let hi = lo + DVec3::splat(cell);
        let (a, b) = ((lo / block).floor().as_ivec3(), (hi / block).floor().as_ivec3());
        for z in a.z..=b.z {
            for y in a.y..=b.y {
                for x in a.x..=b.x {
                    keys.insert((z, y, x));
                }
            }
        }
    }
    if let Some(budget) = budget_bytes {
        let need = keys.len() * spec.block_bytes();
        if need > budget {
            return Err(NsdfError::Options(format!(
                "the mesh grid would need {:.0} MB ({} blocks) at voxel {voxel}, over the {:.0} MB budget: use a larger --voxel",
                need as f64 / 1e6,
                keys.len(),
                budget as f64 / 1e6
            )));
        }
    }
    // Voxels count as observed within reach of an occupied cell, so that a voxel coarser than
    // the cells still has all eight cube corners observed across the surface.
    let reach = ((voxel as f64 * 3f64.sqrt()) / cell).ceil() as i32;
    let observed = occupancy.dilated(reach);
    let keys: Vec<IVec3> = keys.into_iter().map(|(z, y, x)| IVec3::new(x, y, z)).collect();
    let mut world = Vec::with_capacity(keys.len() * BLOCK_VOXELS);
    for k in &keys {
        for i in 0..BLOCK_VOXELS {
            world.push((block_voxel(*k, i).as_dvec3() + 0.5) * voxel as f64);
        }
    }
    let unit: Vec<Vec3> = world.iter().map(|p| bounds.to_unit(*p)).collect();
    let mask = vec![1.0; cfg.levels];
    let mut sdf = Vec::with_capacity(unit.len());
    let mut rgb = Vec::new();
    for chunk in unit.chunks(CHUNK) {
        let out = params.forward(cfg, table, encode(cfg, chunk), &mask, false).out;
        let n = chunk.len();
        sdf.extend(crate::field::to_vec(out.clone().slice([0..n, 0..1])));
        if cfg.color {
            rgb.extend(crate::field::to_vec(sigmoid(out.slice([0..n, 1..4]))));
        }
    }
    let trunc = spec.trunc as f64;
    for (bi, k) in keys.iter().enumerate() {
        let mut b = Block::new(cfg.color);
        for i in 0..BLOCK_VOXELS {
            let j = bi * BLOCK_VOXELS + i;
            if observed.occupied(unit[j]) {
                b.tsdf[i] = ((sdf[j] as f64 * bounds.scale) / trunc).clamp(-1.0, 1.0) as f32;
                b.weight[i] = 1.0;
                if cfg.color {
                    b.color[i] = [rgb[3 * j] * 255.0, rgb[3 * j + 1] * 255.0, rgb[3 * j + 2] * 255.0];
                }
            }
        }
        grid.insert_block(*k, b).map_err(|e| NsdfError::Options(e.to_string()))?;
    }
    Ok(grid)
}

/// Extracts the zero level set of a trained field (parameters on any device) as a world mesh.
pub fn extract(
    values: &[(Vec<f32>, [usize; 2])],
    cfg: &FieldConfig,
    bounds: &Bounds,
    occupancy: &Occupancy,
    voxel: f32,
    device: &Device,
    opts: &ExtractOptions,
) -> Result<TriMesh, NsdfError> {
    let (table, params) = Params::from_values(values, device, false);
    let grid = sample_grid(&table, &params, cfg, bounds, occupancy, voxel, Some(4 << 30))?;
    let mesh = extract_mesh(&grid, &ExtractOptions { min_component_triangles: 0, ..opts.clone() });
    // The grid reaches past the occupied cells so coarse voxels see the surface; zero crossings
    // out there are the field's guesses away from any observation: keep triangles whose centre
    // lies in an occupied cell.
    let keep: Vec<bool> = (0..mesh.indices.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle(t);
            occupancy.occupied(bounds.to_unit(((a + b + c) / 3.0).as_dvec3()))
        })
        .collect();
    let mut mesh = filter_triangles(&mesh, &keep);
    if opts.min_component_triangles > 0 {
        let keep = component_filter(&mesh, opts.min_component_triangles);
        mesh = filter_triangles(&mesh, &keep);
    }
    Ok(mesh)
}
