//! Input preprocessing exactly as Dens3R's `load_images` (model spec section 2) and the
//! inverse `rotate_recover` (section 3.2).

use crate::BackboneError;
use burn::tensor::{Device, Tensor, TensorData};
use image::{DynamicImage, ImageDecoder, RgbImage};
use std::path::Path;

/// How an image became a network input, and how to map outputs back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PrepInfo {
    /// Size after EXIF orientation, before anything else (width, height).
    pub original: (u32, u32),
    /// The image was portrait and was rotated 90 degrees counter-clockwise to landscape.
    pub rotated: bool,
    /// Size after rotation and resizing (width, height).
    pub resized: (u32, u32),
    /// Crop box `(x0, y0, x1, y1)` in the resized image.
    pub crop: (u32, u32, u32, u32),
}

impl PrepInfo {
    /// Network input size (width, height).
    pub fn input_size(&self) -> (u32, u32) {
        (self.crop.2 - self.crop.0, self.crop.3 - self.crop.1)
    }

    /// Pixels of the network input per pixel of the photo: the resize factor (cropping keeps a
    /// focal length in pixels unchanged, so this converts one).
    pub fn resize_factor(&self) -> f64 {
        let (o, r) = (self.original, self.resized);
        f64::from(r.0.max(r.1)) / f64::from(o.0.max(o.1).max(1))
    }

    /// The resized size, the crop's offset in it and the network input's size, each
    /// `(width, height)` in the photo's own orientation (a rotated image's `size_info`
    /// permuted as `[1,0,3,2,5,4,7,6]`, as `rescale_to_orig` reads it).
    pub fn oriented(&self) -> ((u32, u32), (u32, u32), (u32, u32)) {
        let (rw, rh) = self.resized;
        let (x0, y0) = (self.crop.0, self.crop.1);
        let (iw, ih) = self.input_size();
        if self.rotated {
            ((rh, rw), (y0, x0), (ih, iw))
        } else {
            ((rw, rh), (x0, y0), (iw, ih))
        }
    }
}

/// A preprocessed image.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The network input as RGB (landscape, cropped).
    pub rgb: RgbImage,
    /// Geometry of the transformation.
    pub info: PrepInfo,
}

impl Prepared {
    /// `(1, 3, H, W)` tensor normalised to `[-1, 1]` ([`normalised_planes`] with
    /// [`DENS3R_MEAN`] / [`DENS3R_STD`]).
    pub fn tensor(&self, device: &Device) -> Tensor<4> {
        let (w, h) = self.rgb.dimensions();
        let v = normalised_planes(&self.rgb, DENS3R_MEAN, DENS3R_STD);
        Tensor::from_data(TensorData::new(v, [1, 3, h as usize, w as usize]), device)
    }
}

/// Dens3R's input normalisation (torchvision `Normalize(0.5, 0.5)` after `ToTensor`): pixels
/// to `[-1, 1]`.
pub const DENS3R_MEAN: [f32; 3] = [0.5; 3];
/// See [`DENS3R_MEAN`].
pub const DENS3R_STD: [f32; 3] = [0.5; 3];

/// The one input normalisation: `(x / 255 - mean) / std` per channel, as `(3, H, W)` planes
/// row-major (Dens3R's [`DENS3R_MEAN`] / [`DENS3R_STD`], or DINOv2's ImageNet statistics).
pub fn normalised_planes(image: &RgbImage, mean: [f32; 3], std: [f32; 3]) -> Vec<f32> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let mut out = vec![0.0; 3 * h * w];
    for (i, p) in image.pixels().enumerate() {
        for c in 0..3 {
            out[c * h * w + i] = (p[c] as f32 / 255.0 - mean[c]) / std[c];
        }
    }
    out
}

/// Python's `round` (half to even) of a non-negative float.
fn round_half_even(x: f64) -> u32 {
    let r = x.round();
    if (x - x.trunc() - 0.5).abs() < 1e-12 && r as u64 % 2 == 1 {
        (r - 1.0) as u32
    } else {
        r as u32
    }
}

/// Resized size (width, height) for long side `size`: `round(W L / S) x round(H L / S)`.
pub fn resized_size(w: u32, h: u32, size: u32) -> (u32, u32) {
    let s = w.max(h) as f64;
    (round_half_even(w as f64 * size as f64 / s), round_half_even(h as f64 * size as f64 / s))
}

/// The centred crop to multiples of 16 of a `w x h` image: `(x0, y0, x1, y1)`.
pub fn crop_box(w: u32, h: u32) -> (u32, u32, u32, u32) {
    let (cx, cy) = (w / 2, h / 2);
    let (hw, hh) = (((2 * cx) / 16) * 8, ((2 * cy) / 16) * 8);
    (cx - hw, cy - hh, cx + hw, cy + hh)
}

/// Whether `bytes` is a JPEG whose last scan (start-of-scan marker `FF DA`) is not followed by
/// an end-of-image marker (`FF D9`): the file was cut off. Entropy-coded data never holds
/// `FF D9` (a data `FF` is stuffed as `FF 00`), and an EXIF thumbnail's markers come before
/// the main image's scans.
pub fn jpeg_truncated(bytes: &[u8]) -> bool {
    if !bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        return false;
    }
    let Some(sos) = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]) else { return true };
    !bytes[sos..].windows(2).any(|w| w == [0xFF, 0xD9])
}

/// The network input's long sides [`preprocess`] takes.
pub const SIZES: std::ops::RangeInclusive<u32> = 16..=8192;

/// Most pixels of an image read by [`open_oriented`] (16384 x 16384: phone photos of 200
/// Mpixels pass).
pub const MAX_PIXELS: u64 = 16384 * 16384;

/// Most bytes [`open_oriented`] decodes a file of `file_len` bytes into: 256 MB, or 2000 times
/// the file (images compress, even uniform ones not past that), and never over 1 GB.
pub fn max_decoded_bytes(file_len: u64) -> u64 {
    (256u64 << 20).max(file_len.saturating_mul(2000)).min(1 << 30)
}

/// Reads an image file applying its EXIF orientation.
pub fn open_oriented(path: &Path) -> Result<DynamicImage, BackboneError> {
    let bytes = std::fs::read(path).map_err(|e| BackboneError::file(path, format!("cannot read ({e})")))?;
    decode_oriented(path, &bytes)
}

/// [`open_oriented`] of a file's `bytes` already in memory (`path` names it in errors).
pub fn decode_oriented(path: &Path, bytes: &[u8]) -> Result<DynamicImage, BackboneError> {
    let file = |m: String| BackboneError::file(path, m);
    let err =
        |e: image::ImageError| file(format!("unreadable image ({e}); give an undamaged PNG, JPEG, PGM or PPM file"));
    let mut decoder = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| file(format!("cannot read ({e})")))?
        .into_decoder()
        .map_err(err)?;
    // A damaged header can claim any size: refuse before the pixels are allocated.
    let (w, h) = image::ImageDecoder::dimensions(&decoder);
    let most = max_decoded_bytes(bytes.len() as u64);
    if u64::from(w) * u64::from(h) > MAX_PIXELS || image::ImageDecoder::total_bytes(&decoder) > most {
        return Err(file(format!(
            "the image claims {w}x{h} pixels, more than this {}-byte file can hold ({} MB decoded at most, {} Mpixels); \
             check that the file is not damaged, or resize it",
            bytes.len(),
            most >> 20,
            MAX_PIXELS / 1_000_000
        )));
    }
    // JPEG decoders fill a cut-off file's missing rows with grey without a word.
    if jpeg_truncated(bytes) {
        return Err(file(
            "the JPEG is truncated (no end of image after its last scan); copy or export it again".into(),
        ));
    }
    let orientation = decoder.orientation().map_err(err)?;
    let mut img = DynamicImage::from_decoder(decoder).map_err(err)?;
    img.apply_orientation(orientation);
    Ok(img)
}

/// Preprocesses an oriented image for long side `size` (512 or 1024 for Dens3R):
/// portrait -> rotate 90 degrees counter-clockwise; resize (Lanczos3 when shrinking,
/// Catmull-Rom bicubic otherwise, as PIL's LANCZOS / BICUBIC); centre crop to multiples of 16.
/// `rotate_portrait = false` keeps portrait images as they are (upstream DUSt3R / MASt3R).
pub fn preprocess(img: &DynamicImage, size: u32, rotate_portrait: bool) -> Result<Prepared, BackboneError> {
    let (w0, h0) = (img.width(), img.height());
    if w0 == 0 || h0 == 0 {
        return Err(BackboneError::invalid("image is empty"));
    }
    if !SIZES.contains(&size) {
        return Err(BackboneError::invalid(format!("size {size} must be in {SIZES:?}")));
    }
    let rotated = rotate_portrait && w0 < h0;
    let rgb = img.to_rgb8();
    let rgb = if rotated { image::imageops::rotate270(&rgb) } else { rgb };
    let (w, h) = rgb.dimensions();
    let (rw, rh) = resized_size(w, h, size);
    let filter =
        if w.max(h) > size { image::imageops::FilterType::Lanczos3 } else { image::imageops::FilterType::CatmullRom };
    let resized = image::imageops::resize(&rgb, rw.max(1), rh.max(1), filter);
    let crop = crop_box(rw, rh);
    if crop.2 <= crop.0 || crop.3 <= crop.1 {
        return Err(BackboneError::invalid(format!(
            "image of {w0}x{h0} is too small for size {size}: the crop to multiples of 16 is empty"
        )));
    }
    let cropped = image::imageops::crop_imm(&resized, crop.0, crop.1, crop.2 - crop.0, crop.3 - crop.1).to_image();
    Ok(Prepared { rgb: cropped, info: PrepInfo { original: (w0, h0), rotated, resized: (rw, rh), crop } })
}

/// Undoes the portrait rotation of an `(H, W, C)` row-major map: rotates it 90 degrees
/// clockwise (numpy `rot90(k=-1)`), returning the new `(H, W)`.
pub fn rotate_map_clockwise<T: Copy>(data: &[T], h: usize, w: usize, c: usize) -> (Vec<T>, usize, usize) {
    // out has shape (w, h): out[i][j] = in[h - 1 - j][i]
    let mut out = Vec::with_capacity(data.len());
    for i in 0..w {
        for j in 0..h {
            let src = ((h - 1 - j) * w + i) * c;
            out.extend_from_slice(&data[src..src + c]);
        }
    }
    (out, w, h)
}

/// `rescale_to_orig` (spec 3.3) of an `(H, W, C)` row-major map at network-input resolution
/// **in the image's own orientation** (after [`rotate_map_clockwise`] for portrait images, as
/// the official code runs `rotate_recover` first and then rescales with the permuted
/// `size_info`): edge-pad the crop back to the resized size, then nearest-neighbour resize
/// (OpenCV's `INTER_NEAREST`, source index `floor(dst * src_size / dst_size)`) to the original
/// size. Returns the map and its `(H, W)`.
pub fn rescale_to_original<T: Copy>(data: &[T], info: &PrepInfo, c: usize) -> (Vec<T>, usize, usize) {
    let ((rw, rh), (x0, y0), (iw, ih)) = info.oriented();
    let (rw, rh, x0, y0, iw, ih) = (rw as usize, rh as usize, x0 as usize, y0 as usize, iw as usize, ih as usize);
    assert_eq!(data.len(), iw * ih * c, "map does not have the network-input size");
    let (ow, oh) = (info.original.0 as usize, info.original.1 as usize);
    let mut out = Vec::with_capacity(ow * oh * c);
    for y in 0..oh {
        // resized-image row, then clamped into the crop (edge padding)
        let ry = (y * rh / oh).min(rh - 1);
        let cy = ry.clamp(y0, y0 + ih - 1) - y0;
        for x in 0..ow {
            let rx = (x * rw / ow).min(rw - 1);
            let cx = rx.clamp(x0, x0 + iw - 1) - x0;
            out.extend_from_slice(&data[(cy * iw + cx) * c..][..c]);
        }
    }
    (out, oh, ow)
}

/// Rotation applied to OpenCV-frame vectors (points and normals) when undoing the portrait
/// rotation: `R_z(+90)`, `(x, y, z) -> (-y, x, z)`.
pub fn unrotate_vector(v: [f32; 3]) -> [f32; 3] {
    [-v[1], v[0], v[2]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_header_claiming_more_pixels_than_the_file_can_hold_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.jpg");
        image::RgbImage::from_pixel(20, 12, image::Rgb([90, 100, 110])).save(&path).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        // The baseline frame header: FF C0, length, precision, then height and width.
        let sof = bytes.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
        bytes[sof + 5..sof + 9].copy_from_slice(&[0xFF, 0xFF, 0xFF, 0xFF]);
        std::fs::write(&path, &bytes).unwrap();
        // It used to allocate 12.9 GB (65535 x 65535 x 3) for a file of a few hundred bytes.
        let e = open_oriented(&path).unwrap_err().to_string();
        assert!(e.contains("big.jpg") && e.contains("65535x65535"), "{e}");
        // A 108-Mpixel phone photo (12000 x 9000, 324 MB decoded) of 25 MB passes the bound.
        assert!(max_decoded_bytes(25 << 20) >= 12000 * 9000 * 3);
        assert_eq!(max_decoded_bytes(700), 256 << 20);
    }

    #[test]
    fn a_truncated_jpeg_is_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let img = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, 90]));
        let path = dir.path().join("whole.jpg");
        img.save(&path).unwrap();
        assert_eq!(open_oriented(&path).unwrap().width(), 64);
        let bytes = std::fs::read(&path).unwrap();
        let cut = dir.path().join("cut.jpg");
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let e = open_oriented(&cut).unwrap_err().to_string();
        assert!(e.contains("cut.jpg") && e.contains("truncated"), "{e}");
        // Data after the end of the image (camera trailers) is not truncation.
        let mut trailer = bytes.clone();
        trailer.extend_from_slice(b"trailer bytes");
        std::fs::write(&cut, &trailer).unwrap();
        assert!(open_oriented(&cut).is_ok());
        // A cut PNG fails in its decoder: named, with the formats read.
        let png = dir.path().join("whole.png");
        img.save(&png).unwrap();
        let bytes = std::fs::read(&png).unwrap();
        let cut = dir.path().join("cut.png");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let e = open_oriented(&cut).unwrap_err().to_string();
        assert!(e.contains("cut.png") && e.contains("unreadable image") && e.contains("PNG, JPEG, PGM or PPM"), "{e}");
    }

    #[test]
    fn spec_examples() {
        // Spec section 2 step 4.
        for ((w, h), resized, input) in [
            ((1920, 1080), (512, 288), (512, 288)),
            ((4032, 3024), (512, 384), (512, 384)),
            ((1000, 750), (512, 384), (512, 384)),
            ((1000, 700), (512, 358), (512, 352)),
        ] {
            let img = DynamicImage::new_rgb8(w, h);
            let p = preprocess(&img, 512, true).unwrap();
            assert_eq!((p.info.resized, p.info.input_size(), p.info.rotated), (resized, input, false), "{w}x{h}");
        }
        // Python rounds half to even: 2.5 -> 2, 3.5 -> 4.
        assert_eq!((round_half_even(2.5), round_half_even(3.5), round_half_even(2.4999)), (2, 4, 2));
        // A portrait phone photo is rotated to landscape.
        let p = preprocess(&DynamicImage::new_rgb8(3024, 4032), 512, true).unwrap();
        assert_eq!((p.info.rotated, p.info.input_size()), (true, (512, 384)));
        let p = preprocess(&DynamicImage::new_rgb8(3024, 4032), 512, false).unwrap();
        assert_eq!((p.info.rotated, p.info.input_size()), (false, (384, 512)));
        assert!(preprocess(&DynamicImage::new_rgb8(4, 2), 8, true).is_err());
    }

    #[test]
    fn rescale_to_original_pads_edges_and_picks_nearest() {
        // Original 40 x 24 resized to 20 x 12; a hand-made crop (2, 2)-(18, 10) exercises the
        // edge padding on all four sides.
        let info = PrepInfo { original: (40, 24), rotated: false, resized: (20, 12), crop: (2, 2, 18, 10) };
        let (iw, ih) = (16usize, 8usize);
        // Map value = crop-frame (x, y) encoded as x + 100 y.
        let data: Vec<i32> = (0..ih).flat_map(|y| (0..iw).map(move |x| (x + 100 * y) as i32)).collect();
        let (out, h, w) = rescale_to_original(&data, &info, 1);
        assert_eq!((h, w), (24, 40));
        for y in 0..24 {
            for x in 0..40 {
                // original pixel -> resized pixel (x/2, y/2) -> clamped into the crop
                let (rx, ry) = (x / 2, y / 2);
                let (cx, cy) = (rx.clamp(2, 17) - 2, ry.clamp(2, 9) - 2);
                assert_eq!(out[y * 40 + x], (cx + 100 * cy) as i32, "pixel ({x}, {y})");
            }
        }
        // Portrait: the same geometry transposed. The map arrives rotated back (8 wide, 16
        // tall) and comes out at the portrait size, sampled with the permuted size info.
        let info = PrepInfo { original: (24, 40), rotated: true, ..info };
        let tdata: Vec<i32> = (0..iw).flat_map(|x| (0..ih).map(move |y| (x + 100 * y) as i32)).collect();
        let (out, h, w) = rescale_to_original(&tdata, &info, 1);
        assert_eq!((h, w), (40, 24));
        for y in 0..40 {
            for x in 0..24 {
                let (cx, cy) = ((y / 2).clamp(2, 17) - 2, (x / 2).clamp(2, 9) - 2);
                assert_eq!(out[y * 24 + x], (cx + 100 * cy) as i32, "portrait pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn portrait_rotation_round_trips() {
        // Rotating counter-clockwise (as preprocessing does) then back clockwise is identity.
        let img = RgbImage::from_fn(5, 3, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let ccw = image::imageops::rotate270(&img);
        let (back, h, w) = rotate_map_clockwise(ccw.as_raw(), ccw.height() as usize, ccw.width() as usize, 3);
        assert_eq!((w, h), (5, 3));
        assert_eq!(back, img.into_raw());
        // The camera-frame rotation: the rotated view's x axis is the portrait's y axis.
        assert_eq!(unrotate_vector([1.0, 0.0, 2.0]), [0.0, 1.0, 2.0]);
    }

    #[test]
    fn tensor_is_normalised_chw() {
        let img = DynamicImage::ImageRgb8(RgbImage::from_fn(32, 16, |x, _| {
            image::Rgb([if x == 0 { 255 } else { 0 }, 128, 0])
        }));
        let p = preprocess(&img, 32, true).unwrap();
        let t = p.tensor(&Device::flex()).to_data();
        assert_eq!(t.shape().to_vec(), vec![1, 3, 16, 32]);
        let v = t.try_to_vec::<f32>().unwrap();
        assert_eq!((v[0], v[1], v[16 * 32 * 2]), (1.0, -1.0, -1.0));
    }
}
