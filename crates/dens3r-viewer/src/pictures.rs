//! The per-view pictures the page shows: depth and normals in the colours `dens3r predict`
//! uses (`dens3r_scene::viz`), confidence on a grey ramp, photo thumbnails for the frustums.

use base64::Engine;
use dens3r_geom::Raster;
use image::{imageops::FilterType, Rgb, RgbImage};

/// Confidence on a log grey ramp between its 2nd and 98th percentiles (bright: confident);
/// invalid values black.
pub fn conf_viz(c: &Raster<f32>) -> RgbImage {
    let mut v: Vec<f32> = c.data().iter().copied().filter(|x| x.is_finite() && *x > 0.0).map(f32::ln).collect();
    v.sort_by(f32::total_cmp);
    let q = |p: f32| v.get(((v.len().max(1) - 1) as f32 * p) as usize).copied().unwrap_or(0.0);
    let (lo, hi) = (q(0.02), q(0.98).max(q(0.02) + 1e-6));
    RgbImage::from_fn(c.width() as u32, c.height() as u32, |x, y| {
        let z = *c.get(x as usize, y as usize);
        if !(z.is_finite() && z > 0.0) {
            return Rgb([0, 0, 0]);
        }
        let g = (((z.ln() - lo) / (hi - lo)).clamp(0.0, 1.0) * 235.0 + 20.0) as u8;
        Rgb([g, g, g])
    })
}

/// `img` scaled so its longer side is at most `max_side` (never enlarged).
pub fn fit(img: &RgbImage, max_side: u32) -> RgbImage {
    let (w, h) = img.dimensions();
    let long = w.max(h);
    if long <= max_side || long == 0 {
        return img.clone();
    }
    let s = max_side as f64 / long as f64;
    let (nw, nh) = (((w as f64 * s).round() as u32).max(1), ((h as f64 * s).round() as u32).max(1));
    image::imageops::resize(img, nw, nh, FilterType::Triangle)
}

/// A JPEG `data:` URL of `img` (textures from `data:` URLs are allowed in WebGL on a page
/// opened from the file system, where a texture read from a file beside it is not).
pub fn jpeg_data_url(img: &RgbImage, quality: u8) -> String {
    let mut bytes = Vec::new();
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality);
    enc.encode_image(img).expect("encoding into memory does not fail");
    format!("data:image/jpeg;base64,{}", base64::engine::general_purpose::STANDARD.encode(bytes))
}
