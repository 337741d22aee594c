//! Checkpoints: the tensors (parameters, and Adam moments while training) as safetensors, the
//! configuration, options, scene normalisation and iteration as JSON beside them. Both are
//! written to temporary files and renamed, the JSON last, so an interrupted save leaves the
//! previous checkpoint readable.

use crate::data::Bounds;
use crate::field::{param_names, FieldConfig};
use crate::options::TrainOptions;
use crate::NsdfError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Everything a checkpoint holds.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    /// Field architecture.
    pub config: FieldConfig,
    /// Training options.
    pub options: TrainOptions,
    /// World <-> normalised frame.
    pub bounds: Bounds,
    /// Iterations done.
    pub iter: usize,
    /// [`crate::data::TrainData::fingerprint`] of the data it was trained on (absent in
    /// checkpoints written before it was recorded).
    pub data: Option<u64>,
    /// Parameter values and shapes, in [`param_names`] order.
    pub values: Vec<(Vec<f32>, [usize; 2])>,
    /// Adam first and second moments per parameter (absent in exported fields).
    pub moments: Option<Vec<(Vec<f32>, Vec<f32>)>>,
}

#[derive(Serialize, Deserialize)]
struct Meta {
    format: String,
    config: FieldConfig,
    options: TrainOptions,
    bounds: Bounds,
    iter: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    data: Option<String>,
    tensors_bytes: u64,
}

/// Most iterations a checkpoint may say it has done (a damaged count is refused).
pub const MAX_ITERS: usize = 100_000_000;

const FORMAT: &str = "dens3r-nsdf/1";

/// The JSON file beside a checkpoint's `.safetensors`.
pub fn meta_path(path: &Path) -> PathBuf {
    path.with_extension("json")
}

/// Writes a checkpoint.
pub fn save(path: &Path, ck: &Checkpoint) -> Result<(), NsdfError> {
    let names = param_names(&ck.config);
    let mut named: Vec<(String, Vec<usize>, &[f32])> = Vec::new();
    for (i, (v, s)) in ck.values.iter().enumerate() {
        named.push((names[i].clone(), s.to_vec(), v));
        if let Some(m) = &ck.moments {
            named.push((format!("adam.m.{}", names[i]), s.to_vec(), &m[i].0));
            named.push((format!("adam.v.{}", names[i]), s.to_vec(), &m[i].1));
        }
    }
    let tensors_bytes = dens3r_io::tensors::save(path, &named).map_err(|e| NsdfError::Checkpoint(e.to_string()))?;
    let meta = Meta {
        format: FORMAT.into(),
        config: ck.config.clone(),
        options: ck.options.clone(),
        bounds: ck.bounds,
        iter: ck.iter,
        data: ck.data.map(|h| format!("{h:016x}")),
        tensors_bytes,
    };
    dens3r_io::tensors::save_json(&meta_path(path), &meta).map_err(|e| NsdfError::Checkpoint(e.to_string()))
}

/// Reads a checkpoint, checking names, shapes and that both files belong together.
pub fn load(path: &Path) -> Result<Checkpoint, NsdfError> {
    let err = |m: String| NsdfError::Checkpoint(format!("{}: {m}", path.display()));
    let mp = meta_path(path);
    let json = std::fs::read(&mp).map_err(|e| err(format!("cannot read {}: {e}", mp.display())))?;
    let meta: Meta = serde_json::from_slice(&json)
        .map_err(|e| err(format!("{} is not a dens3r-nsdf checkpoint: {e}", mp.display())))?;
    if meta.format != FORMAT {
        return Err(err(format!("format '{}', expected '{FORMAT}'", meta.format)));
    }
    meta.config.check().map_err(|e| err(format!("bad field config: {e}")))?;
    if meta.iter > MAX_ITERS {
        return Err(err(format!(
            "{} says {} iterations, more than {MAX_ITERS}: damaged; delete both to start over",
            mp.display(),
            meta.iter
        )));
    }
    let data_hash = match &meta.data {
        Some(h) => Some(u64::from_str_radix(h, 16).map_err(|_| {
            err(format!("{}: data fingerprint '{h}' is not hexadecimal: damaged; delete both", mp.display()))
        })?),
        None => None,
    };
    let len = std::fs::metadata(path).map_err(|e| err(format!("cannot read: {e}")))?.len();
    if len != meta.tensors_bytes {
        return Err(err(format!(
            "{len} bytes, but {} says {}: the pair is from different saves or truncated; delete both to start over",
            mp.display(),
            meta.tensors_bytes
        )));
    }
    let file = dens3r_io::tensors::TensorFile::open(path, "delete both to start over")
        .map_err(|e| NsdfError::Checkpoint(e.to_string()))?;
    let read = |name: &str| -> Result<(Vec<f32>, [usize; 2]), NsdfError> {
        let (shape, v) = file.get(name).map_err(|e| NsdfError::Checkpoint(e.to_string()))?;
        match shape[..] {
            [a, b] => Ok((v, [a, b])),
            _ => Err(err(format!("tensor '{name}' must be 2-D, is {shape:?}"))),
        }
    };
    let expected = crate::field::param_shapes(&meta.config);
    let names = param_names(&meta.config);
    let mut values = Vec::new();
    let mut moments = Vec::new();
    let has_moments = file.names().iter().any(|n| n.starts_with("adam."));
    for (name, shape) in names.iter().zip(&expected) {
        let v = read(name)?;
        if v.1 != *shape {
            return Err(err(format!("tensor '{name}' is {:?}, the config needs {shape:?}", v.1)));
        }
        values.push(v);
        if has_moments {
            moments.push((read(&format!("adam.m.{name}"))?.0, read(&format!("adam.v.{name}"))?.0));
        }
    }
    Ok(Checkpoint {
        config: meta.config,
        options: meta.options,
        bounds: meta.bounds,
        iter: meta.iter,
        data: data_hash,
        values,
        moments: has_moments.then_some(moments),
    })
}
