//! Tessellated primitive shapes (closed, outward-facing, counter-clockwise triangles).

use crate::TriMesh;
use glam::Vec3;
use std::f32::consts::{PI, TAU};

/// UV sphere of `radius` centred at the origin with `rings` latitude bands (>= 2) and
/// `segments` longitude slices (>= 3).
pub fn uv_sphere(radius: f32, rings: u32, segments: u32) -> TriMesh {
    let (rings, segments) = (rings.max(2), segments.max(3));
    let mut pos = vec![Vec3::new(0.0, 0.0, radius)];
    for r in 1..rings {
        let theta = PI * r as f32 / rings as f32;
        for s in 0..segments {
            let phi = TAU * s as f32 / segments as f32;
            pos.push(Vec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()) * radius);
        }
    }
    pos.push(Vec3::new(0.0, 0.0, -radius));
    let south = pos.len() as u32 - 1;
    let ring = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
    let mut idx = Vec::new();
    for s in 0..segments {
        idx.push([0, ring(1, s), ring(1, s + 1)]);
        idx.push([south, ring(rings - 1, s + 1), ring(rings - 1, s)]);
    }
    for r in 1..rings - 1 {
        for s in 0..segments {
            let (a, b, c, d) = (ring(r, s), ring(r, s + 1), ring(r + 1, s), ring(r + 1, s + 1));
            idx.push([a, c, d]);
            idx.push([a, d, b]);
        }
    }
    finish(pos, idx)
}

/// Axis-aligned box with the given half extents, centred at the origin.
pub fn cuboid(half: Vec3) -> TriMesh {
    let mut pos = Vec::new();
    let mut idx = Vec::new();
    // Each face: outward normal axis, then two in-plane axes ordered so u x v = normal.
    for (n, u, v) in [
        (Vec3::X, Vec3::Y, Vec3::Z),
        (Vec3::NEG_X, Vec3::Z, Vec3::Y),
        (Vec3::Y, Vec3::Z, Vec3::X),
        (Vec3::NEG_Y, Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X, Vec3::Y),
        (Vec3::NEG_Z, Vec3::Y, Vec3::X),
    ] {
        let base = pos.len() as u32;
        for (a, b) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            pos.push((n + u * a + v * b) * half);
        }
        idx.push([base, base + 1, base + 2]);
        idx.push([base, base + 2, base + 3]);
    }
    finish(pos, idx)
}

/// Torus around the z axis: ring radius `major`, tube radius `minor`.
pub fn torus(major: f32, minor: f32, rings: u32, tube: u32) -> TriMesh {
    let (rings, tube) = (rings.max(3), tube.max(3));
    let mut pos = Vec::new();
    for i in 0..rings {
        let u = TAU * i as f32 / rings as f32;
        for j in 0..tube {
            let v = TAU * j as f32 / tube as f32;
            let r = major + minor * v.cos();
            pos.push(Vec3::new(r * u.cos(), r * u.sin(), minor * v.sin()));
        }
    }
    let at = |i: u32, j: u32| (i % rings) * tube + j % tube;
    let mut idx = Vec::new();
    for i in 0..rings {
        for j in 0..tube {
            let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
            idx.push([a, b, c]);
            idx.push([a, c, d]);
        }
    }
    finish(pos, idx)
}

/// Icosphere of `radius`: an icosahedron subdivided `subdivisions` times (20 * 4^s faces).
pub fn icosphere(radius: f32, subdivisions: u32) -> TriMesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut pos: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut idx: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, pos: &mut Vec<Vec3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                pos.push(((pos[a as usize] + pos[b as usize]) * 0.5).normalize());
                pos.len() as u32 - 1
            })
        };
        let mut next = Vec::with_capacity(idx.len() * 4);
        for [a, b, c] in idx {
            let (ab, bc, ca) = (midpoint(a, b, &mut pos), midpoint(b, c, &mut pos), midpoint(c, a, &mut pos));
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        idx = next;
    }
    finish(pos.into_iter().map(|p| p * radius).collect(), idx)
}

/// A parallelogram with corner `origin` and edges `u`, `v`; its normal is `u x v`.
pub fn quad(origin: Vec3, u: Vec3, v: Vec3) -> TriMesh {
    finish(vec![origin, origin + u, origin + u + v, origin + v], vec![[0, 1, 2], [0, 2, 3]])
}

fn finish(pos: Vec<Vec3>, idx: Vec<[u32; 3]>) -> TriMesh {
    let mut m = TriMesh::new(pos, idx);
    m.compute_vertex_normals();
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed volume by the divergence theorem: positive iff faces point outward.
    fn volume(m: &TriMesh) -> f64 {
        (0..m.indices.len())
            .map(|t| {
                let [a, b, c] = m.triangle(t).map(|p| p.as_dvec3());
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn closed_outward_and_close_to_analytic() {
        let s = uv_sphere(2.0, 96, 192);
        let v = 4.0 / 3.0 * std::f64::consts::PI * 8.0;
        assert!((volume(&s) / v - 1.0).abs() < 2e-3, "{}", volume(&s));
        assert!((s.area() / (4.0 * std::f64::consts::PI * 4.0) - 1.0).abs() < 2e-3);
        let b = cuboid(Vec3::new(1.0, 2.0, 3.0));
        assert!((volume(&b) - 48.0).abs() < 1e-4 && (b.area() - 88.0).abs() < 1e-4);
        let ico = icosphere(1.0, 5);
        assert_eq!(ico.indices.len(), 20 * 4usize.pow(5));
        assert!((volume(&ico) / (4.0 / 3.0 * std::f64::consts::PI) - 1.0).abs() < 2e-3);
        let q = quad(Vec3::ZERO, Vec3::X * 2.0, Vec3::Y * 3.0);
        assert!((q.area() - 6.0).abs() < 1e-9 && q.face_normal(1) == Vec3::Z);
        let t = torus(2.0, 0.5, 128, 64);
        let tv = 2.0 * std::f64::consts::PI.powi(2) * 2.0 * 0.25;
        assert!((volume(&t) / tv - 1.0).abs() < 3e-3, "{} vs {tv}", volume(&t));
        // Every face normal agrees with the outward direction on a sphere.
        assert!((0..s.indices.len()).all(|f| {
            let [a, b, c] = s.triangle(f);
            s.face_normal(f).dot((a + b + c) / 3.0) > 0.0
        }));
    }
}
