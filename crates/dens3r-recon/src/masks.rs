//! Object masks in: one picture per photo (what a background remover or a segmentation tool
//! writes), taken through the photo's own preprocessing so each lands on the maps' pixels.
//! Masked-out pixels are left out of the mesh and marked in the scene folder's `masks/`.

use crate::input::{InputImage, IMAGE_EXTENSIONS};
use crate::ReconError;
use dens3r_backbone::preprocess::{decode_oriented, preprocess};
use dens3r_geom::Raster;
use image::imageops::rotate90;
use image::{DynamicImage, GrayImage};
use std::path::{Path, PathBuf};

/// The mask file of `image` in `dir`: the photo's file stem with one of [`IMAGE_EXTENSIONS`].
pub fn mask_path(image: &InputImage, dir: &Path) -> Result<PathBuf, ReconError> {
    let stem = image.path.file_stem().and_then(|s| s.to_str()).unwrap_or(&image.name);
    IMAGE_EXTENSIONS
        .iter()
        .flat_map(|e| [e.to_string(), e.to_ascii_uppercase()])
        .map(|e| dir.join(format!("{stem}.{e}")))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            ReconError::input(
                dir,
                format!(
                    "no mask for photo {} (expected {stem}.png here: white = object, black = background)",
                    image.path.display()
                ),
            )
        })
}

/// Which pixels of a decoded mask picture keep the object: its alpha where it has one (a
/// cut-out with a transparent background), else its grey level; at least half keeps.
pub fn keep_pixels(mask: &DynamicImage) -> GrayImage {
    if mask.color().has_alpha() {
        let la = mask.to_luma_alpha8();
        GrayImage::from_fn(la.width(), la.height(), |x, y| image::Luma([la.get_pixel(x, y).0[1]]))
    } else {
        mask.to_luma8()
    }
}

/// Reads `path` as `image`'s mask (the photo's size, after EXIF orientation) and takes it
/// through the photo's preprocessing (portrait rotation, resize, centre crop): `true` where the
/// object is, at the size of the maps ([`InputImage::size`]).
pub fn read_mask(image: &InputImage, path: &Path) -> Result<Raster<bool>, ReconError> {
    let bytes = std::fs::read(path).map_err(|e| ReconError::input(path, format!("cannot read ({e})")))?;
    let decoded = decode_oriented(path, &bytes)?;
    let info = &image.prep.info;
    if (decoded.width(), decoded.height()) != info.original {
        return Err(ReconError::input(
            path,
            format!(
                "the mask is {}x{} but its photo {} is {}x{}; a mask must have its photo's size",
                decoded.width(),
                decoded.height(),
                image.path.display(),
                info.original.0,
                info.original.1
            ),
        ));
    }
    // The photo's own preprocessing (same size and portrait rotation give the same resize and
    // crop), then back to the photo's orientation as the maps are.
    let keep = DynamicImage::ImageLuma8(keep_pixels(&decoded));
    let prep = preprocess(&keep, info.resized.0.max(info.resized.1), info.rotated)?;
    let luma = image::imageops::grayscale(&prep.rgb);
    let own = if prep.info.rotated { rotate90(&luma) } else { luma };
    let (w, h) = image.size();
    debug_assert_eq!((own.width() as usize, own.height() as usize), (w, h));
    Raster::from_vec(w, h, own.pixels().map(|p| p.0[0] >= 128).collect())
        .map_err(|e| ReconError::input(path, e.to_string()))
}

/// Attaches every photo's mask from `dir` ([`mask_path`], [`read_mask`]); any missing or
/// unreadable mask fails the call before work starts.
pub fn attach_masks(images: &mut [InputImage], dir: &Path) -> Result<(), ReconError> {
    if !dir.is_dir() {
        return Err(ReconError::input(dir, "no such folder (--masks: a folder with one mask picture per photo)"));
    }
    for im in images.iter_mut() {
        let path = mask_path(im, dir)?;
        let mask = read_mask(im, &path)?;
        if !mask.data().iter().any(|&k| k) {
            return Err(ReconError::input(&path, "the mask keeps no pixel (white = object, black = background)"));
        }
        im.mask = Some(mask);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::input::load_images;

    /// A photo with a white disc, and its mask: the disc's pixels. Landscape and portrait,
    /// downsized and cropped: the mask lands where the photo's disc landed in the maps.
    #[test]
    fn a_mask_lands_on_the_pixels_its_photo_landed_on() {
        let dir = tempfile::tempdir().unwrap();
        for (w, h) in [(400u32, 300u32), (300, 400), (333, 250)] {
            let (cx, cy, r) = (w as f64 * 0.6, h as f64 * 0.4, 60.0);
            let inside = |x: u32, y: u32| (x as f64 + 0.5 - cx).hypot(y as f64 + 0.5 - cy) < r;
            let photo = image::RgbImage::from_fn(w, h, |x, y| image::Rgb(if inside(x, y) { [255; 3] } else { [0; 3] }));
            let p = dir.path().join(format!("p{w}x{h}.png"));
            photo.save(&p).unwrap();
            let masks = dir.path().join("masks");
            std::fs::create_dir_all(&masks).unwrap();
            // The mask as a cut-out: transparent background.
            let cut =
                image::RgbaImage::from_fn(w, h, |x, y| image::Rgba([9, 9, 9, if inside(x, y) { 255 } else { 0 }]));
            cut.save(masks.join(format!("p{w}x{h}.png"))).unwrap();
            let mut ims = load_images(&[p], 224, false).unwrap();
            attach_masks(&mut ims, &masks).unwrap();
            let rgb = ims[0].rgb();
            let mask = ims[0].mask.as_ref().unwrap();
            assert_eq!((mask.width(), mask.height()), (rgb.width() as usize, rgb.height() as usize));
            // Away from the disc's edge the photo is pure white or black: the mask must agree.
            let (mut agree, mut total) = (0, 0);
            for (x, y, px) in rgb.enumerate_pixels() {
                let v = px.0[0];
                if !(15..=240).contains(&v) {
                    total += 1;
                    agree += usize::from((v > 240) == *mask.get(x as usize, y as usize));
                }
            }
            assert!(total > 1000 && agree as f64 / total as f64 > 0.995, "{w}x{h}: {agree} of {total}");
        }
    }

    #[test]
    fn masks_of_the_wrong_size_or_missing_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        image::RgbImage::new(64, 48).save(&p).unwrap();
        let masks = dir.path().join("m");
        std::fs::create_dir_all(&masks).unwrap();
        let mut ims = load_images(&[p], 224, false).unwrap();
        let e = attach_masks(&mut ims, &masks).unwrap_err().to_string();
        assert!(e.contains("no mask for photo") && e.contains("a.png"), "{e}");
        image::GrayImage::new(48, 64).save(masks.join("a.png")).unwrap();
        let e = attach_masks(&mut ims, &masks).unwrap_err().to_string();
        assert!(e.contains("48x64") && e.contains("64x48"), "{e}");
        image::GrayImage::new(64, 48).save(masks.join("a.png")).unwrap();
        let e = attach_masks(&mut ims, &masks).unwrap_err().to_string();
        assert!(e.contains("keeps no pixel"), "{e}");
        assert!(ims[0].mask.is_none());
    }
}
