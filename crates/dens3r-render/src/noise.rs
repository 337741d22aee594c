//! Sensor-like noise on a rendered scene folder, for testing what consumes noisy depth and
//! normals (fusion, the neural SDF): multiplicative Gaussian depth noise and normals tilted by
//! a random tangent offset. Seeded, so the same call gives the same files.

use dens3r_scene::{npy, Scene, SceneError};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Noise levels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Noise {
    /// Depth is multiplied by `1 + depth_sigma * N(0, 1)` (0.01 = 1% of the depth).
    pub depth_sigma: f32,
    /// Root-mean-square angle, in degrees, by which each normal is tilted in a random
    /// direction (a Gaussian tangent offset of `deg / sqrt(2)` radians per axis).
    pub normal_deg: f32,
    /// Seed.
    pub seed: u64,
}

/// One draw of a standard normal variable (Box-Muller).
pub fn gauss(rng: &mut ChaCha8Rng) -> f32 {
    let (u1, u2): (f64, f64) = (rng.gen_range(1e-12..1.0), rng.gen());
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

/// Rewrites the `depth/` and `normals/` layers of the scene folder at `dir` with noise added
/// (atomic per file). The folder is modified: run it on a scene you have just rendered or copied.
pub fn add_noise(dir: &std::path::Path, noise: &Noise) -> Result<(), SceneError> {
    if !((0.0..1.0).contains(&noise.depth_sigma) && (0.0..90.0).contains(&noise.normal_deg)) {
        return Err(SceneError {
            path: dir.to_path_buf(),
            message: format!(
                "noise depth {} / normals {} deg must be in [0, 1) / [0, 90)",
                noise.depth_sigma, noise.normal_deg
            ),
        });
    }
    let scene = Scene::open(dir)?;
    for (i, f) in scene.frames().iter().enumerate() {
        let mut rng = ChaCha8Rng::seed_from_u64(noise.seed.wrapping_mul(0x9e37_79b9).wrapping_add(i as u64));
        let path = dir.join("depth").join(format!("{}.npy", f.name));
        if noise.depth_sigma > 0.0 && path.is_file() {
            let (shape, mut d) = npy::read_f32(&path)?;
            for v in d.iter_mut().filter(|v| v.is_finite() && **v > 0.0) {
                *v *= 1.0 + noise.depth_sigma * gauss(&mut rng);
            }
            npy::write_f32(&path, &shape, &d)?;
        }
        let path = dir.join("normals").join(format!("{}.npy", f.name));
        if noise.normal_deg > 0.0 && path.is_file() {
            let sigma = noise.normal_deg.to_radians() / std::f32::consts::SQRT_2;
            let (shape, mut n) = npy::read_f32(&path)?;
            for c in n.chunks_exact_mut(3) {
                let v = Vec3::new(c[0], c[1], c[2]);
                if v.length_squared() < 0.25 {
                    continue;
                }
                let (t1, t2) = v.normalize().any_orthonormal_pair();
                let p = (v.normalize() + sigma * (gauss(&mut rng) * t1 + gauss(&mut rng) * t2)).normalize();
                c.copy_from_slice(&p.to_array());
            }
            npy::write_f32(&path, &shape, &n)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural;
    use dens3r_geom::Intrinsics;

    #[test]
    fn noise_has_the_requested_statistics() {
        let dir = tempfile::tempdir().unwrap();
        let clean = dir.path().join("clean");
        let world = crate::World::new(procedural::single_object(procedural::blob_mesh(0, 3), 0)).unwrap();
        let poses = crate::path::orbit(glam::DVec3::ZERO, 3.0, 25.0, 15.0, 2);
        let k = Intrinsics::from_hfov(96, 72, 60.0);
        crate::render_to_scene(&world, k, (96, 72), &poses, &Default::default(), &clean, |_| {}).unwrap();
        let noisy = dir.path().join("noisy");
        for sub in ["", "depth", "normals", "images"] {
            std::fs::create_dir_all(noisy.join(sub)).unwrap();
            for e in std::fs::read_dir(clean.join(sub)).unwrap() {
                let e = e.unwrap();
                if e.file_type().unwrap().is_file() {
                    std::fs::copy(e.path(), noisy.join(sub).join(e.file_name())).unwrap();
                }
            }
        }
        add_noise(&noisy, &Noise { depth_sigma: 0.01, normal_deg: 5.0, seed: 3 }).unwrap();
        let (a, b) = (Scene::open(&clean).unwrap(), Scene::open(&noisy).unwrap());
        let (mut rel, mut ang) = (Vec::new(), Vec::new());
        for f in a.frames() {
            let (d0, d1) = (a.depth(f).unwrap().unwrap(), b.depth(f).unwrap().unwrap());
            let (n0, n1) = (a.normals(f).unwrap().unwrap(), b.normals(f).unwrap().unwrap());
            for i in 0..d0.data().len() {
                if d0.data()[i] > 0.0 {
                    rel.push((d1.data()[i] / d0.data()[i] - 1.0) as f64);
                    ang.push(n0.data()[i].angle_between(n1.data()[i]).to_degrees() as f64);
                }
            }
        }
        let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        let mean = rel.iter().sum::<f64>() / rel.len() as f64;
        assert!(rel.len() > 2000);
        assert!((rms(&rel) - 0.01).abs() < 0.0005, "depth noise rms {}", rms(&rel));
        assert!(mean.abs() < 0.0005, "depth noise mean {mean}");
        // A small tilt of RMS 5 deg (the tangent-plane approximation is within 0.2%).
        assert!((rms(&ang) - 5.0).abs() < 0.15, "normal noise rms {} deg", rms(&ang));
    }
}
