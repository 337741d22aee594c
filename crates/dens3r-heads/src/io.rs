//! A head's tensors and JSON through dens3r-io's checkpoint files (atomic writes, checked reads).

use crate::HeadsError;
use std::path::Path;

/// Writes named f32 tensors as safetensors.
pub fn save_tensors(path: &Path, tensors: &[(String, Vec<usize>, &[f32])]) -> Result<(), HeadsError> {
    dens3r_io::tensors::save(path, tensors)?;
    Ok(())
}

/// Reads the tensors named in `shapes` (each must be there, f32, with that shape and finite).
pub fn load_tensors(path: &Path, shapes: &[(String, Vec<usize>)]) -> Result<Vec<Vec<f32>>, HeadsError> {
    let file = dens3r_io::tensors::TensorFile::open(path, "delete it and retrain")?;
    Ok(shapes.iter().map(|(name, shape)| file.get_shaped(name, shape)).collect::<Result<_, _>>()?)
}

/// Writes pretty JSON atomically.
pub fn save_json(path: &Path, value: &serde_json::Value) -> Result<(), HeadsError> {
    Ok(dens3r_io::tensors::save_json(path, value)?)
}
