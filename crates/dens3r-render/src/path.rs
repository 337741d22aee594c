//! Camera paths: OpenCV camera-to-world poses for a sequence of views. World up is +z.

use dens3r_geom::camera::look_at;
use glam::{DMat4, DVec3};
use rand::{Rng, SeedableRng};

/// `n` views on a circle of `radius` around `center`, all looking at it. The elevation
/// (degrees above the horizontal) swings by `±swing_deg` twice per turn so the top and the
/// sides are both seen.
pub fn orbit(center: DVec3, radius: f64, elevation_deg: f64, swing_deg: f64, n: usize) -> Vec<DMat4> {
    (0..n)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / n as f64;
            let el = (elevation_deg + swing_deg * (2.0 * a).sin()).to_radians();
            let eye = center + DVec3::new(el.cos() * a.cos(), el.cos() * a.sin(), el.sin()) * radius;
            look_at(eye, center, DVec3::Z).expect("orbit elevation is below 90 degrees")
        })
        .collect()
}

/// `n` views walking an ellipse inside the box `[lo, hi]` (a room; z up) at eye height
/// `height`, each looking across the room at a point on the far side, with seeded jitter.
pub fn room_walk(lo: DVec3, hi: DVec3, height: f64, n: usize, seed: u64) -> Vec<DMat4> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let c = (lo + hi) * 0.5;
    let half = (hi - lo) * 0.5;
    (0..n)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / n as f64;
            let eye = DVec3::new(c.x + 0.45 * half.x * a.cos(), c.y + 0.45 * half.y * a.sin(), lo.z + height)
                + DVec3::new(rng.gen_range(-0.05..0.05), rng.gen_range(-0.05..0.05), rng.gen_range(-0.1..0.1))
                    * half.x.min(half.y);
            let b = a + std::f64::consts::PI + rng.gen_range(-0.6..0.6);
            let target = DVec3::new(
                c.x + 0.7 * half.x * b.cos(),
                c.y + 0.7 * half.y * b.sin(),
                lo.z + height * rng.gen_range(0.35..0.8),
            );
            look_at(eye, target, DVec3::Z).expect("eye and target differ")
        })
        .collect()
}
