//! A head's tensors read back checked, through dens3r-io's checkpoint files.

use crate::HeadsError;
use std::path::Path;

/// Reads the tensors named in `shapes` (each must be there, f32, with that shape and finite).
pub fn load_tensors(path: &Path, shapes: &[(String, Vec<usize>)]) -> Result<Vec<Vec<f32>>, HeadsError> {
    let file = dens3r_io::tensors::TensorFile::open(path, "delete it and retrain")?;
    Ok(shapes.iter().map(|(name, shape)| file.get_shaped(name, shape)).collect::<Result<_, _>>()?)
}
