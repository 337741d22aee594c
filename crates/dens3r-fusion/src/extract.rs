//! Marching cubes over the sparse TSDF: one indexed mesh without cracks across block borders
//! (a vertex is keyed by the grid edge it lies on, so the cubes on both sides of a border share
//! it), vertex normals from the TSDF gradient, vertex colours, then optional removal of small
//! connected components and a crop to a box. The case tables are the classic Lorensen-Cline /
//! Bourke tables from the `marching-cubes` crate.

use crate::grid::{IntMap, VoxelBlockGrid, BLOCK};
use dens3r_mesh::TriMesh;
use glam::{IVec3, Vec3};
use marching_cubes::tables::{EDGE_TABLE, TRI_TABLE};
use rayon::prelude::*;
use std::collections::HashMap;

/// Mesh extraction options.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ExtractOptions {
    /// Drop connected components with fewer triangles than this (0 keeps everything).
    pub min_component_triangles: usize,
    /// Keep only triangles whose three vertices lie in this box `(min, max)`.
    pub crop: Option<(Vec3, Vec3)>,
}

/// Bourke's cube corners: 0-3 go round the z = 0 face, 4-7 the z = 1 face above them.
const CORNERS: [IVec3; 8] = [
    IVec3::new(0, 0, 0),
    IVec3::new(1, 0, 0),
    IVec3::new(1, 1, 0),
    IVec3::new(0, 1, 0),
    IVec3::new(0, 0, 1),
    IVec3::new(1, 0, 1),
    IVec3::new(1, 1, 1),
    IVec3::new(0, 1, 1),
];

/// The 12 cube edges as (lower corner, axis 0 = x / 1 = y / 2 = z), in the tables' order.
const EDGES: [(usize, usize); 12] =
    [(0, 0), (1, 1), (3, 0), (0, 1), (4, 0), (5, 1), (7, 0), (4, 1), (0, 2), (1, 2), (2, 2), (3, 2)];

/// Local grid of a block plus a margin: voxel-local coordinates -1 ..= 9 on each axis.
const G: i32 = BLOCK + 3;

#[derive(Clone, Copy)]
struct Sample {
    f: f32,
    w: f32,
    c: [f32; 3],
}

const EMPTY: Sample = Sample { f: 1.0, w: 0.0, c: [0.0; 3] };

/// Unit step along axis `a`.
fn unit(a: usize) -> IVec3 {
    let mut e = IVec3::ZERO;
    e[a] = 1;
    e
}

fn gidx(l: IVec3) -> usize {
    ((l.x + 1) + G * ((l.y + 1) + G * (l.z + 1))) as usize
}

/// Copies the block at `key` and the needed parts of its 26 neighbours into a local grid.
fn gather(tsdf: &VoxelBlockGrid, key: IVec3) -> Vec<Sample> {
    let mut g = vec![EMPTY; (G * G * G) as usize];
    for dz in -1..=1 {
        for dy in -1..=1 {
            for dx in -1..=1 {
                let d = IVec3::new(dx, dy, dz);
                let Some(b) = tsdf.block(key + d) else { continue };
                // Local range of this neighbour inside -1..=9, per axis.
                let range = |o: i32| match o {
                    -1 => (-1, -1),
                    0 => (0, BLOCK - 1),
                    _ => (BLOCK, BLOCK + 1),
                };
                let (rx, ry, rz) = (range(dx), range(dy), range(dz));
                for z in rz.0..=rz.1 {
                    for y in ry.0..=ry.1 {
                        for x in rx.0..=rx.1 {
                            let l = IVec3::new(x, y, z);
                            let inner = l - d * BLOCK;
                            let i = (inner.x + BLOCK * (inner.y + BLOCK * inner.z)) as usize;
                            g[gidx(l)] =
                                Sample { f: b.tsdf[i], w: b.weight[i], c: b.color.get(i).copied().unwrap_or([0.0; 3]) };
                        }
                    }
                }
            }
        }
    }
    g
}

/// TSDF gradient at a local grid point (central differences, one-sided at unobserved
/// neighbours), pointing from the surface's back towards free space.
fn gradient(g: &[Sample], l: IVec3) -> Vec3 {
    let f0 = g[gidx(l)].f;
    let mut out = Vec3::ZERO;
    for a in 0..3 {
        let e = unit(a);
        let (p, m) = (l + e, l - e);
        let fp = (p.max_element() <= BLOCK + 1 && g[gidx(p)].w > 0.0).then(|| g[gidx(p)].f);
        let fm = (m.min_element() >= -1 && g[gidx(m)].w > 0.0).then(|| g[gidx(m)].f);
        out[a] = match (fp, fm) {
            (Some(p), Some(m)) => 0.5 * (p - m),
            (Some(p), None) => p - f0,
            (None, Some(m)) => f0 - m,
            (None, None) => 0.0,
        };
    }
    out
}

/// A vertex on a grid edge: key, position, normal, colour.
type EdgeVertex = (u64, Vec3, Vec3, [u8; 3]);

/// Packs (global voxel, axis) into a key: 20 bits per coordinate, 2 for the axis.
fn edge_key(v: IVec3, axis: usize) -> Option<u64> {
    const OFF: i32 = 1 << 19;
    let u = v + IVec3::splat(OFF);
    if u.min_element() < 0 || u.max_element() >= (1 << 20) {
        return None;
    }
    Some(((u.x as u64) << 42) | ((u.y as u64) << 22) | ((u.z as u64) << 2) | axis as u64)
}

/// Cubes whose lower corner lies in one block: vertices (with duplicates) and triangles by key.
fn block_surface(tsdf: &VoxelBlockGrid, key: IVec3) -> (Vec<EdgeVertex>, Vec<[u64; 3]>) {
    let g = gather(tsdf, key);
    let voxel = tsdf.spec().voxel;
    // Largest plausible TSDF step between neighbouring voxels (normalised units): one voxel of
    // distance is voxel / trunc; allow 3x for grazing views, and never less than 0.5.
    let max_jump = (3.0 * voxel / tsdf.spec().trunc).max(0.5);
    let origin = key * BLOCK;
    let (mut verts, mut tris) = (Vec::new(), Vec::new());
    for z in 0..BLOCK {
        for y in 0..BLOCK {
            for x in 0..BLOCK {
                let l = IVec3::new(x, y, z);
                let s: [Sample; 8] = CORNERS.map(|c| g[gidx(l + c)]);
                if s.iter().any(|s| s.w <= 0.0) {
                    continue;
                }
                let mut case = 0usize;
                for (i, si) in s.iter().enumerate() {
                    if si.f < 0.0 {
                        case |= 1 << i;
                    }
                }
                let mask = EDGE_TABLE[case] as u16;
                if mask == 0 {
                    continue;
                }
                // A sign change from a fully truncated "free space" value (+1) to a negative one,
                // a jump far larger than one voxel of distance, is no surface but the seam where
                // views past a silhouette meet views of the back (ghost sheets behind objects):
                // skip such cubes. On the bench object at 2 cm this takes the mean distance to
                // the truth from 7.3 to 0.66 mm at unchanged recall.
                let ghost = EDGES.iter().enumerate().any(|(e, &(c0, axis))| {
                    let c1 = CORNERS.iter().position(|&c| c == CORNERS[c0] + unit(axis)).expect("edge corner");
                    mask & (1 << e) != 0 && (s[c0].f - s[c1].f).abs() > max_jump && s[c0].f.max(s[c1].f) > 0.999
                });
                if ghost {
                    continue;
                }
                let mut keys = [u64::MAX; 12];
                for (e, &(c0, axis)) in EDGES.iter().enumerate() {
                    if mask & (1 << e) == 0 {
                        continue;
                    }
                    let a = l + CORNERS[c0];
                    let b = a + unit(axis);
                    let (sa, sb) = (g[gidx(a)], g[gidx(b)]);
                    let t = (sa.f / (sa.f - sb.f)).clamp(0.0, 1.0);
                    let Some(k) = edge_key(origin + a, axis) else { continue };
                    let pos = ((origin + a).as_vec3() + 0.5 + unit(axis).as_vec3() * t) * voxel;
                    let n = gradient(&g, a).lerp(gradient(&g, b), t).normalize_or_zero();
                    let c = [0, 1, 2].map(|ch| (sa.c[ch] + t * (sb.c[ch] - sa.c[ch])).round().clamp(0.0, 255.0) as u8);
                    keys[e] = k;
                    verts.push((k, pos, n, c));
                }
                for tri in TRI_TABLE[case].chunks_exact(3) {
                    if tri[0] < 0 {
                        break;
                    }
                    // Bourke's winding is clockwise seen from the positive side: reverse it so
                    // faces wind counter-clockwise around the outward (gradient) normal.
                    let t = [keys[tri[0] as usize], keys[tri[2] as usize], keys[tri[1] as usize]];
                    if t.iter().all(|&k| k != u64::MAX) {
                        tris.push(t);
                    }
                }
            }
        }
    }
    (verts, tris)
}

/// Extracts the zero level set as an indexed mesh with normals and (if integrated) colours.
pub fn extract_mesh(tsdf: &VoxelBlockGrid, opts: &ExtractOptions) -> TriMesh {
    // Blocks whose observed voxels are all on one side, like their +x/+y/+z neighbours,
    // cannot hold a zero crossing in the cubes they own: skip them without gathering.
    let signs: IntMap<IVec3, (bool, bool)> = tsdf
        .blocks()
        .map(|(k, b)| {
            let obs = b.tsdf.iter().zip(&b.weight).filter(|(_, &w)| w > 0.0);
            let (mut neg, mut pos) = (false, false);
            for (&f, _) in obs {
                neg |= f < 0.0;
                pos |= f >= 0.0;
            }
            (k, (neg, pos))
        })
        .collect();
    let mut keys: Vec<IVec3> = tsdf
        .blocks()
        .map(|(k, _)| k)
        .filter(|k| {
            let (mut neg, mut pos) = (false, false);
            for c in CORNERS {
                if let Some(&(n, p)) = signs.get(&(*k + c)) {
                    neg |= n;
                    pos |= p;
                }
            }
            neg && pos
        })
        .collect();
    keys.sort_by_key(|k| (k.z, k.y, k.x));
    let parts: Vec<(Vec<EdgeVertex>, Vec<[u64; 3]>)> = keys.par_iter().map(|&k| block_surface(tsdf, k)).collect();
    let mut index: IntMap<u64, u32> = IntMap::default();
    let (mut positions, mut normals, mut colors) = (Vec::new(), Vec::new(), Vec::new());
    for (verts, _) in &parts {
        for &(k, p, n, c) in verts {
            index.entry(k).or_insert_with(|| {
                positions.push(p);
                normals.push(n);
                colors.push(c);
                (positions.len() - 1) as u32
            });
        }
    }
    let mut indices = Vec::new();
    for (_, tris) in &parts {
        for t in tris {
            let f = t.map(|k| index[&k]);
            if f[0] != f[1] && f[1] != f[2] && f[0] != f[2] {
                indices.push(f);
            }
        }
    }
    let mut mesh = TriMesh::new(positions, indices);
    mesh.normals = Some(normals);
    if tsdf.spec().color {
        mesh.colors = Some(colors);
    }
    if let Some((lo, hi)) = opts.crop {
        let inside = |p: Vec3| p.cmpge(lo).all() && p.cmple(hi).all();
        let keep: Vec<bool> =
            mesh.indices.iter().map(|t| t.iter().all(|&i| inside(mesh.positions[i as usize]))).collect();
        mesh = filter_triangles(&mesh, &keep);
    }
    if opts.min_component_triangles > 0 {
        let keep = component_filter(&mesh, opts.min_component_triangles);
        mesh = filter_triangles(&mesh, &keep);
    }
    mesh
}

/// Triangles in connected components (through shared vertices) of at least `min` triangles.
pub fn component_filter(mesh: &TriMesh, min: usize) -> Vec<bool> {
    let n = mesh.positions.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn find(p: &mut [u32], mut x: u32) -> u32 {
        while p[x as usize] != x {
            p[x as usize] = p[p[x as usize] as usize];
            x = p[x as usize];
        }
        x
    }
    for t in &mesh.indices {
        let r0 = find(&mut parent, t[0]);
        for &v in &t[1..] {
            let r = find(&mut parent, v);
            if r != r0 {
                parent[r as usize] = r0;
            }
        }
    }
    let roots: Vec<u32> = mesh.indices.iter().map(|t| find(&mut parent, t[0])).collect();
    let mut count: HashMap<u32, usize> = HashMap::new();
    for &r in &roots {
        *count.entry(r).or_default() += 1;
    }
    roots.iter().map(|r| count[r] >= min).collect()
}

/// The mesh with only the kept triangles and the vertices they use (attributes follow).
pub fn filter_triangles(mesh: &TriMesh, keep: &[bool]) -> TriMesh {
    let mut remap = vec![u32::MAX; mesh.positions.len()];
    let mut out = TriMesh::new(Vec::new(), Vec::new());
    let mut normals = Vec::new();
    let mut colors = Vec::new();
    for (t, _) in mesh.indices.iter().zip(keep).filter(|(_, &k)| k) {
        let f = t.map(|i| {
            if remap[i as usize] == u32::MAX {
                remap[i as usize] = out.positions.len() as u32;
                out.positions.push(mesh.positions[i as usize]);
                if let Some(n) = &mesh.normals {
                    normals.push(n[i as usize]);
                }
                if let Some(c) = &mesh.colors {
                    colors.push(c[i as usize]);
                }
            }
            remap[i as usize]
        });
        out.indices.push(f);
    }
    out.normals = mesh.normals.as_ref().map(|_| normals);
    out.colors = mesh.colors.as_ref().map(|_| colors);
    out
}
