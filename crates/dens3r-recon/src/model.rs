//! The network a caller runs: a checkpoint file, a Hugging Face style folder, a known name
//! (fetched into the cache when missing) or, when none is given, the bundled default model.
//! `dens3r predict` / `reconstruct` and the Python package resolve `weights` through here.

use crate::ReconError;
use dens3r_backbone::{default_model, Dens3r};
use dens3r_hub::{Known, Progress, Source};
use std::path::{Path, PathBuf};

/// A resolved checkpoint.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFiles {
    /// The weights file (`.safetensors` or `.pth`).
    pub weights: PathBuf,
    /// Its config (head counts), when one was given or sits in its folder.
    pub config: Option<PathBuf>,
    /// The one line to show when this is the bundled default model (how to use the official
    /// checkpoints instead); `None` otherwise.
    pub default_notice: Option<String>,
}

/// A known name's folder: the bundled model, the cached download, or fetched now (`progress`
/// gets each file's name and bytes; `announce` a line before a download starts).
pub fn fetch_known(
    k: &Known,
    announce: &mut dyn FnMut(&str),
    progress: &mut dyn FnMut(&str, Progress),
) -> Result<PathBuf, ReconError> {
    if let Source::Bundled = k.source {
        return Ok(default_model::locate()?);
    }
    if dens3r_hub::is_cached(k) {
        return Ok(dens3r_hub::model_dir(k));
    }
    announce(&format!(
        "downloading {} ({} MB, licence {}) into {}",
        k.official,
        k.size_mb,
        k.licence,
        dens3r_hub::model_dir(k).display()
    ));
    dens3r_hub::fetch_model(k, progress).map_err(|e| ReconError::Other(e.to_string()))
}

/// The checkpoint and config that `weights` / `config` name: a file, a Hugging Face style
/// folder (its `model.safetensors` and `config.json`), a known name that is not a path
/// (`fetch` returns its folder), or, without `weights`, the bundled default model.
pub fn resolve(
    weights: Option<&Path>,
    config: Option<&Path>,
    fetch: &mut dyn FnMut(&Known) -> Result<PathBuf, ReconError>,
) -> Result<ModelFiles, ReconError> {
    let named = match weights.filter(|w| !w.exists()).and_then(|w| w.to_str()).and_then(dens3r_hub::find) {
        Some(k) => Some(fetch(k)?),
        None => None,
    };
    let given = config.map(Path::to_path_buf);
    let folder = |dir: &Path, notice: Option<String>| -> Result<ModelFiles, ReconError> {
        let (file, cfg) =
            dens3r_backbone::verify::model_folder_files(dir).map_err(|e| ReconError::Other(e.to_string()))?;
        Ok(ModelFiles { weights: file, config: given.clone().or(cfg), default_notice: notice })
    };
    match named.as_deref().or(weights) {
        Some(w) if !w.exists() => Err(ReconError::input(
            w,
            format!(
                "weights not found (a .safetensors / .pth checkpoint, a Hugging Face folder or a name `dens3r models` \
                 lists; leave the weights out for the bundled {})",
                default_model::NAME
            ),
        )),
        Some(w) if w.is_dir() => folder(w, None),
        Some(w) => Ok(ModelFiles { weights: w.to_path_buf(), config: given, default_notice: None }),
        None => {
            let dir = default_model::locate()?;
            let notice = Some(default_model::notice(&dir));
            if dir.is_file() {
                return Ok(ModelFiles { weights: dir, config: given, default_notice: notice });
            }
            folder(&dir, notice)
        }
    }
}

/// Loads the network of `weights` (and its `config`) on the CPU, or with `gpu` on the GPU,
/// computing in `precision` ([`dens3r_backbone::device::network_device_at`]); also returns the
/// checkpoint keys the model does not use.
pub fn load_network(
    weights: &Path,
    config: Option<&Path>,
    gpu: bool,
    precision: dens3r_backbone::Precision,
) -> Result<(Dens3r, Vec<String>), ReconError> {
    let device = dens3r_backbone::device::network_device_at(gpu, precision)?;
    dens3r_backbone::verify::load_model(weights, config, &device).map_err(|e| ReconError::Other(e.to_string()))
}

/// DUSt3R's demo threshold: pixels under this confidence are not fused into its meshes.
pub const DEFAULT_MIN_CONF: f32 = 3.0;

/// The confidence under which `reconstruct` fuses no pixel for this model: the `"min_conf"` of
/// its `config.json` (a model trained elsewhere has its own confidence scale), else
/// [`DEFAULT_MIN_CONF`]. A config that cannot be read, or a value that is not a finite number,
/// is an error naming the file.
pub fn mesh_min_conf(config: Option<&Path>) -> Result<f32, ReconError> {
    let Some(c) = config.filter(|c| c.is_file()) else {
        return Ok(DEFAULT_MIN_CONF);
    };
    let v = dens3r_backbone::verify::config_json(c).map_err(|e| ReconError::Other(e.to_string()))?;
    match v.get("min_conf") {
        None => Ok(DEFAULT_MIN_CONF),
        Some(m) => m.as_f64().map(|m| m as f32).filter(|m| m.is_finite()).ok_or_else(|| {
            ReconError::input(
                c,
                format!("\"min_conf\" is {m}, not a finite number (the confidence under which no pixel is fused)"),
            )
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_config_sets_the_mesh_confidence_threshold() {
        let dir = tempfile::tempdir().unwrap();
        let c = dir.path().join("config.json");
        assert_eq!(mesh_min_conf(None).unwrap(), 3.0);
        std::fs::write(&c, r#"{"enc_depth": 12}"#).unwrap();
        assert_eq!(mesh_min_conf(Some(&c)).unwrap(), 3.0);
        std::fs::write(&c, r#"{"enc_depth": 12, "min_conf": 1.0}"#).unwrap();
        assert_eq!(mesh_min_conf(Some(&c)).unwrap(), 1.0);
        std::fs::write(&c, r#"{"min_conf": "low"}"#).unwrap();
        let e = mesh_min_conf(Some(&c)).unwrap_err().to_string();
        assert!(e.contains("config.json") && e.contains("min_conf"), "{e}");
    }
}
