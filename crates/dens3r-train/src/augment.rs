//! Photometric augmentations of training images, normalised `(3, H, W)` planes in `[-1, 1]`:
//! colour jitter, grey, and a camera's degradations (vignetting, white balance, lens blur, tone curve,
//! sensor noise) that rendered images lack and photographs have.

use dens3r_render::noise::gauss;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Colour jitter of a normalised `(3, H, W)` image: brightness, contrast and saturation
/// factors in `1 ± amp`, clamped to `[-1, 1]`.
pub fn jitter(mut img: Vec<f32>, amp: f32, rng: &mut ChaCha8Rng) -> Vec<f32> {
    if amp <= 0.0 {
        return img;
    }
    let mut f = || 1.0 + rng.gen_range(-amp..=amp);
    let (bright, contrast, sat) = (f(), f(), f());
    let n = img.len() / 3;
    let mean = img.iter().sum::<f32>() / img.len() as f32;
    for i in 0..n {
        let grey = (img[i] + img[n + i] + img[2 * n + i]) / 3.0;
        for c in 0..3 {
            let v = &mut img[c * n + i];
            let s = grey + (*v - grey) * sat;
            let s = mean + (s - mean) * contrast;
            *v = ((s + 1.0) * bright - 1.0).clamp(-1.0, 1.0);
        }
    }
    img
}

/// A normalised `(3, H, W)` image as a monochrome camera sees it: every channel the luma
/// `0.299 R + 0.587 G + 0.114 B` (ITU-R BT.601, as common image libraries turn colour into
/// grey).
pub fn to_grey(img: &mut [f32]) {
    let n = img.len() / 3;
    let (r, rest) = img.split_at_mut(n);
    let (g, b) = rest.split_at_mut(n);
    for ((r, g), b) in r.iter_mut().zip(g.iter_mut()).zip(b.iter_mut()) {
        let y = 0.299 * *r + 0.587 * *g + 0.114 * *b;
        (*r, *g, *b) = (y, y, y);
    }
}

/// A camera's degradations of one image, applied in this order to intensities in `[0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Degradation {
    /// Vignetting: brightness falls by this fraction at the corners, as the squared distance
    /// from the centre.
    pub vignette: f32,
    /// White balance: per-channel gains (R, G, B).
    pub gains: [f32; 3],
    /// Lens blur: standard deviation of a Gaussian, in pixels (0 = none).
    pub blur: f32,
    /// Tone curve: intensities raised to this power.
    pub gamma: f32,
    /// Sensor noise: standard deviation of additive Gaussian noise, per pixel and channel.
    pub noise: f32,
}

impl Degradation {
    /// No change.
    pub const NONE: Self = Self { vignette: 0.0, gains: [1.0; 3], blur: 0.0, gamma: 1.0, noise: 0.0 };

    /// A random degradation of a phone or robot camera: vignetting up to 35%, gains within
    /// 12% per channel, blur up to 1.2 px, gamma 0.7-1.4, noise up to 3% of full scale.
    pub fn draw(rng: &mut ChaCha8Rng) -> Self {
        Self {
            vignette: rng.gen_range(0.0..0.35),
            gains: [(); 3].map(|_| rng.gen_range(0.88..1.12)),
            blur: rng.gen_range(0.0..1.2),
            gamma: rng.gen_range(-0.35f32..0.35).exp(),
            noise: rng.gen_range(0.0..0.03),
        }
    }

    /// Applies it to a normalised `(3, h, w)` image (values in `[-1, 1]`, which it keeps);
    /// `rng` draws the noise.
    pub fn apply(&self, img: &mut [f32], (w, h): (usize, usize), rng: &mut ChaCha8Rng) {
        let n = w * h;
        assert_eq!(img.len(), 3 * n, "a (3, {h}, {w}) image");
        let (cx, cy) = ((w as f32 - 1.0) / 2.0, (h as f32 - 1.0) / 2.0);
        let corner = (cx * cx + cy * cy).max(f32::MIN_POSITIVE);
        for (c, plane) in img.chunks_mut(n).enumerate() {
            for (i, v) in plane.iter_mut().enumerate() {
                let (dx, dy) = ((i % w) as f32 - cx, (i / w) as f32 - cy);
                let fall = 1.0 - self.vignette * (dx * dx + dy * dy) / corner;
                *v = (*v + 1.0) / 2.0 * fall * self.gains[c];
            }
            if self.blur > 0.0 {
                gaussian_blur(plane, (w, h), self.blur);
            }
        }
        for v in img.iter_mut() {
            let mut x = v.clamp(0.0, 1.0).powf(self.gamma);
            if self.noise > 0.0 {
                x += self.noise * gauss(rng);
            }
            *v = x.clamp(0.0, 1.0) * 2.0 - 1.0;
        }
    }
}

/// Separable Gaussian blur of one `(h, w)` plane, standard deviation `sigma` pixels, the
/// kernel cut at 3 sigma and the border clamped.
pub fn gaussian_blur(plane: &mut [f32], (w, h): (usize, usize), sigma: f32) {
    let r = (3.0 * sigma).ceil() as isize;
    let mut k: Vec<f32> = (-r..=r).map(|d| (-(d * d) as f32 / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f32 = k.iter().sum();
    k.iter_mut().for_each(|x| *x /= sum);
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    let mut tmp = vec![0.0f32; plane.len()];
    for y in 0..h {
        for x in 0..w {
            tmp[y * w + x] = (-r..=r).map(|d| k[(d + r) as usize] * plane[y * w + clamp(x as isize + d, w)]).sum();
        }
    }
    for y in 0..h {
        for x in 0..w {
            plane[y * w + x] = (-r..=r).map(|d| k[(d + r) as usize] * tmp[clamp(y as isize + d, h) * w + x]).sum();
        }
    }
}
