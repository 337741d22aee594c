//! Grey working images: the photo resized to the working size, and its pyramid.

use dens3r_geom::Intrinsics;
use image::RgbImage;

/// A grey image (0..1, linear in the photo's encoded values) sampled bilinearly.
#[derive(Debug, Clone, PartialEq)]
pub struct Grey {
    width: usize,
    height: usize,
    data: Vec<f32>,
    /// Largest sample coordinates whose 2 x 2 neighbourhood is inside (just under w - 1, h - 1).
    umax: f32,
    vmax: f32,
}

fn limit(n: usize) -> f32 {
    (n as f32 - 1.0 - 1e-3).max(0.0)
}

impl Grey {
    /// The photo's luma (Rec. 601 weights), 0..1.
    pub fn from_rgb(img: &RgbImage) -> Self {
        let data =
            img.pixels().map(|p| (0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32) / 255.0).collect();
        let (width, height) = (img.width() as usize, img.height() as usize);
        Self::from_vec(width, height, data)
    }

    /// An image from its pixels, row-major.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), width * height, "grey image of {width} x {height} needs that many pixels");
        assert!(width >= 2 && height >= 2, "grey images are at least 2 x 2");
        Self { width, height, data, umax: limit(width), vmax: limit(height) }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Pixel `(x, y)`.
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Bilinear sample at `(u, v)` (pixel centres at integers), clamped at the border.
    #[inline(always)]
    pub fn sample(&self, u: f32, v: f32) -> f32 {
        // NaN clamps to 0 through `max`.
        let u = u.max(0.0).min(self.umax);
        let v = v.max(0.0).min(self.vmax);
        let (x0, y0) = (u as usize, v as usize);
        let (fx, fy) = (u - x0 as f32, v - y0 as f32);
        let i = y0 * self.width + x0;
        // In bounds: x0 + 1 <= width - 1 and y0 + 1 <= height - 1 by the clamps above.
        let (a, b, c, d) = if i + self.width + 1 < self.data.len() {
            // SAFETY: the largest index read, i + width + 1, was just checked.
            unsafe {
                (
                    *self.data.get_unchecked(i),
                    *self.data.get_unchecked(i + 1),
                    *self.data.get_unchecked(i + self.width),
                    *self.data.get_unchecked(i + self.width + 1),
                )
            }
        } else {
            return self.data[i.min(self.data.len() - 1)];
        };
        let top = a + fx * (b - a);
        let bottom = c + fx * (d - c);
        top + fy * (bottom - top)
    }

    /// Pixels, width and the largest in-bounds sample coordinates, for vector kernels.
    pub(crate) fn raw(&self) -> (&[f32], usize, f32, f32) {
        (&self.data, self.width, self.umax, self.vmax)
    }

    /// Smoothed by a 3 x 3 binomial filter (clamped border): takes the edge off aliased
    /// pixel-scale texture that no two views see alike.
    pub fn smoothed(&self) -> Self {
        let (w, h) = (self.width, self.height);
        let at = |x: isize, y: isize| {
            self.data[(y.clamp(0, h as isize - 1) as usize) * w + x.clamp(0, w as isize - 1) as usize]
        };
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h as isize {
            for x in 0..w as isize {
                let row = |yy: isize| at(x - 1, yy) + 2.0 * at(x, yy) + at(x + 1, yy);
                data.push((row(y - 1) + 2.0 * row(y) + row(y + 1)) / 16.0);
            }
        }
        Self::from_vec(w, h, data)
    }

    /// Half the size: each pixel the mean of its 2 x 2 block (intrinsics follow by
    /// `Intrinsics::scaled(0.5, 0.5)`).
    pub fn half(&self) -> Self {
        let (w, h) = ((self.width / 2).max(2), (self.height / 2).max(2));
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h {
            let (y0, y1) = ((2 * y).min(self.height - 1), (2 * y + 1).min(self.height - 1));
            for x in 0..w {
                let (x0, x1) = ((2 * x).min(self.width - 1), (2 * x + 1).min(self.width - 1));
                data.push(0.25 * (self.at(x0, y0) + self.at(x1, y0) + self.at(x0, y1) + self.at(x1, y1)));
            }
        }
        Self::from_vec(w, h, data)
    }
}

/// The size a photo is worked at: its long side at most `max_size` (never enlarged).
pub fn working_size(width: usize, height: usize, max_size: usize) -> (usize, usize) {
    let long = width.max(height);
    if long <= max_size || max_size == 0 {
        return (width, height);
    }
    let s = max_size as f64 / long as f64;
    (((width as f64 * s).round() as usize).max(1), ((height as f64 * s).round() as usize).max(1))
}

/// The photo resized to `size` (a triangle filter) and its intrinsics moved along.
pub fn resize_view(img: &RgbImage, k: &Intrinsics, size: (usize, usize)) -> (RgbImage, Intrinsics) {
    let (w, h) = (img.width() as usize, img.height() as usize);
    if (w, h) == size {
        return (img.clone(), *k);
    }
    let out = image::imageops::resize(img, size.0 as u32, size.1 as u32, image::imageops::FilterType::Triangle);
    (out, k.scaled(size.0 as f64 / w as f64, size.1 as f64 / h as f64))
}

/// Intrinsics of a pyramid level `level` times halved from `k` (each halving as [`Grey::half`]).
pub fn level_intrinsics(k: &Intrinsics, level: usize) -> Intrinsics {
    (0..level).fold(*k, |k, _| k.scaled(0.5, 0.5))
}
