//! Mesh decimation for the browser by vertex clustering: vertices snapped to a grid, each
//! cell's vertices merged into their mean (colours averaged), triangles that collapse dropped.
//! Fast and predictable on the large TSDF meshes dens3r writes; the cell is doubled until the
//! triangle budget is met.

use dens3r_mesh::TriMesh;
use glam::{IVec3, Vec3};
use std::collections::HashMap;

/// `mesh` with at most `max_triangles` triangles (the mesh itself when already that small).
pub fn decimate(mesh: &TriMesh, max_triangles: usize) -> TriMesh {
    if mesh.indices.len() <= max_triangles || mesh.positions.is_empty() {
        return mesh.clone();
    }
    let (lo, hi) = mesh
        .positions
        .iter()
        .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    let extent = (hi - lo).max_element().max(1e-9);
    // A closed surface of N triangles on a grid of cell c has about 2 (extent / c)^2 * k
    // triangles; start from that guess and grow.
    let mut cell = extent / (max_triangles as f32 / 4.0).sqrt().max(1.0);
    loop {
        let out = cluster(mesh, lo, cell);
        if out.indices.len() <= max_triangles {
            return out;
        }
        cell *= 1.25;
    }
}

fn cluster(mesh: &TriMesh, origin: Vec3, cell: f32) -> TriMesh {
    let mut ids: HashMap<IVec3, u32> = HashMap::new();
    let mut sum: Vec<(Vec3, [u32; 3], u32)> = Vec::new();
    let remap: Vec<u32> = mesh
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let key = ((*p - origin) / cell).floor().as_ivec3();
            let id = *ids.entry(key).or_insert_with(|| {
                sum.push((Vec3::ZERO, [0; 3], 0));
                (sum.len() - 1) as u32
            });
            let s = &mut sum[id as usize];
            s.0 += *p;
            if let Some(c) = mesh.colors.as_ref().map(|c| c[i]) {
                (0..3).for_each(|k| s.1[k] += c[k] as u32);
            }
            s.2 += 1;
            id
        })
        .collect();
    let mut seen = std::collections::HashSet::new();
    let indices: Vec<[u32; 3]> = mesh
        .indices
        .iter()
        .map(|t| t.map(|v| remap[v as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .filter(|t| {
            // One triangle per cell triple and orientation.
            let m = t.iter().position(|v| v == t.iter().min().expect("three")).expect("present");
            seen.insert([t[m], t[(m + 1) % 3], t[(m + 2) % 3]])
        })
        .collect();
    // Only the clusters a triangle still uses, renumbered.
    let mut new_id = vec![u32::MAX; sum.len()];
    let mut kept = Vec::new();
    let indices = indices
        .into_iter()
        .map(|t| {
            t.map(|v| {
                if new_id[v as usize] == u32::MAX {
                    new_id[v as usize] = kept.len() as u32;
                    kept.push(v as usize);
                }
                new_id[v as usize]
            })
        })
        .collect();
    let positions = kept.iter().map(|&v| sum[v].0 / sum[v].2 as f32).collect();
    let colors = mesh.colors.as_ref().map(|_| kept.iter().map(|&v| sum[v].1.map(|c| (c / sum[v].2) as u8)).collect());
    TriMesh { positions, indices, normals: None, colors }
}
