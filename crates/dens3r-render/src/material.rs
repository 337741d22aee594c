//! Materials: a base colour modulated by a texture evaluated in the object's own frame (so the
//! pattern sticks to the surface and is view-consistent: something for feature matching to
//! lock on): procedural 3-D patterns, or a photograph projected along the dominant axis of
//! the surface normal (tri-planar mapping).

use image::RgbImage;
use std::sync::Arc;

/// A texture pattern.
#[derive(Debug, Clone, PartialEq)]
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
    /// A photograph tiled over the surface (mirrored repeat), projected along the dominant
    /// axis of the object-space normal; `size` object units per image width.
    Photo {
        /// The picture (sRGB).
        image: Arc<RgbImage>,
        /// Object units covered by the image's width.
        size: f32,
        /// Each of the six projection faces (+-x, +-y, +-z) shows its own part of the
        /// picture, so that opposite sides of an object do not repeat one another (a real
        /// object's texture does not); otherwise all six show the same tiling.
        per_face: bool,
    },
}

/// Surface appearance.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    /// Base colour, linear 0..1.
    pub color: [f32; 3],
    /// Pattern.
    pub texture: Texture,
    /// Seed for the pattern, so objects do not share texture.
    pub seed: u32,
}

impl Material {
    /// Albedo at object-space point `p` with object-space normal `n`.
    pub fn albedo(&self, p: glam::Vec3, n: glam::Vec3) -> [f32; 3] {
        let m = match &self.texture {
            Texture::Plain => 1.0,
            Texture::Checker { size } => {
                let c = (p / *size).floor();
                let parity = (c.x + c.y + c.z).rem_euclid(2.0);
                0.55 + 0.35 * parity + 0.1 * fbm(p / *size * 3.0, self.seed)
            }
            Texture::Noise { scale } => {
                // Stretch the noise (it clusters around 0.5) for strong, matchable contrast.
                let n = ((fbm(p / *scale, self.seed) - 0.5) * 2.5 + 0.5).clamp(0.0, 1.0);
                0.3 + 0.7 * n
            }
            Texture::Photo { image, size, per_face } => {
                let rgb = photo_texel(image, p, n, *size, self.seed, *per_face);
                return [0, 1, 2].map(|c| (self.color[c] * rgb[c]).clamp(0.0, 1.0));
            }
        };
        self.color.map(|c| (c * m).clamp(0.0, 1.0))
    }
}

/// Linear colour of `image` at the tri-planar coordinates of `p` (the two axes other than
/// the normal's dominant one), bilinear with mirrored repeat; `seed` offsets the tiling, and
/// with `per_face` each projection face (axis and sign) is offset by its own amount.
fn photo_texel(image: &RgbImage, p: glam::Vec3, n: glam::Vec3, size: f32, seed: u32, per_face: bool) -> [f32; 3] {
    let a = n.abs();
    let (u, v, face) = if a.x >= a.y && a.x >= a.z {
        (p.y, p.z, if n.x >= 0.0 { 0 } else { 1 })
    } else if a.y >= a.z {
        (p.x, p.z, if n.y >= 0.0 { 2 } else { 3 })
    } else {
        (p.x, p.y, if n.z >= 0.0 { 4 } else { 5 })
    };
    let (w, h) = (image.width().max(1) as f32, image.height().max(1) as f32);
    let off = (seed % 1024) as f32 / 1024.0;
    // Steps of irrational fractions of the mirrored period (two picture widths / heights).
    let (du, dv) = if per_face { (face as f32 * 0.618, face as f32 * 0.414) } else { (0.0, 0.0) };
    let x = (u / size.max(1e-6) + off + du) * w;
    let y = (-v / size.max(1e-6) + off + dv) * w;
    let mirror = |t: f32, n: f32| {
        let period = 2.0 * n;
        let t = t.rem_euclid(period);
        if t < n {
            t
        } else {
            period - t - 1e-3
        }
    };
    let (x, y) = (mirror(x - 0.5, w).clamp(0.0, w - 1.0), mirror(y - 0.5, h).clamp(0.0, h - 1.0));
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = ((x0 + 1).min(image.width() - 1), (y0 + 1).min(image.height() - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let px = |x: u32, y: u32, c: usize| (image.get_pixel(x, y)[c] as f32 / 255.0).powf(2.2);
    [0, 1, 2].map(|c| {
        let top = px(x0, y0, c) * (1.0 - fx) + px(x1, y0, c) * fx;
        let bottom = px(x0, y1, c) * (1.0 - fx) + px(x1, y1, c) * fx;
        top * (1.0 - fy) + bottom * fy
    })
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

/// A value in [0, 1] (16-bit steps) hashed from an integer cell and a seed.
pub(crate) fn hash(x: i32, y: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x9e37_79b9);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h & 0xffff) as f32 / 65535.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// A picture with no two pixels alike (each colour codes its position).
    fn gradient() -> Arc<RgbImage> {
        Arc::new(RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, ((x + y) * 2) as u8])))
    }

    /// Without `per_face`, the point (0, v, w) shows the same texel on the +x and -x sides (the
    /// projection drops x, and the sign of the normal); with it, the two sides differ, and a
    /// side still shows one continuous picture.
    #[test]
    fn per_face_photos_differ_between_opposite_sides() {
        let mat = |per_face| Material {
            color: [1.0; 3],
            texture: Texture::Photo { image: gradient(), size: 1.0, per_face },
            seed: 5,
        };
        let p = Vec3::new(0.0, 0.3, 0.2);
        let shared = mat(false);
        assert_eq!(shared.albedo(p, Vec3::X), shared.albedo(p, Vec3::NEG_X));
        let own = mat(true);
        let (plus, minus) = (own.albedo(p, Vec3::X), own.albedo(p, Vec3::NEG_X));
        assert!(plus.iter().zip(&minus).any(|(a, b)| (a - b).abs() > 0.05), "{plus:?} {minus:?}");
        // Nearby points on one side have nearby colours (bilinear, no jumps within a face).
        let near = own.albedo(p + Vec3::new(0.0, 1e-3, 0.0), Vec3::X);
        assert!(plus.iter().zip(&near).all(|(a, b)| (a - b).abs() < 0.02), "{plus:?} {near:?}");
    }
}
