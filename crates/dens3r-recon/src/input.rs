//! Photos in: decoding with EXIF orientation, Dens3R preprocessing (portrait rotated to
//! landscape, resize, crop to multiples of 16), unique names, content hashes for the cache.

use crate::ReconError;
use dens3r_backbone::preprocess::{decode_oriented, preprocess, Prepared};
use image::RgbImage;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// File extensions read from a photo folder (case-insensitive): PNG, JPEG, and PGM / PPM (a
/// monochrome camera's frames often come as PGM).
pub const IMAGE_EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "pgm", "ppm"];

/// One input photo, preprocessed for the network.
#[derive(Debug, Clone)]
pub struct InputImage {
    /// Unique name (file stem, suffixed on clashes): the frame name in the scene folder.
    pub name: String,
    /// Where it was read from.
    pub path: PathBuf,
    /// The network input and how it was made.
    pub prep: Prepared,
    /// FNV-1a hash of the file's bytes (pair cache key).
    pub hash: u64,
    /// Focal length in pixels at [`size`](Self::size), when known: from the photo's EXIF 35 mm
    /// equivalent focal length ([`exif_focal`]), or given by [`set_focal`](Self::set_focal).
    /// Structure from motion keeps a focal the user gave fixed ([`focal_fixed`](Self::focal_fixed))
    /// and refines an EXIF focal with it as a prior; the dense path keeps either fixed.
    pub focal: Option<f64>,
    /// Whether `focal` was given by the user (kept fixed) rather than read from EXIF.
    pub focal_fixed: bool,
    /// What the user should know about this photo (an EXIF focal out of bounds, ignored).
    pub warnings: Vec<String>,
    /// Why the photo shows no scene ([`no_scene`]: too small, one flat colour, noise), where it
    /// does not: [`keep_scenes`] leaves it out of a reconstruction.
    pub no_scene: Option<String>,
    /// The object's pixels at [`size`](Self::size), when a mask was given
    /// ([`crate::masks::attach_masks`]): only these are fused into the mesh.
    pub mask: Option<dens3r_geom::Raster<bool>>,
}

impl InputImage {
    /// Size (width, height) of the maps predicted for this image: the network input in the
    /// photo's own orientation.
    pub fn size(&self) -> (usize, usize) {
        let (w, h) = self.prep.rgb.dimensions();
        if self.prep.info.rotated {
            (h as usize, w as usize)
        } else {
            (w as usize, h as usize)
        }
    }

    /// Sets the focal length from `photo_px`, in pixels of the photo as read (after its EXIF
    /// orientation, before resizing); `None` forgets it, so it is estimated.
    pub fn set_focal(&mut self, photo_px: Option<f64>) {
        self.focal = photo_px.filter(|f| f.is_finite() && *f > 0.0).map(|f| f * self.photo_to_map());
        self.focal_fixed = self.focal.is_some();
    }

    /// Refuses a focal (pixels of the photo as read) that gives the photo a horizontal field
    /// of view outside 1 to 170 degrees: a focal in other units, a typo; `flag` names it.
    pub fn check_focal(&self, photo_px: f64, flag: &str) -> Result<(), String> {
        check_focal(photo_px, self.prep.info.original.0 as f64, flag)
    }

    /// Pixels of the maps per pixel of the photo (the resize factor; cropping keeps the focal).
    pub fn photo_to_map(&self) -> f64 {
        self.prep.info.resize_factor()
    }

    /// The network input in the photo's own orientation (the colours of the scene frame).
    pub fn rgb(&self) -> RgbImage {
        if self.prep.info.rotated {
            image::imageops::rotate90(&self.prep.rgb)
        } else {
            self.prep.rgb.clone()
        }
    }
}

pub use dens3r_io::hash::fnv1a;

/// The photos of a folder (sorted by file name), or the given files as they are.
pub fn list_images(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, ReconError> {
    let mut out = Vec::new();
    for p in inputs {
        if p.is_dir() {
            let rd = std::fs::read_dir(p).map_err(|e| ReconError::input(p, format!("cannot list ({e})")))?;
            let mut files: Vec<PathBuf> = rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.is_file()
                        && f.extension()
                            .and_then(|e| e.to_str())
                            .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
                })
                .collect();
            files.sort();
            if files.is_empty() {
                let kinds: Vec<String> = IMAGE_EXTENSIONS.iter().map(|e| format!(".{e}")).collect();
                return Err(ReconError::input(p, format!("no {} images in this folder", kinds.join(" / "))));
            }
            out.extend(files);
        } else if p.is_file() {
            out.push(p.clone());
        } else if p.exists() {
            return Err(ReconError::input(
                p,
                "is not a regular file (a pipe or a device?); give a photo file or a folder of photos",
            ));
        } else {
            return Err(ReconError::input(p, "no such file or folder"));
        }
    }
    Ok(out)
}

/// Decodes and preprocesses every photo (long side `size`; portraits rotated unless
/// `keep_portrait`); any unreadable photo fails the whole call before work starts.
pub fn load_images(paths: &[PathBuf], size: u32, keep_portrait: bool) -> Result<Vec<InputImage>, ReconError> {
    let mut names = HashSet::new();
    let mut out = Vec::with_capacity(paths.len());
    for p in paths {
        let bytes = std::fs::read(p).map_err(|e| ReconError::input(p, format!("cannot read ({e})")))?;
        let img = decode_oriented(p, &bytes)?;
        let no_scene = no_scene(&img);
        let prep = preprocess(&img, size, !keep_portrait).map_err(|e| ReconError::input(p, e.to_string()))?;
        let (focal, warnings) = match exif_focal(&bytes, (img.width(), img.height())) {
            Ok(f) => (f, vec![]),
            Err(w) => (None, vec![format!("{}: {w}", p.display())]),
        };
        let mut im = InputImage {
            name: unique_name(p, &mut names),
            path: p.clone(),
            prep,
            hash: fnv1a(&bytes, 0),
            focal: None,
            focal_fixed: false,
            warnings,
            no_scene,
            mask: None,
        };
        im.set_focal(focal);
        im.focal_fixed = false;
        out.push(im);
    }
    Ok(out)
}

/// The smallest side, in pixels, of a photo that can show a scene.
pub const MIN_PHOTO_SIDE: u32 = 16;

/// Why `img` shows no scene a reconstruction could use, or None: smaller than
/// [`MIN_PHOTO_SIDE`] on a side; one flat colour (grey levels with a standard deviation under
/// 1.5 of 255: all black, all white, a blank frame); or noise (neighbouring pixels'
/// grey levels correlate under 0.25, where photographs, even of grass or gravel, correlate
/// above 0.5). Measured on at most about a million pixels, sampled on a grid.
pub fn no_scene(img: &image::DynamicImage) -> Option<String> {
    let (w, h) = (img.width(), img.height());
    if w.min(h) < MIN_PHOTO_SIDE {
        return Some(format!(
            "is {w} x {h} pixels: too small to show a scene (at least {MIN_PHOTO_SIDE} on each side)"
        ));
    }
    // Grey levels read at the sampled pixels only (a whole grey copy of a 12-megapixel photo
    // is 48 MB).
    let step = ((w as f64 * h as f64 / 1e6).sqrt().ceil() as u32).max(1);
    let at = |x: u32, y: u32| {
        use image::{GenericImageView, Pixel};
        f64::from(img.get_pixel(x, y).to_luma().0[0])
    };
    let (mut n, mut sum, mut sq) = (0.0, 0.0, 0.0);
    let (mut pairs, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for y in (0..h - 1).step_by(step as usize) {
        for x in (0..w - 1).step_by(step as usize) {
            let v = at(x, y);
            n += 1.0;
            sum += v;
            sq += v * v;
            for u in [at(x + 1, y), at(x, y + 1)] {
                pairs += 1.0;
                (sa, sb, saa, sbb, sab) = (sa + v, sb + u, saa + v * v, sbb + u * u, sab + v * u);
            }
        }
    }
    let var = (sq / n - (sum / n).powi(2)).max(0.0);
    if var.sqrt() < 1.5 {
        return Some("is one flat colour (no detail to see a scene in)".into());
    }
    let (ma, mb) = (sa / pairs, sb / pairs);
    let cov = sab / pairs - ma * mb;
    let corr = cov / ((saa / pairs - ma * ma).max(1e-12) * (sbb / pairs - mb * mb).max(1e-12)).sqrt();
    if corr < 0.25 {
        return Some(format!(
            "looks like noise, not a photograph (neighbouring pixels correlate {corr:.2}; photographs above 0.5)"
        ));
    }
    None
}

/// The photos of `images` that show a scene, and a warning naming each one left out and why
/// ([`InputImage::no_scene`]).
pub fn keep_scenes(images: Vec<InputImage>) -> (Vec<InputImage>, Vec<String>) {
    let mut warnings = Vec::new();
    let kept = images
        .into_iter()
        .filter(|im| match &im.no_scene {
            Some(why) => {
                warnings.push(format!("{}: {why}; left out", im.path.display()));
                false
            }
            None => true,
        })
        .collect();
    (kept, warnings)
}

/// Diagonal of a 36 x 24 mm frame, mm: a 35 mm equivalent focal length gives the same field of
/// view across the image diagonal as this lens on that frame (CIPA DC-008).
pub const FULL_FRAME_DIAGONAL_MM: f64 = 43.266_615;

/// The focal length in pixels of a `(w, h)` photo from its EXIF `FocalLengthIn35mmFilm` tag
/// (JPEG, PNG, TIFF or HEIF container): `f35 / 43.27 mm * diagonal`. `Ok(None)` when the file
/// has no EXIF, no such tag, or the value 0 ("unknown"); an error saying why where the focal
/// lies outside the bounds `--focal` has (fields of view of 1 to 170 degrees: a damaged or
/// edited tag), so it is not used.
pub fn exif_focal(bytes: &[u8], (w, h): (u32, u32)) -> Result<Option<f64>, String> {
    let Ok(exif) = exif::Reader::new().read_from_container(&mut std::io::Cursor::new(bytes)) else { return Ok(None) };
    let Some(f35) = exif
        .get_field(exif::Tag::FocalLengthIn35mmFilm, exif::In::PRIMARY)
        .and_then(|f| f.value.get_uint(0))
        .filter(|f| *f > 0)
    else {
        return Ok(None);
    };
    let f = f64::from(f35) / FULL_FRAME_DIAGONAL_MM * f64::from(w).hypot(f64::from(h));
    check_focal(f, f64::from(w), "EXIF 35 mm equivalent focal length").map_err(|_| {
        format!(
            "its EXIF focal length ({f35} mm, 35 mm equivalent: {f:.1} px) gives a field of view outside 1 to 170 degrees; ignored, the focal is estimated"
        )
    })?;
    Ok(Some(f))
}

/// A frame name for `p` not yet in `taken` (the file stem, suffixed `_1`, `_2`, .. on clashes),
/// recorded in `taken`.
pub fn unique_name(p: &Path, taken: &mut HashSet<String>) -> String {
    let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("image").replace(['/', '\\'], "_");
    let mut name = stem.clone();
    let mut k = 1;
    while !taken.insert(name.clone()) {
        name = format!("{stem}_{k}");
        k += 1;
    }
    name
}

/// Refuses a focal of `width`-pixel-wide photos (pixels) outside horizontal fields of view of
/// 1 to 170 degrees, naming `flag` and the range that fits.
pub fn check_focal(focal: f64, width: f64, flag: &str) -> Result<(), String> {
    let at = |deg: f64| width / (2.0 * (deg.to_radians() / 2.0).tan());
    let (lo, hi) = (at(170.0), at(1.0));
    if !(focal.is_finite() && focal >= lo && focal <= hi) {
        return Err(format!(
            "{flag} {focal}: for a {width:.0}-pixel-wide photo give a focal in its pixels between {lo:.0} and {hi:.0} \
             (fields of view of 170 to 1 degrees)"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A JPEG of `w x h` whose EXIF says `f35` mm (35 mm equivalent), as phones write it.
    fn jpeg_with_focal(w: u32, h: u32, f35: Option<u16>) -> Vec<u8> {
        use image::ImageEncoder;
        let img = RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7 % 256) as u8, (y * 5 % 256) as u8, 128]));
        let mut bytes = Vec::new();
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 90);
        if let Some(f) = f35 {
            let field = exif::Field {
                tag: exif::Tag::FocalLengthIn35mmFilm,
                ifd_num: exif::In::PRIMARY,
                value: exif::Value::Short(vec![f]),
            };
            let mut writer = exif::experimental::Writer::new();
            writer.push_field(&field);
            let mut tiff = std::io::Cursor::new(Vec::new());
            writer.write(&mut tiff, false).unwrap();
            enc.set_exif_metadata(tiff.into_inner()).unwrap();
        }
        enc.write_image(img.as_raw(), w, h, image::ExtendedColorType::Rgb8).unwrap();
        bytes
    }

    /// A phone's 26 mm (35 mm equivalent) main camera on a 4:3 photo: 79.5 degrees across the
    /// diagonal (2 atan(21.63 / 26)), 67.3 across the width (the width is 0.8 of the diagonal).
    #[test]
    fn exif_focal_gives_the_field_of_view_of_its_35mm_equivalent() {
        let bytes = jpeg_with_focal(400, 300, Some(26));
        let f = exif_focal(&bytes, (400, 300)).unwrap().expect("EXIF focal");
        let hfov = 2.0 * (200.0 / f).atan().to_degrees();
        let dfov = 2.0 * (250.0 / f).atan().to_degrees();
        assert!((hfov - 67.3).abs() < 0.1 && (dfov - 79.5).abs() < 0.1, "{hfov} {dfov}");
        // No EXIF, or "unknown" (0): no focal.
        assert_eq!(exif_focal(&jpeg_with_focal(400, 300, None), (400, 300)).unwrap(), None);
        assert_eq!(exif_focal(&jpeg_with_focal(400, 300, Some(0)), (400, 300)).unwrap(), None);
        // Issue 77, 9: an EXIF focal of 1 mm (a 173 deg field of view here) was kept as a
        // fixed focal of a few pixels, 3000 mm (0.7 deg) as a telescope's. Outside --focal's
        // bounds (1 to 170 degrees): ignored, and said why.
        for mm in [1, 3000] {
            let e = exif_focal(&jpeg_with_focal(400, 300, Some(mm)), (400, 300)).unwrap_err();
            assert!(e.contains(&format!("{mm} mm")) && e.contains("ignored"), "{e}");
        }
        assert!(exif_focal(&jpeg_with_focal(400, 300, Some(2)), (400, 300)).unwrap().is_some());

        // Loaded at long side 256 (0.64 of the photo), portrait or not: the focal follows the
        // resize, and the field of view stays.
        let dir = tempfile::tempdir().unwrap();
        let (land, port) = (dir.path().join("land.jpg"), dir.path().join("port.jpg"));
        std::fs::write(&land, &bytes).unwrap();
        std::fs::write(&port, jpeg_with_focal(300, 400, Some(26))).unwrap();
        let ims = load_images(&[land, port], 256, false).unwrap();
        for im in &ims {
            let fm = im.focal.expect("focal at the map size");
            let (w, h) = im.size();
            assert_eq!(w.max(h), 256);
            let dfov_map = 2.0 * ((w as f64).hypot(h as f64) / 2.0 / fm).atan().to_degrees();
            assert!((dfov_map - 79.5).abs() < 0.3, "{}: {dfov_map}", im.name);
            assert!(!im.focal_fixed, "an EXIF focal is a prior, not fixed");
        }
        // `set_focal` overrides, in photo pixels; `None` forgets.
        let mut im = ims[0].clone();
        im.set_focal(Some(500.0));
        assert!((im.focal.unwrap() - 320.0).abs() < 1e-9 && im.focal_fixed);
        im.set_focal(None);
        assert_eq!(im.focal, None);
    }

    /// Issue 77, 8: all-black, all-white, noise, 8x8 and 1x1 photos each gave cameras and a
    /// mesh. They are told apart from photographs (the bundled ones, and a dim, low-contrast
    /// one) by what they hold, and left out with a reason.
    #[test]
    fn photos_without_a_scene_are_named() {
        use image::{DynamicImage, Rgb, RgbImage};
        let mut seed = 12345u64;
        let mut rnd = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 56) as u8
        };
        let noise = RgbImage::from_fn(640, 480, |_, _| Rgb([rnd(), rnd(), rnd()]));
        let cases = [
            (RgbImage::new(640, 480), "flat"),
            (RgbImage::from_pixel(640, 480, Rgb([255, 255, 255])), "flat"),
            (noise, "noise"),
            (RgbImage::from_pixel(8, 8, Rgb([10, 200, 30])), "small"),
            (RgbImage::new(1, 1), "small"),
        ];
        for (img, kind) in cases {
            let why = no_scene(&DynamicImage::ImageRgb8(img)).unwrap_or_else(|| panic!("{kind} not found"));
            let word = match kind {
                "flat" => "flat colour",
                "noise" => "noise",
                _ => "too small",
            };
            assert!(why.contains(word), "{kind}: {why}");
        }
        let photos = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/photos");
        for name in ["chelsea.png", "coffee.png"] {
            let img = image::open(photos.join(name)).unwrap();
            assert_eq!(no_scene(&img), None, "{name}");
            // Dim and low in contrast (a night shot): still a photograph.
            let rgb = img.to_rgb8();
            let dim =
                RgbImage::from_fn(img.width(), img.height(), |x, y| Rgb(rgb.get_pixel(x, y).0.map(|c| 20 + c / 16)));
            assert_eq!(no_scene(&DynamicImage::ImageRgb8(dim)), None, "{name} dimmed");
        }
        let tiny = |w, h| InputImage { no_scene: Some(format!("{w}x{h}")), ..load_one() };
        let (kept, left) = keep_scenes(vec![load_one(), tiny(1, 1), load_one()]);
        assert_eq!(kept.len(), 2);
        assert!(left.len() == 1 && left[0].contains("1x1; left out"), "{left:?}");
    }

    fn load_one() -> InputImage {
        let photos = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/photos");
        load_images(&[photos.join("coffee.png")], 64, false).unwrap().remove(0)
    }

    /// A folder's PGM photos are listed (other files are not) and decode to grey RGB.
    #[test]
    fn pgm_photos_are_listed_and_read() {
        let dir = tempfile::tempdir().unwrap();
        let grey = image::GrayImage::from_fn(64, 48, |x, y| image::Luma([(x * 3 + y) as u8]));
        grey.save(dir.path().join("a.pgm")).unwrap();
        std::fs::write(dir.path().join("notes.txt"), "not a photo").unwrap();
        let paths = list_images(&[dir.path().to_path_buf()]).unwrap();
        assert_eq!(paths, vec![dir.path().join("a.pgm")]);
        let img = &load_images(&paths, 64, false).unwrap()[0];
        let rgb = img.rgb();
        let px = rgb.get_pixel(10, 5).0;
        assert!(px[0] == px[1] && px[1] == px[2] && px[0] == (10 * 3 + 5) as u8, "{px:?}");
    }

    #[test]
    fn names_are_unique() {
        let mut t = HashSet::new();
        let a = unique_name(Path::new("x/a.png"), &mut t);
        let b = unique_name(Path::new("y/a.jpg"), &mut t);
        assert_eq!((a.as_str(), b.as_str()), ("a", "a_1"));
    }
}
