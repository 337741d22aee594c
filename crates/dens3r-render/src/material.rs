//! Materials: a base colour modulated by a procedural 3-D texture evaluated in the object's
//! own frame (so the pattern sticks to the surface and is view-consistent: something for
//! feature matching to lock on).

/// A procedural texture pattern.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Texture {
    /// Flat colour.
    Plain,
    /// 3-D checkerboard of cell size `size`, with a little noise on top.
    Checker {
        /// Cell size, in object units.
        size: f32,
    },
    /// Multi-octave value noise with feature size `scale`.
    Noise {
        /// Feature size, in object units.
        scale: f32,
    },
}

/// Surface appearance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Base colour, linear 0..1.
    pub color: [f32; 3],
    /// Pattern.
    pub texture: Texture,
    /// Seed for the pattern, so objects do not share texture.
    pub seed: u32,
}

impl Material {
    /// Albedo at object-space point `p`.
    pub fn albedo(&self, p: glam::Vec3) -> [f32; 3] {
        let m = match self.texture {
            Texture::Plain => 1.0,
            Texture::Checker { size } => {
                let c = (p / size).floor();
                let parity = (c.x + c.y + c.z).rem_euclid(2.0);
                0.55 + 0.35 * parity + 0.1 * fbm(p / size * 3.0, self.seed)
            }
            Texture::Noise { scale } => {
                // Stretch the noise (it clusters around 0.5) for strong, matchable contrast.
                let n = ((fbm(p / scale, self.seed) - 0.5) * 2.5 + 0.5).clamp(0.0, 1.0);
                0.3 + 0.7 * n
            }
        };
        self.color.map(|c| (c * m).clamp(0.0, 1.0))
    }
}

/// Fractal value noise in 0..1 (4 octaves).
pub fn fbm(p: glam::Vec3, seed: u32) -> f32 {
    let (mut sum, mut amp, mut freq, mut norm) = (0.0, 0.5, 1.0, 0.0);
    for o in 0..4 {
        sum += amp * value_noise(p * freq, seed.wrapping_add(o * 1013));
        norm += amp;
        amp *= 0.5;
        freq *= 2.03;
    }
    sum / norm
}

fn value_noise(p: glam::Vec3, seed: u32) -> f32 {
    let i = p.floor();
    let f = p - i;
    let s = f * f * (glam::Vec3::splat(3.0) - 2.0 * f);
    let h = |dx: i32, dy: i32, dz: i32| hash(i.x as i32 + dx, i.y as i32 + dy, i.z as i32 + dz, seed);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(h(0, 0, 0), h(1, 0, 0), s.x);
    let x10 = lerp(h(0, 1, 0), h(1, 1, 0), s.x);
    let x01 = lerp(h(0, 0, 1), h(1, 0, 1), s.x);
    let x11 = lerp(h(0, 1, 1), h(1, 1, 1), s.x);
    lerp(lerp(x00, x10, s.y), lerp(x01, x11, s.y), s.z)
}

fn hash(x: i32, y: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x9e37_79b9);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h & 0xffff) as f32 / 65535.0
}
