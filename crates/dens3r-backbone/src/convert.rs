//! A checkpoint (an official `.pth`, a `.safetensors` or a Hugging Face folder) converted into a
//! Hugging Face style folder that every command takes as `--weights` without `--config`:
//! `model.safetensors` (f32, the checkpoint's own key names) and `config.json` (the constructor
//! call an official `.pth` records, which gives the head counts). Natively: no PyTorch, and
//! nothing in a `.pth` is executed (`crate::pth`).

use crate::verify::model_folder_files;
use crate::weights::{Weights, WeightsError};
use std::path::Path;

/// What a conversion wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct Converted {
    /// Tensors written.
    pub tensors: usize,
    /// The constructor call carried into `config.json`, when the checkpoint has one.
    pub args: Option<String>,
    /// Whether a `config.json` was written (the constructor call, or the input folder's own).
    pub config: bool,
}

/// Converts `input` into the folder `out` (created; its `model.safetensors` and `config.json`
/// staged and moved in together, replacing only what an earlier conversion wrote). Integer tensors of a `.pth` (step counters and the like) are left
/// out, as a network reads none.
pub fn to_folder(input: &Path, out: &Path) -> Result<Converted, WeightsError> {
    let (file, folder_config) = if input.is_dir() { model_folder_files(input)? } else { (input.to_path_buf(), None) };
    let w = Weights::from_safetensors(&file)?;
    let model = out.join("model.safetensors");
    if std::fs::canonicalize(&file).ok() == std::fs::canonicalize(&model).ok() {
        return Err(WeightsError::new(out, "is the input's own folder: convert into another folder"));
    }
    // Staged and moved in at the end: a failure leaves the folder as it was, and a file there
    // that dens3r did not write is refused, not replaced.
    let dir = dens3r_io::output::OutputDir::begin(out)?;
    w.save_safetensors(&dir.root().join("model.safetensors"))?;
    let args = w.args_model().map(str::to_string);
    let config_path = dir.root().join("config.json");
    let config = match (&args, &folder_config) {
        (Some(a), _) => {
            dens3r_io::tensors::save_json(&config_path, &serde_json::json!({ "args": a }))?;
            true
        }
        (None, Some(c)) => {
            let text = std::fs::read(c).map_err(|e| WeightsError::new(c, format!("cannot read: {e}")))?;
            dens3r_io::write_atomic(&config_path, |f| std::io::Write::write_all(f, &text))?;
            true
        }
        (None, None) => false,
    };
    dir.finish()?;
    Ok(Converted { tensors: w.keys().count(), args, config })
}
