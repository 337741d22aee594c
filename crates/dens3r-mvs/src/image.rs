//! Grey working images: the photo resized to the working size, and its pyramid.

use dens3r_geom::Intrinsics;
use image::RgbImage;

/// A grey image (0..1, linear in the photo's encoded values) sampled bilinearly.
#[derive(Debug, Clone, PartialEq)]
pub struct Grey {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl Grey {
    /// The photo's luma (Rec. 601 weights), 0..1.
    pub fn from_rgb(img: &RgbImage) -> Self {
        let data =
            img.pixels().map(|p| (0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32) / 255.0).collect();
        Self { width: img.width() as usize, height: img.height() as usize, data }
    }

    /// An image from its pixels, row-major.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), width * height, "grey image of {width} x {height} needs that many pixels");
        Self { width, height, data }
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
    #[inline]
    pub fn sample(&self, u: f32, v: f32) -> f32 {
        let u = u.clamp(0.0, (self.width - 1) as f32);
        let v = v.clamp(0.0, (self.height - 1) as f32);
        let x0 = u as usize;
        let y0 = v as usize;
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        let fx = u - x0 as f32;
        let fy = v - y0 as f32;
        let r0 = y0 * self.width;
        let r1 = y1 * self.width;
        let a = self.data[r0 + x0] + fx * (self.data[r0 + x1] - self.data[r0 + x0]);
        let b = self.data[r1 + x0] + fx * (self.data[r1 + x1] - self.data[r1 + x0]);
        a + fy * (b - a)
    }

    /// Half the size: each pixel the mean of its 2 x 2 block (intrinsics follow by
    /// `Intrinsics::scaled(0.5, 0.5)`).
    pub fn half(&self) -> Self {
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h {
            let (y0, y1) = ((2 * y).min(self.height - 1), (2 * y + 1).min(self.height - 1));
            for x in 0..w {
                let (x0, x1) = ((2 * x).min(self.width - 1), (2 * x + 1).min(self.width - 1));
                data.push(0.25 * (self.at(x0, y0) + self.at(x1, y0) + self.at(x0, y1) + self.at(x1, y1)));
            }
        }
        Self { width: w, height: h, data }
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
