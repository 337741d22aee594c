//! Atomic safetensors / JSON files for heads and checkpoints, with checked reads.

use crate::HeadsError;
use safetensors::tensor::Dtype;
use safetensors::SafeTensors;
use std::io::Write;
use std::path::Path;

/// Writes bytes to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, data: &[u8]) -> Result<(), HeadsError> {
    dens3r_mesh::io::write_atomic(path, |w| w.write_all(data))
        .map_err(|e| HeadsError::file(path, format!("cannot write: {e}")))
}

/// Writes named f32 tensors as safetensors.
pub fn save_tensors(path: &Path, tensors: &[(String, Vec<usize>, &[f32])]) -> Result<(), HeadsError> {
    let data = dens3r_backbone::weights::f32_safetensors(tensors).map_err(|e| HeadsError::file(path, e.to_string()))?;
    write_atomic(path, &data)
}

/// Reads the tensors named in `shapes` (each must be there, f32, with that shape and finite).
pub fn load_tensors(path: &Path, shapes: &[(String, Vec<usize>)]) -> Result<Vec<Vec<f32>>, HeadsError> {
    let bytes = std::fs::read(path).map_err(|e| HeadsError::file(path, format!("cannot read ({e})")))?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| HeadsError::file(path, format!("not a valid safetensors file ({e}); delete it and retrain")))?;
    shapes
        .iter()
        .map(|(name, shape)| {
            let t = st.tensor(name).map_err(|_| {
                HeadsError::file(path, format!("tensor {name} is missing; the file does not belong to its .json"))
            })?;
            if t.dtype() != Dtype::F32 || t.shape() != shape.as_slice() {
                return Err(HeadsError::file(
                    path,
                    format!("tensor {name} is {:?} {:?}, expected F32 {shape:?}", t.dtype(), t.shape()),
                ));
            }
            let v: Vec<f32> = t.data().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            if v.iter().any(|x| !x.is_finite()) {
                return Err(HeadsError::file(path, format!("tensor {name} holds NaN or infinity")));
            }
            Ok(v)
        })
        .collect()
}

/// Writes pretty JSON atomically.
pub fn save_json(path: &Path, value: &serde_json::Value) -> Result<(), HeadsError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| HeadsError::file(path, e.to_string()))?;
    write_atomic(path, text.as_bytes())
}
