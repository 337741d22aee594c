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

/// What a model's `config.json` says about running it, beside its architecture.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelSettings {
    /// The confidence under which `reconstruct` fuses no pixel: `"min_conf"` (a model trained
    /// elsewhere has its own confidence scale), else [`DEFAULT_MIN_CONF`].
    pub min_conf: f32,
    /// Portrait photos go in as they are: `"keep_portrait": true` for a model trained on
    /// upright portrait frames (every model `dens3r train` writes, dens3r-s included), which
    /// Dens3R's rotation to landscape would show a world on its side. Else false: rotated, as
    /// the official Dens3R code does.
    pub keep_portrait: bool,
    /// `"tta_scales"`: fractions of the input size at which `predict` also runs the network
    /// and averages the results in (test-time augmentation); else none.
    pub tta_scales: Vec<f64>,
    /// `"tta_mirror": true`: those extra passes see the photo mirrored left-right (read back
    /// mirrored, [`dens3r_backbone::predict::Pass`]); else as it is.
    pub tta_mirror: bool,
}

/// The [`ModelSettings`] of a model's `config` (none: the official models' defaults). A config
/// that cannot be read, or a value of the wrong type, is an error naming the file.
pub fn model_settings(config: Option<&Path>) -> Result<ModelSettings, ReconError> {
    let mut s =
        ModelSettings { min_conf: DEFAULT_MIN_CONF, keep_portrait: false, tta_scales: Vec::new(), tta_mirror: false };
    let Some(c) = config.filter(|c| c.is_file()) else {
        return Ok(s);
    };
    let v = dens3r_backbone::verify::config_json(c).map_err(|e| ReconError::Other(e.to_string()))?;
    if let Some(m) = v.get("min_conf") {
        s.min_conf = m.as_f64().map(|m| m as f32).filter(|m| m.is_finite()).ok_or_else(|| {
            ReconError::input(
                c,
                format!("\"min_conf\" is {m}, not a finite number (the confidence under which no pixel is fused)"),
            )
        })?;
    }
    if let Some(k) = v.get("keep_portrait") {
        s.keep_portrait = k.as_bool().ok_or_else(|| {
            ReconError::input(
                c,
                format!("\"keep_portrait\" is {k}, not true or false (whether portrait photos go in unrotated)"),
            )
        })?;
    }
    if let Some(t) = v.get("tta_scales") {
        let scales: Option<Vec<f64>> =
            t.as_array().and_then(|a| a.iter().map(|x| x.as_f64().filter(|x| x.is_finite() && *x > 0.0)).collect());
        s.tta_scales = scales.ok_or_else(|| {
            ReconError::input(c, format!("\"tta_scales\" is {t}, not a list of positive numbers (e.g. [0.75])"))
        })?;
    }
    if let Some(m) = v.get("tta_mirror") {
        s.tta_mirror = m.as_bool().ok_or_else(|| {
            ReconError::input(
                c,
                format!("\"tta_mirror\" is {m}, not true or false (whether the extra passes see the photo mirrored)"),
            )
        })?;
    }
    Ok(s)
}

/// The long sides of the extra passes at `scales` of `size` (`predict`'s test-time
/// augmentation): each rounded, and refused unless in 16..=8192.
pub fn tta_sizes(scales: &[f64], size: u32) -> Result<Vec<u32>, ReconError> {
    scales
        .iter()
        .map(|&s| {
            let side = (f64::from(size) * s).round();
            if s.is_finite() && s > 0.0 && (16.0..=8192.0).contains(&side) {
                Ok(side as u32)
            } else {
                Err(ReconError::Other(format!(
                    "test-time scale {s}: each scale times the size ({size}) must give a long side in 16..=8192 (e.g. 0.75)"
                )))
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 0.75 of 512 is 384, rounded to the nearest pixel; a side outside 16..=8192, a zero,
    /// negative or NaN scale is refused naming it.
    #[test]
    fn tta_sizes_round_and_refuse_what_cannot_run() {
        assert_eq!(tta_sizes(&[0.75, 0.5, 1.0 / 3.0], 512).unwrap(), vec![384, 256, 171]);
        assert_eq!(tta_sizes(&[], 512).unwrap(), Vec::<u32>::new());
        for bad in [0.01, 20.0, 0.0, -0.5, f64::NAN] {
            let e = tta_sizes(&[0.75, bad], 512).unwrap_err().to_string();
            assert!(e.contains(&format!("scale {bad}")), "{e}");
        }
    }

    #[test]
    fn a_config_sets_the_mesh_confidence_and_portrait_handling() {
        let dir = tempfile::tempdir().unwrap();
        let c = dir.path().join("config.json");
        let official = ModelSettings { min_conf: 3.0, keep_portrait: false, tta_scales: Vec::new(), tta_mirror: false };
        assert_eq!(model_settings(None).unwrap(), official);
        std::fs::write(&c, r#"{"enc_depth": 12}"#).unwrap();
        assert_eq!(model_settings(Some(&c)).unwrap(), official);
        std::fs::write(
            &c,
            r#"{"enc_depth": 12, "min_conf": 1.0, "keep_portrait": true, "tta_scales": [0.75], "tta_mirror": true}"#,
        )
        .unwrap();
        let want = ModelSettings { min_conf: 1.0, keep_portrait: true, tta_scales: vec![0.75], tta_mirror: true };
        assert_eq!(model_settings(Some(&c)).unwrap(), want);
        for (bad, key) in [
            (r#"{"min_conf": "low"}"#, "min_conf"),
            (r#"{"keep_portrait": "yes"}"#, "keep_portrait"),
            (r#"{"tta_scales": 0.75}"#, "tta_scales"),
            (r#"{"tta_scales": [0.75, -1]}"#, "tta_scales"),
            (r#"{"tta_mirror": 1}"#, "tta_mirror"),
        ] {
            std::fs::write(&c, bad).unwrap();
            let e = model_settings(Some(&c)).unwrap_err().to_string();
            assert!(e.contains("config.json") && e.contains(key), "{e}");
        }
    }

    /// The bundled dens3r-s was trained on upright portrait frames: its config keeps them; and
    /// `predict` averages in a pass over the mirrored photo at three quarters of the size.
    #[test]
    fn the_bundled_model_keeps_portrait_photos() {
        let c = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/models/dens3r-s/config.json");
        let s = model_settings(Some(&c)).unwrap();
        assert!(s.keep_portrait && s.min_conf == 1.0 && s.tta_scales == [0.75] && s.tta_mirror, "{s:?}");
    }
}
