//! Area-weighted uniform sampling of points on a mesh surface.

use crate::TriMesh;
use glam::Vec3;
use rand::{Rng, SeedableRng};

/// `n` points drawn uniformly over the surface (seeded, reproducible), each with the unit
/// normal of the triangle it lies on. Degenerate triangles are never picked. Empty when the
/// mesh has no area.
pub fn sample_surface(mesh: &TriMesh, n: usize, seed: u64) -> (Vec<Vec3>, Vec<Vec3>) {
    let mut cdf = Vec::with_capacity(mesh.indices.len());
    let mut total = 0.0f64;
    for t in 0..mesh.indices.len() {
        let [a, b, c] = mesh.triangle(t).map(|p| p.as_dvec3());
        total += 0.5 * (b - a).cross(c - a).length();
        cdf.push(total);
    }
    if total.is_nan() || total <= 0.0 {
        return (Vec::new(), Vec::new());
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let (mut pts, mut nrm) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        let r = rng.gen::<f64>() * total;
        let t = cdf.partition_point(|&c| c <= r).min(cdf.len() - 1);
        let [a, b, c] = mesh.triangle(t);
        let (mut u, mut v) = (rng.gen::<f32>(), rng.gen::<f32>());
        if u + v > 1.0 {
            (u, v) = (1.0 - u, 1.0 - v);
        }
        pts.push(a + (b - a) * u + (c - a) * v);
        nrm.push(mesh.face_normal(t));
    }
    (pts, nrm)
}
