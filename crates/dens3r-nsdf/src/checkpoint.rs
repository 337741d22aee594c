//! Checkpoints: the tensors (parameters, and Adam moments while training) as safetensors, the
//! configuration, options, scene normalisation and iteration as JSON beside them. Both are
//! written to temporary files and renamed, the JSON last, so an interrupted save leaves the
//! previous checkpoint readable.

use crate::data::Bounds;
use crate::field::{param_names, FieldConfig};
use crate::train::TrainOptions;
use crate::NsdfError;
use safetensors::tensor::{Dtype, TensorView};
use serde::{Deserialize, Serialize};
use std::io::Write;
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

fn bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn write_atomic(path: &Path, data: &[u8]) -> Result<(), NsdfError> {
    dens3r_mesh::io::write_atomic(path, |w| w.write_all(data))
        .map_err(|e| NsdfError::Checkpoint(format!("{}: cannot write: {e}", path.display())))
}

/// Writes a checkpoint.
pub fn save(path: &Path, ck: &Checkpoint) -> Result<(), NsdfError> {
    let names = param_names(&ck.config);
    let mut owned: Vec<(String, Vec<u8>, Vec<usize>)> = Vec::new();
    for (i, (v, s)) in ck.values.iter().enumerate() {
        owned.push((names[i].clone(), bytes(v), s.to_vec()));
        if let Some(m) = &ck.moments {
            owned.push((format!("adam.m.{}", names[i]), bytes(&m[i].0), s.to_vec()));
            owned.push((format!("adam.v.{}", names[i]), bytes(&m[i].1), s.to_vec()));
        }
    }
    let views: Vec<(String, TensorView)> = owned
        .iter()
        .map(|(n, b, s)| Ok((n.clone(), TensorView::new(Dtype::F32, s.clone(), b)?)))
        .collect::<Result<_, safetensors::SafeTensorError>>()
        .map_err(|e| NsdfError::Checkpoint(format!("{}: {e}", path.display())))?;
    let data =
        safetensors::serialize(views, None).map_err(|e| NsdfError::Checkpoint(format!("{}: {e}", path.display())))?;
    write_atomic(path, &data)?;
    let meta = Meta {
        format: FORMAT.into(),
        config: ck.config.clone(),
        options: ck.options.clone(),
        bounds: ck.bounds,
        iter: ck.iter,
        data: ck.data.map(|h| format!("{h:016x}")),
        tensors_bytes: data.len() as u64,
    };
    let json = serde_json::to_vec_pretty(&meta).map_err(|e| NsdfError::Checkpoint(e.to_string()))?;
    write_atomic(&meta_path(path), &json)
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
    let data = std::fs::read(path).map_err(|e| err(format!("cannot read: {e}")))?;
    if data.len() as u64 != meta.tensors_bytes {
        return Err(err(format!(
            "{} bytes, but {} says {}: the pair is from different saves or truncated; delete both to start over",
            data.len(),
            mp.display(),
            meta.tensors_bytes
        )));
    }
    let st = safetensors::SafeTensors::deserialize(&data).map_err(|e| err(format!("corrupt safetensors: {e}")))?;
    let read = |name: &str| -> Result<(Vec<f32>, [usize; 2]), NsdfError> {
        let t = st.tensor(name).map_err(|_| err(format!("missing tensor '{name}'")))?;
        if t.dtype() != Dtype::F32 || t.shape().len() != 2 {
            return Err(err(format!("tensor '{name}' must be 2-D f32, is {:?} {:?}", t.dtype(), t.shape())));
        }
        let v: Vec<f32> = t.data().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(err(format!("tensor '{name}' holds NaN or infinite values")));
        }
        Ok((v, [t.shape()[0], t.shape()[1]]))
    };
    let expected = crate::field::param_shapes(&meta.config);
    let names = param_names(&meta.config);
    let mut values = Vec::new();
    let mut moments = Vec::new();
    let has_moments = st.names().iter().any(|n| n.starts_with("adam."));
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
