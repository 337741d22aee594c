//! Photos in: decoding with EXIF orientation, Dens3R preprocessing (portrait rotated to
//! landscape, resize, crop to multiples of 16), unique names, content hashes for the cache.

use crate::ReconError;
use dens3r_backbone::preprocess::{open_oriented, preprocess, Prepared};
use image::RgbImage;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// File extensions read from a photo folder (case-insensitive).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

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
                return Err(ReconError::input(p, "no .png / .jpg / .jpeg images in this folder"));
            }
            out.extend(files);
        } else if p.is_file() {
            out.push(p.clone());
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
        let img = open_oriented(p)?;
        let prep = preprocess(&img, size, !keep_portrait).map_err(|e| ReconError::input(p, e.to_string()))?;
        out.push(InputImage { name: unique_name(p, &mut names), path: p.clone(), prep, hash: fnv1a(&bytes, 0) });
    }
    Ok(out)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique() {
        let mut t = HashSet::new();
        let a = unique_name(Path::new("x/a.png"), &mut t);
        let b = unique_name(Path::new("y/a.jpg"), &mut t);
        assert_eq!((a.as_str(), b.as_str()), ("a", "a_1"));
    }
}
