//! The pair cache: each ordered pair's network output on disk (`.npy` arrays, one folder per
//! pair), keyed by the predictor's id, both images' content hashes and the preprocessing, so
//! re-running a reconstruction (other alignment or fusion settings, one more photo) never runs
//! a pair twice. Entries are written to a temporary folder and renamed: a crash leaves no
//! half entry. An unreadable entry is recomputed.

use crate::input::{fnv1a, InputImage};
use crate::predictor::ViewOutput;
use dens3r_backbone::predict::DescriptorMap;
use dens3r_geom::{Raster, Vec3};
use dens3r_io::IoError;
use dens3r_scene::npy;
use std::path::{Path, PathBuf};

/// Where pair outputs are kept (None: memory only, nothing reused across runs).
#[derive(Debug, Clone)]
pub struct PairCache {
    dir: Option<PathBuf>,
}

impl PairCache {
    /// A cache in `dir` (created on first store), or none.
    pub fn new(dir: Option<PathBuf>) -> Self {
        Self { dir }
    }

    /// The folder, if any.
    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    /// The entry name of the ordered pair `(a, b)` under predictor `id`.
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

    /// The cached output of `key`, or None (absent, no cache, or unreadable: recomputed).
    pub fn load(&self, key: &str, sizes: [(usize, usize); 2]) -> Option<[ViewOutput; 2]> {
        let dir = self.dir.as_ref()?.join(key);
        if !dir.is_dir() {
            return None;
        }
        let read = |v: usize| read_view(&dir, v, sizes[v]).ok();
        Some([read(0)?, read(1)?])
    }

    /// The cached output of `key`, else `compute`'s, checked by it and stored; the bool says
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
        if let Err(w) = self.store(key, &out) {
            warnings.push(format!("pair cache not written: {w}"));
        }
        Ok((out, false))
    }

    /// Stores `out` under `key` (no-op without a folder).
    pub fn store(&self, key: &str, out: &[ViewOutput; 2]) -> Result<(), IoError> {
        let Some(root) = &self.dir else { return Ok(()) };
        std::fs::create_dir_all(root).map_err(|e| IoError::new(root, format!("cannot create the pair cache ({e})")))?;
        // Entries of killed runs are swept; this one is removed if the process is stopped.
        dens3r_io::cleanup::sweep_stale(root);
        let tmp = root.join(format!(".{key}{}d", dens3r_io::cleanup::temp_prefix()));
        let _ = std::fs::remove_dir_all(&tmp);
        let _staged = dens3r_io::cleanup::stage(&tmp);
        std::fs::create_dir_all(&tmp).map_err(|e| IoError::new(&tmp, format!("cannot write the pair cache ({e})")))?;
        let res = out.iter().enumerate().try_for_each(|(v, o)| write_view(&tmp, v, o));
        if let Err(e) = res {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
        let dst = root.join(key);
        let _ = std::fs::remove_dir_all(&dst);
        std::fs::rename(&tmp, &dst).map_err(|e| IoError::new(&dst, format!("cannot finish the cache entry ({e})")))
    }
}

fn vec3s(r: &Raster<Vec3>) -> Vec<f32> {
    r.data().iter().flat_map(|p| p.to_array()).collect()
}

fn write_view(dir: &Path, v: usize, o: &ViewOutput) -> Result<(), IoError> {
    let (w, h) = (o.points.width(), o.points.height());
    let p = |n: &str| dir.join(format!("v{v}_{n}.npy"));
    let e = |e: dens3r_scene::SceneError| IoError::new(&e.path, e.message);
    npy::write_f32(&p("points"), &[h, w, 3], &vec3s(&o.points)).map_err(e)?;
    npy::write_f32(&p("conf"), &[h, w], o.conf.data()).map_err(e)?;
    if let Some(n) = &o.normals {
        npy::write_f32(&p("normals"), &[h, w, 3], &vec3s(n)).map_err(e)?;
    }
    if let Some(d) = &o.desc {
        npy::write_f32(&p("desc"), &[h, w, d.dim], &d.data).map_err(e)?;
    }
    if let Some(c) = &o.desc_conf {
        npy::write_f32(&p("desc_conf"), &[h, w], c.data()).map_err(e)?;
    }
    Ok(())
}

fn read_view(dir: &Path, v: usize, (w, h): (usize, usize)) -> Result<ViewOutput, String> {
    let p = |n: &str| dir.join(format!("v{v}_{n}.npy"));
    let read = |n: &str, c: Option<usize>| -> Result<Option<Vec<f32>>, String> {
        let path = p(n);
        if !path.exists() {
            return Ok(None);
        }
        let (shape, data) = npy::read_f32(&path).map_err(|e| e.to_string())?;
        // A damaged entry (NaN or infinite values) is a miss, recomputed; it would otherwise
        // make every rerun's alignment fail without naming the cache.
        if data.iter().any(|v| !v.is_finite()) {
            return Err(format!("{}: holds NaN or infinite values", path.display()));
        }
        let ok = shape.len() >= 2 && shape[0] == h && shape[1] == w && c.is_none_or(|c| shape.get(2) == Some(&c));
        if !ok {
            return Err(format!("{}: shape {shape:?}", path.display()));
        }
        Ok(Some(data))
    };
    let to_vec3 = |d: Vec<f32>| {
        Raster::from_vec(w, h, d.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect())
            .map_err(|e| e.to_string())
    };
    let scalar = |d: Vec<f32>| Raster::from_vec(w, h, d).map_err(|e| e.to_string());
    let points = to_vec3(read("points", Some(3))?.ok_or("no points")?)?;
    let conf = scalar(read("conf", None)?.ok_or("no conf")?)?;
    let normals = read("normals", Some(3))?.map(to_vec3).transpose()?;
    let desc = match read("desc", None)? {
        Some(data) => {
            let dim = data.len() / (w * h).max(1);
            Some(DescriptorMap { width: w, height: h, dim, data })
        }
        None => None,
    };
    let desc_conf = read("desc_conf", None)?.map(scalar).transpose()?;
    let out = ViewOutput { points, conf, normals, desc, desc_conf };
    out.check((w, h)).map_err(|e| e.0)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::Raster;

    fn view(w: usize, h: usize) -> ViewOutput {
        let pts = (0..w * h).map(|i| Vec3::new(i as f32, 1.0, 2.0)).collect();
        ViewOutput {
            points: Raster::from_vec(w, h, pts).unwrap(),
            conf: Raster::from_vec(w, h, vec![2.0; w * h]).unwrap(),
            normals: None,
            desc: None,
            desc_conf: None,
        }
    }

    #[test]
    fn entries_round_trip_and_a_nan_entry_is_a_miss() {
        let dir = tempfile::tempdir().unwrap();
        let cache = PairCache::new(Some(dir.path().to_path_buf()));
        cache.store("k", &[view(4, 3), view(4, 3)]).unwrap();
        let back = cache.load("k", [(4, 3), (4, 3)]).expect("a stored entry is read back");
        assert_eq!(back[1].points.data(), view(4, 3).points.data());
        let path = dir.path().join("k/v1_conf.npy");
        let mut conf = vec![2.0f32; 12];
        conf[5] = f32::NAN;
        npy::write_f32(&path, &[3, 4], &conf).unwrap();
        assert!(cache.load("k", [(4, 3), (4, 3)]).is_none(), "a NaN entry is recomputed, not used");
    }
}
