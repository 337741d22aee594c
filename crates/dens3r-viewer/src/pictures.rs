//! Sizing the per-view pictures (drawn by `dens3r_scene::viz`) and the frustums' photo
//! thumbnails.

use base64::Engine;
use image::{imageops::FilterType, RgbImage};

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
