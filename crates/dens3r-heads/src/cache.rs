//! On-disk feature cache: each image's frozen features are computed once and memory-mapped
//! afterwards, so training epochs never re-run the backbone. [`FeatureCache::store`] hands out
//! [`StoredFeatures`], a complete entry read at each use, so a training set's features need
//! not fit in memory.
//!
//! Key: the image's pixels and size (FNV-1a), the backbone id (kind, weights hash, hooked
//! layers) and the storage precision; a change of any gives a new entry. A file is a JSON
//! header line padded to 64 bytes, then the layers' values (f32 or f16, little endian); it is
//! written to a temporary file and renamed, and an entry that does not parse or has the wrong
//! length is recomputed. Which layers are raw pixels is the backbone's to say, not the file's.

use crate::features::{fnv1a, Backbone, FeatureMaps};
use crate::HeadsError;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Storage precision.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// Exact.
    F32,
    /// Half the size; values rounded to f16 (about 3 significant digits).
    F16,
}

#[derive(Serialize, Deserialize)]
struct Header {
    format: String,
    backbone: String,
    grid: (usize, usize),
    dims: Vec<usize>,
    f16: bool,
}

const FORMAT: &str = "dens3r-features/1";

/// A feature cache folder.
pub struct FeatureCache {
    dir: PathBuf,
    precision: Precision,
    /// Entries read from disk (hits) and computed (misses) so far.
    pub stats: (usize, usize),
}

impl FeatureCache {
    /// A cache in `dir` (created when first written).
    pub fn new(dir: &Path, precision: Precision) -> Self {
        Self { dir: dir.to_path_buf(), precision, stats: (0, 0) }
    }

    /// The entry path of an image for a backbone.
    pub fn entry(&self, backbone: &dyn Backbone, image: &RgbImage) -> PathBuf {
        let (w, h) = image.dimensions();
        let mut key = fnv1a(image.as_raw(), (w as u64) << 32 | h as u64);
        key = fnv1a(backbone.id().as_bytes(), key);
        let tag = if self.precision == Precision::F16 { "f16" } else { "f32" };
        self.dir.join(format!("{key:016x}-{w}x{h}.{tag}.feat"))
    }

    /// The features of `image`: read from the cache, or computed and stored.
    pub fn get(&mut self, backbone: &dyn Backbone, image: &RgbImage) -> Result<FeatureMaps, HeadsError> {
        self.store(backbone, image)?.read()
    }

    /// Makes sure `image` has a complete entry (computing and storing its features when it has
    /// none, or a damaged one) and returns it without holding its values.
    pub fn store(&mut self, backbone: &dyn Backbone, image: &RgbImage) -> Result<StoredFeatures, HeadsError> {
        let path = self.entry(backbone, image);
        let id = backbone.id();
        let grid = match check_entry(&path, &id) {
            Some(h) => {
                self.stats.0 += 1;
                h.grid
            }
            None => {
                let f = backbone.extract(image);
                self.stats.1 += 1;
                std::fs::create_dir_all(&self.dir)
                    .map_err(|e| HeadsError::file(&self.dir, format!("cannot create the cache ({e})")))?;
                write_entry(&path, &id, &f, self.precision)?;
                f.grid
            }
        };
        // Values are always served from what was stored, so a cached and a fresh run see the same.
        Ok(StoredFeatures { path, backbone: id, grid, pixel_layers: backbone.pixel_layers() })
    }
}

/// A complete cache entry: one image's features, read from disk at each [`StoredFeatures::read`].
#[derive(Debug, Clone, PartialEq)]
pub struct StoredFeatures {
    path: PathBuf,
    backbone: String,
    grid: (usize, usize),
    pixel_layers: Vec<usize>,
}

impl StoredFeatures {
    /// Token grid `(rows, cols)`.
    pub fn grid(&self) -> (usize, usize) {
        self.grid
    }

    /// The entry's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The features, read from the entry.
    pub fn read(&self) -> Result<FeatureMaps, HeadsError> {
        read_entry(&self.path, &self.backbone, &self.pixel_layers).filter(|f| f.grid == self.grid).ok_or_else(|| {
            HeadsError::file(
                &self.path,
                "this feature-cache entry vanished or changed while in use; rerun, which recomputes it",
            )
        })
    }
}

fn write_entry(path: &Path, backbone: &str, f: &FeatureMaps, p: Precision) -> Result<(), HeadsError> {
    let header = Header {
        format: FORMAT.into(),
        backbone: backbone.into(),
        grid: f.grid,
        dims: f.dims.clone(),
        f16: p == Precision::F16,
    };
    let mut bytes = serde_json::to_vec(&header).map_err(|e| HeadsError::file(path, e.to_string()))?;
    bytes.push(b'\n');
    bytes.resize(bytes.len().div_ceil(64) * 64, b' ');
    for l in &f.layers {
        match p {
            Precision::F32 => l.iter().for_each(|x| bytes.extend_from_slice(&x.to_le_bytes())),
            Precision::F16 => l.iter().for_each(|x| bytes.extend_from_slice(&half::f16::from_f32(*x).to_le_bytes())),
        }
    }
    Ok(dens3r_io::write_atomic(path, |w| std::io::Write::write_all(w, &bytes))?)
}

/// The header and data offset of a complete entry of backbone `id` in `map`.
fn parse_header(map: &[u8], id: &str) -> Option<(Header, usize)> {
    let nl = map.iter().position(|&b| b == b'\n')?;
    let header: Header = serde_json::from_slice(&map[..nl]).ok()?;
    if header.format != FORMAT || header.backbone != id {
        return None;
    }
    let start = (nl + 1).div_ceil(64) * 64;
    let n = header.grid.0.checked_mul(header.grid.1)?;
    let size = if header.f16 { 2 } else { 4 };
    let total = header.dims.iter().try_fold(0usize, |t, d| t.checked_add(d.checked_mul(n)?))?;
    (Some(map.len()) == total.checked_mul(size).and_then(|b| b.checked_add(start))).then_some((header, start))
}

/// Maps an entry file.
fn map_entry(path: &Path) -> Option<memmap2::Mmap> {
    let file = std::fs::File::open(path).ok()?;
    // SAFETY: cache entries are only ever replaced by rename, never written in place, so the
    // mapped file does not change under us.
    unsafe { memmap2::Mmap::map(&file) }.ok()
}

/// The header of a complete entry of backbone `id`; `None` when absent, damaged or of another
/// backbone. Reads no values.
fn check_entry(path: &Path, id: &str) -> Option<Header> {
    parse_header(&map_entry(path)?, id).map(|(h, _)| h)
}

/// Reads an entry; `None` when absent, damaged or of another backbone.
fn read_entry(path: &Path, id: &str, pixel_layers: &[usize]) -> Option<FeatureMaps> {
    let map = map_entry(path)?;
    let (header, start) = parse_header(&map, id)?;
    let n = header.grid.0 * header.grid.1;
    let size = if header.f16 { 2 } else { 4 };
    let mut at = start;
    let mut layers = Vec::with_capacity(header.dims.len());
    for d in &header.dims {
        let bytes = &map[at..at + d * n * size];
        at += d * n * size;
        let v: Vec<f32> = if header.f16 {
            bytes.chunks_exact(2).map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32()).collect()
        } else {
            bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
        };
        layers.push(v);
    }
    Some(FeatureMaps { grid: header.grid, dims: header.dims, layers, pixel_layers: pixel_layers.to_vec() })
}
