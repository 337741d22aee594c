//! The pair cache: network outputs on disk, one file per entry, keyed by the predictor's id,
//! the images' content hashes and the preprocessing, so re-running a reconstruction (other
//! alignment or fusion settings, one more photo) never runs the network twice. Three kinds
//! of entry: an ordered pair's two views ([`ViewOutput`]), a photo's own depth, confidence and
//! normals ([`MonoMaps`], what the structure-from-motion path reads), and a photo's retrieval
//! descriptor.
//!
//! Entries are compact: half-precision floats, normals in two numbers (octahedral), a pair's
//! pointmaps as they are, a photo's depth as one number a pixel; 1.6 MB a photo at 512 x 384.
//! Each is written to a temporary file and renamed (a crash leaves no half entry), holds its own
//! key in its header and ends in a checksum of its bytes: a damaged entry, one found under
//! another entry's name, or one holding NaN or infinite values is a miss, recomputed. With a budget
//! ([`PairCache::with_budget`]) the least recently used entries are removed to stay within it.

use crate::input::{fnv1a, InputImage};
use crate::predictor::ViewOutput;
use dens3r_backbone::predict::DescriptorMap;
use dens3r_geom::{Raster, Vec3};
use dens3r_io::IoError;
use half::f16;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Entries' file name suffix (format 2; format 1 was a folder of `.npy` arrays).
const EXT: &str = "d3c";
/// Format 3: the entry's key in its header (format 2 had none: two entries swapped were used).
const MAGIC: &[u8; 8] = b"dens3rC3";

/// Where network outputs are kept (None: memory only, nothing reused across runs).
#[derive(Debug)]
pub struct PairCache {
    dir: Option<PathBuf>,
    /// Most bytes the entries may take, and the bytes they take now (None: not counted yet).
    budget: Option<(u64, Mutex<Option<u64>>)>,
    /// How many entries could not be stored, and why the first could not.
    failed: Mutex<(usize, Option<String>)>,
}

/// A photo's own-frame depth (z), confidence and normals: one network pass of its self-pair.
#[derive(Debug, Clone)]
pub struct MonoMaps {
    /// Depth along the optical axis (0 where the network gives none).
    pub depth: Raster<f32>,
    /// Confidence.
    pub conf: Raster<f32>,
    /// Unit normals in the photo's OpenCV camera frame.
    pub normals: Option<Raster<Vec3>>,
}

impl PairCache {
    /// A cache in `dir` (created on first store), or none.
    pub fn new(dir: Option<PathBuf>) -> Self {
        Self { dir, budget: None, failed: Default::default() }
    }

    /// A cache in `dir` that removes its least recently used entries to stay within `bytes`.
    pub fn with_budget(dir: PathBuf, bytes: u64) -> Self {
        Self { dir: Some(dir), budget: Some((bytes, Mutex::new(None))), failed: Default::default() }
    }

    /// How many entries this cache could not store (a folder that is a file, read-only, full),
    /// and why the first could not.
    pub fn failed_stores(&self) -> (usize, Option<String>) {
        self.failed.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Refuses a folder entries cannot be stored in: created if missing, then a probe file
    /// written and removed.
    pub fn check_writable(&self) -> Result<(), IoError> {
        let Some(root) = &self.dir else { return Ok(()) };
        std::fs::create_dir_all(root).map_err(|e| IoError::new(root, format!("cannot create the pair cache ({e})")))?;
        let probe = root.join(format!(".dens3r-probe-{}", std::process::id()));
        dens3r_io::write_atomic(&probe, |w| std::io::Write::write_all(w, b"probe"))
            .map_err(|e| IoError::new(root, format!("cannot store entries in the pair cache: {}", e.message)))?;
        let _ = std::fs::remove_file(&probe);
        Ok(())
    }

    /// The folder, if any.
    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    /// The entry name of the ordered pair `(a, b)` under predictor `id` (`(a, a)` for a
    /// photo's own entries, with the id saying which kind).
    pub fn key(id: &str, a: &InputImage, b: &InputImage) -> String {
        let mut bytes = id.as_bytes().to_vec();
        for im in [a, b] {
            bytes.extend(im.hash.to_le_bytes());
            let i = &im.prep.info;
            for v in [i.resized.0, i.resized.1, i.crop.0, i.crop.1, i.crop.2, i.crop.3, i.rotated as u32] {
                bytes.extend(v.to_le_bytes());
            }
        }
        format!("{:016x}{:016x}", fnv1a(&bytes, 0), fnv1a(&bytes, 0x9e37_79b9_7f4a_7c15))
    }

    fn path(&self, key: &str) -> Option<PathBuf> {
        self.dir.as_ref().map(|d| d.join(format!("{key}.{EXT}")))
    }

    /// The arrays of entry `key`, checked, or None (absent, no cache, damaged). A hit marks
    /// the entry as used (for the budget's eviction).
    fn read(&self, key: &str) -> Option<Vec<Array>> {
        let path = self.path(key)?;
        let bytes = std::fs::read(&path).ok()?;
        let arrays = decode(&bytes, key)?;
        if arrays.iter().any(|a| a.data.iter().any(|v| !v.is_finite())) {
            return None;
        }
        if self.budget.is_some() {
            let _ = std::fs::File::options()
                .append(true)
                .open(&path)
                .and_then(|f| f.set_modified(std::time::SystemTime::now()));
        }
        Some(arrays)
    }

    /// Writes entry `key` (no-op without a folder), then evicts within the budget.
    fn write(&self, key: &str, arrays: &[Array]) -> Result<(), IoError> {
        self.write_bytes(key, &encode(key, arrays))
    }

    /// Encodes `arrays` as an entry, writes it under `key` and returns them as a later read
    /// will: in half precision. What a run uses is what a rerun reads from the cache, so a
    /// rerun gives the same result, with a cache or without.
    fn put(&self, key: &str, arrays: &[Array], warnings: &mut Vec<String>) -> Vec<Array> {
        let bytes = encode(key, arrays);
        if let Err(w) = self.write_bytes(key, &bytes) {
            let mut failed = self.failed.lock().unwrap_or_else(|e| e.into_inner());
            failed.0 += 1;
            failed.1.get_or_insert_with(|| w.to_string());
            warnings.push(format!("pair cache not written: {w}"));
        }
        decode(&bytes, key).expect("an entry just encoded decodes")
    }

    fn write_bytes(&self, key: &str, bytes: &[u8]) -> Result<(), IoError> {
        let (Some(root), Some(path)) = (&self.dir, self.path(key)) else { return Ok(()) };
        std::fs::create_dir_all(root).map_err(|e| IoError::new(root, format!("cannot create the pair cache ({e})")))?;
        dens3r_io::write_atomic(&path, |w| std::io::Write::write_all(w, bytes))?;
        if let Some((limit, used)) = &self.budget {
            let mut used = used.lock().unwrap_or_else(|e| e.into_inner());
            let total = match *used {
                Some(u) => u + bytes.len() as u64,
                None => entries(root).iter().map(|e| e.1).sum(),
            };
            *used = Some(if total > *limit { evict(root, *limit, &path) } else { total });
        }
        Ok(())
    }

    /// The cached pair output of `key`, or None (absent, no cache, or damaged: recomputed).
    pub fn load(&self, key: &str, sizes: [(usize, usize); 2]) -> Option<[ViewOutput; 2]> {
        let arrays = self.read(key)?;
        Some([view_from(&arrays, "v0", sizes[0])?, view_from(&arrays, "v1", sizes[1])?])
    }

    /// Stores a pair's output under `key` (no-op without a folder).
    pub fn store(&self, key: &str, out: &[ViewOutput; 2]) -> Result<(), IoError> {
        let mut arrays = view_arrays("v0", &out[0]);
        arrays.extend(view_arrays("v1", &out[1]));
        self.write(key, &arrays)
    }

    /// The cached pair output of `key`, else `compute`'s, checked by it and stored; the bool says
    /// whether it came from the cache. A store that fails is a warning pushed on `warnings`,
    /// not an error.
    pub fn load_or<E>(
        &self,
        key: &str,
        sizes: [(usize, usize); 2],
        warnings: &mut Vec<String>,
        compute: impl FnOnce() -> Result<[ViewOutput; 2], E>,
    ) -> Result<([ViewOutput; 2], bool), E> {
        if let Some(out) = self.load(key, sizes) {
            return Ok((out, true));
        }
        let out = compute()?;
        let mut arrays = view_arrays("v0", &out[0]);
        arrays.extend(view_arrays("v1", &out[1]));
        let back = self.put(key, &arrays, warnings);
        let view = |p: &str, k: usize| view_from(&back, p, sizes[k]).expect("checked by compute, just encoded");
        Ok(([view("v0", 0), view("v1", 1)], false))
    }

    /// A photo's cached own maps at `size`, else `compute`'s, stored (as [`PairCache::load_or`]).
    pub fn mono_or<E>(
        &self,
        key: &str,
        size: (usize, usize),
        warnings: &mut Vec<String>,
        compute: impl FnOnce() -> Result<MonoMaps, E>,
    ) -> Result<(MonoMaps, bool), E> {
        if let Some(m) = self.read(key).and_then(|a| mono_from(&a, size)) {
            return Ok((m, true));
        }
        let m = compute()?;
        let mut arrays = vec![Array::new("depth", 1, m.depth.width(), m.depth.height(), m.depth.data().to_vec())];
        arrays.push(Array::new("conf", 1, m.conf.width(), m.conf.height(), m.conf.data().to_vec()));
        if let Some(n) = &m.normals {
            arrays.push(normals_array("normals", n));
        }
        let back = self.put(key, &arrays, warnings);
        let size = (m.depth.width(), m.depth.height());
        Ok((mono_from(&back, size).expect("maps of one size, just encoded"), false))
    }

    /// A photo's cached retrieval descriptor, else `compute`'s, stored.
    pub fn descriptor_or<E>(
        &self,
        key: &str,
        warnings: &mut Vec<String>,
        compute: impl FnOnce() -> Result<Option<Vec<f32>>, E>,
    ) -> Result<Option<Vec<f32>>, E> {
        if let Some(a) = self.read(key).and_then(|a| a.into_iter().find(|a| a.name == "descriptor")) {
            return Ok(Some(a.data));
        }
        Ok(compute()?.map(|d| {
            let back = self.put(key, &[Array::new("descriptor", 1, d.len(), 1, d)], warnings);
            back.into_iter().next().expect("one array").data
        }))
    }
}

/// The entries of `root` (path, bytes, last use), oldest use first.
fn entries(root: &Path) -> Vec<(PathBuf, u64, std::time::SystemTime)> {
    let mut out: Vec<_> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| is_entry_name(&e.file_name().to_string_lossy()))
        .filter_map(|e| {
            let m = e.metadata().ok()?;
            Some((e.path(), m.len(), m.modified().ok()?))
        })
        .collect();
    out.sort_by_key(|e| e.2);
    out
}

/// Whether `name` is an entry's file name as [`PairCache::key`] makes them (32 hex digits and
/// the suffix): eviction never removes another file a user keeps in the cache folder.
fn is_entry_name(name: &str) -> bool {
    name.strip_suffix(&format!(".{EXT}")).is_some_and(|k| k.len() == 32 && k.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// Removes the least recently used entries of `root` (never `keep`) until they take at most
/// `limit` bytes; returns the bytes left.
fn evict(root: &Path, limit: u64, keep: &Path) -> u64 {
    let all = entries(root);
    let mut total: u64 = all.iter().map(|e| e.1).sum();
    for (path, len, _) in all {
        if total <= limit {
            break;
        }
        if path != keep && std::fs::remove_file(&path).is_ok() {
            total -= len;
        }
    }
    total
}

/// A named array of `channels` values a pixel over a `w x h` grid.
struct Array {
    name: String,
    channels: usize,
    w: usize,
    h: usize,
    data: Vec<f32>,
}

impl Array {
    fn new(name: &str, channels: usize, w: usize, h: usize, data: Vec<f32>) -> Self {
        debug_assert_eq!(data.len(), channels * w * h);
        Self { name: name.into(), channels, w, h, data }
    }
}

/// Entry bytes: magic, header length (u32 LE), a JSON header holding the entry's key and
/// listing the arrays (name, channels, width, height), every array's values as f16 LE in that
/// order, and FNV-1a of all bytes before it (u64 LE).
fn encode(key: &str, arrays: &[Array]) -> Vec<u8> {
    let list: Vec<serde_json::Value> = arrays
        .iter()
        .map(|a| serde_json::json!({"name": a.name, "channels": a.channels, "w": a.w, "h": a.h}))
        .collect();
    let header = serde_json::to_vec(&serde_json::json!({"key": key, "arrays": list})).expect("plain JSON");
    let values: usize = arrays.iter().map(|a| a.data.len()).sum();
    let mut out = Vec::with_capacity(12 + header.len() + 2 * values + 8);
    out.extend(MAGIC);
    out.extend((header.len() as u32).to_le_bytes());
    out.extend(&header);
    for a in arrays {
        // Beyond half precision's range is clamped (no scene is 65504 units deep); NaN stays.
        out.extend(a.data.iter().flat_map(|&v| f16::from_f32(v.clamp(-65504.0, 65504.0)).to_le_bytes()));
    }
    let sum = fnv1a(&out, 0);
    out.extend(sum.to_le_bytes());
    out
}

/// The arrays of an entry whose checksum holds and whose header names `key`.
fn decode(bytes: &[u8], key: &str) -> Option<Vec<Array>> {
    let body = bytes.len().checked_sub(8)?;
    if bytes.get(..8)? != MAGIC || fnv1a(&bytes[..body], 0).to_le_bytes() != bytes[body..] {
        return None;
    }
    let hlen = u32::from_le_bytes(bytes.get(8..12)?.try_into().ok()?) as usize;
    let header: serde_json::Value = serde_json::from_slice(bytes.get(12..12usize.checked_add(hlen)?)?).ok()?;
    if header["key"].as_str() != Some(key) {
        return None;
    }
    let mut at = 12 + hlen;
    let mut out = Vec::new();
    for a in header["arrays"].as_array()? {
        let u = |k: &str| a[k].as_u64().map(|v| v as usize);
        let (channels, w, h) = (u("channels")?, u("w")?, u("h")?);
        let n = channels.checked_mul(w)?.checked_mul(h)?;
        let end = at.checked_add(n.checked_mul(2)?)?;
        let raw = bytes.get(at..end).filter(|_| end <= body)?;
        let data = raw.chunks_exact(2).map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32()).collect();
        out.push(Array { name: a["name"].as_str()?.to_string(), channels, w, h, data });
        at = end;
    }
    (at == body).then_some(out)
}

fn find<'a>(arrays: &'a [Array], name: &str, (w, h): (usize, usize), channels: Option<usize>) -> Option<&'a Array> {
    arrays.iter().find(|a| a.name == name).filter(|a| a.w == w && a.h == h && channels.is_none_or(|c| a.channels == c))
}

fn raster(a: &Array) -> Raster<f32> {
    Raster::from_vec(a.w, a.h, a.data.clone()).expect("checked size")
}

/// An invalid normal's two numbers: outside the octahedral square, finite (so an entry's
/// non-finite values can all mean damage).
const NO_NORMAL: [f32; 2] = [2.0, 2.0];

/// Unit normals as two numbers each: the octahedral map (the sphere folded onto a square).
fn normals_array(name: &str, n: &Raster<Vec3>) -> Array {
    let data = n
        .data()
        .iter()
        .flat_map(|v| {
            let l1 = v.x.abs() + v.y.abs() + v.z.abs();
            if !(l1 > 0.0 && l1.is_finite()) {
                return NO_NORMAL;
            }
            let (x, y) = (v.x / l1, v.y / l1);
            if v.z >= 0.0 {
                [x, y]
            } else {
                [(1.0 - y.abs()) * x.signum(), (1.0 - x.abs()) * y.signum()]
            }
        })
        .collect();
    Array::new(name, 2, n.width(), n.height(), data)
}

fn normals_from(a: &Array) -> Raster<Vec3> {
    let v = a
        .data
        .chunks_exact(2)
        .map(|c| {
            let (x, y) = (c[0], c[1]);
            if x.abs() > 1.5 || y.abs() > 1.5 {
                return Vec3::ZERO;
            }
            let z = 1.0 - x.abs() - y.abs();
            let (x, y) = if z >= 0.0 { (x, y) } else { ((1.0 - y.abs()) * x.signum(), (1.0 - x.abs()) * y.signum()) };
            Vec3::new(x, y, z).normalize_or_zero()
        })
        .collect();
    Raster::from_vec(a.w, a.h, v).expect("checked size")
}

fn view_arrays(p: &str, o: &ViewOutput) -> Vec<Array> {
    let (w, h) = (o.points.width(), o.points.height());
    let flat = |r: &Raster<Vec3>| r.data().iter().flat_map(|p| p.to_array()).collect();
    let mut out = vec![
        Array::new(&format!("{p}_points"), 3, w, h, flat(&o.points)),
        Array::new(&format!("{p}_conf"), 1, w, h, o.conf.data().to_vec()),
    ];
    if let Some(n) = &o.normals {
        out.push(normals_array(&format!("{p}_normals"), n));
    }
    if let Some(d) = &o.desc {
        out.push(Array::new(&format!("{p}_desc"), d.dim, w, h, d.data.clone()));
    }
    if let Some(c) = &o.desc_conf {
        out.push(Array::new(&format!("{p}_desc_conf"), 1, w, h, c.data().to_vec()));
    }
    out
}

fn view_from(arrays: &[Array], p: &str, size: (usize, usize)) -> Option<ViewOutput> {
    let (w, h) = size;
    let get = |n: &str, c: Option<usize>| find(arrays, &format!("{p}_{n}"), size, c);
    let pts = get("points", Some(3))?;
    let points =
        Raster::from_vec(w, h, pts.data.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect()).ok()?;
    let out = ViewOutput {
        points,
        conf: raster(get("conf", Some(1))?),
        normals: get("normals", Some(2)).map(normals_from),
        desc: get("desc", None).map(|a| DescriptorMap { width: w, height: h, dim: a.channels, data: a.data.clone() }),
        desc_conf: get("desc_conf", Some(1)).map(raster),
    };
    out.check(size).ok()?;
    Some(out)
}

fn mono_from(arrays: &[Array], size: (usize, usize)) -> Option<MonoMaps> {
    Some(MonoMaps {
        depth: raster(find(arrays, "depth", size, Some(1))?),
        conf: raster(find(arrays, "conf", size, Some(1))?),
        normals: find(arrays, "normals", size, Some(2)).map(normals_from),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::Raster;

    fn view(w: usize, h: usize) -> ViewOutput {
        let pts = (0..w * h).map(|i| Vec3::new(i as f32, 1.0, 2.0)).collect();
        let normals = (0..w * h)
            .map(|i| Vec3::new((i as f32 * 0.7).sin(), (i as f32 * 1.3).cos(), -(i as f32 * 0.3).cos()).normalize())
            .collect();
        ViewOutput {
            points: Raster::from_vec(w, h, pts).unwrap(),
            conf: Raster::from_vec(w, h, vec![2.0; w * h]).unwrap(),
            normals: Some(Raster::from_vec(w, h, normals).unwrap()),
            desc: None,
            desc_conf: None,
        }
    }

    #[test]
    fn entries_round_trip_in_half_precision_and_a_damaged_one_is_a_miss() {
        let dir = tempfile::tempdir().unwrap();
        let cache = PairCache::new(Some(dir.path().to_path_buf()));
        let v = view(4, 3);
        cache.store("k", &[v.clone(), view(4, 3)]).unwrap();
        let back = cache.load("k", [(4, 3), (4, 3)]).expect("a stored entry is read back");
        for (a, b) in back[1].points.data().iter().zip(v.points.data()) {
            assert!((*a - *b).length() <= 1e-3 * b.length(), "{a} {b}");
        }
        // Normals through the octahedral map: within 0.1 degree, facing either way.
        for (a, b) in back[0].normals.as_ref().unwrap().data().iter().zip(v.normals.as_ref().unwrap().data()) {
            assert!(a.dot(*b) > 0.1f32.to_radians().cos(), "{a} {b}");
        }
        assert!(cache.load("k", [(5, 3), (4, 3)]).is_none(), "another size is a miss");
        let path = dir.path().join("k.d3c");
        let mut bytes = std::fs::read(&path).unwrap();
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x40;
        std::fs::write(&path, &bytes).unwrap();
        assert!(cache.load("k", [(4, 3), (4, 3)]).is_none(), "a damaged entry is recomputed, not used");
    }

    /// Issue 77, 5: two entries swapped on disk (same size) were used, each for the other's
    /// photos; an entry holding NaN gave all-NaN depth with exit 0.
    #[test]
    fn entries_are_bound_to_their_key_and_a_nan_entry_is_a_miss() {
        let dir = tempfile::tempdir().unwrap();
        let cache = PairCache::new(Some(dir.path().to_path_buf()));
        let mut other = view(4, 3);
        other.conf = Raster::from_vec(4, 3, vec![5.0; 12]).unwrap();
        cache.store("a", &[view(4, 3), view(4, 3)]).unwrap();
        cache.store("b", &[other.clone(), other]).unwrap();
        assert!(cache.load("a", [(4, 3); 2]).is_some() && cache.load("b", [(4, 3); 2]).is_some());
        let (a, b, t) = (dir.path().join("a.d3c"), dir.path().join("b.d3c"), dir.path().join("t"));
        assert_eq!(std::fs::metadata(&a).unwrap().len(), std::fs::metadata(&b).unwrap().len());
        std::fs::rename(&a, &t).unwrap();
        std::fs::rename(&b, &a).unwrap();
        std::fs::rename(&t, &b).unwrap();
        assert!(cache.load("a", [(4, 3); 2]).is_none(), "b's entry under a's name is a miss");
        assert!(cache.load("b", [(4, 3); 2]).is_none(), "a's entry under b's name is a miss");

        // A NaN entry is recomputed; an invalid normal (zero) is not damage.
        let mut w = Vec::new();
        let maps = |z: f32| MonoMaps {
            depth: Raster::from_vec(2, 2, vec![z; 4]).unwrap(),
            conf: Raster::from_vec(2, 2, vec![1.0; 4]).unwrap(),
            normals: Some(Raster::from_vec(2, 2, vec![Vec3::ZERO, Vec3::Z, Vec3::Z, Vec3::Z]).unwrap()),
        };
        let (m, hit) = cache.mono_or("m", (2, 2), &mut w, || Ok::<_, ()>(maps(f32::NAN))).unwrap();
        assert!(!hit && m.depth.data()[0].is_nan());
        let (m, hit) = cache.mono_or("m", (2, 2), &mut w, || Ok::<_, ()>(maps(2.0))).unwrap();
        assert!(!hit, "the NaN entry was used");
        assert_eq!(m.depth.data()[0], 2.0);
        let (m, hit) = cache.mono_or("m", (2, 2), &mut w, || Ok::<_, ()>(maps(3.0))).unwrap();
        assert!(hit && m.depth.data()[0] == 2.0);
        let n = m.normals.unwrap();
        assert_eq!(n.data()[0], Vec3::ZERO);
        assert!((n.data()[1] - Vec3::Z).length() < 1e-3);
        assert!(w.is_empty(), "{w:?}");
    }

    /// Entries' names are keys: 32 hex digits.
    fn k(c: char) -> String {
        c.to_string().repeat(32)
    }

    #[test]
    fn a_budget_keeps_the_most_recently_used_entries() {
        let dir = tempfile::tempdir().unwrap();
        // A user's file in the cache folder, older than every entry: never evicted.
        std::fs::write(dir.path().join("notes.d3c"), vec![b'n'; 4096]).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        let one = encode(&k('a'), &view_arrays("v0", &view(8, 8))).len() as u64 * 2;
        let cache = PairCache::with_budget(dir.path().to_path_buf(), 3 * one);
        for c in ['a', 'b', 'c'] {
            cache.store(&k(c), &[view(8, 8), view(8, 8)]).unwrap();
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        // "a" is read (used again), then a fourth entry exceeds the budget: "b" goes.
        assert!(cache.load(&k('a'), [(8, 8); 2]).is_some());
        std::thread::sleep(std::time::Duration::from_millis(20));
        cache.store(&k('d'), &[view(8, 8), view(8, 8)]).unwrap();
        let left: Vec<bool> =
            ['a', 'b', 'c', 'd'].iter().map(|&c| dir.path().join(format!("{}.d3c", k(c))).exists()).collect();
        assert_eq!(left, vec![true, false, true, true]);
        let bytes: u64 = entries(dir.path()).iter().map(|e| e.1).sum();
        assert!(bytes <= 3 * one, "{bytes} > {}", 3 * one);
        assert!(dir.path().join("notes.d3c").is_file(), "a user's file was evicted");
    }
}
