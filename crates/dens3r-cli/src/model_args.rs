//! The model options shared by the commands that run the network, and the frozen backbones
//! of `--backbone` (train-head, predict --head).

use anyhow::{anyhow, bail, Result};
use clap::Args;
use dens3r_backbone::default_model;
use dens3r_backbone::{Dens3r, Precision};
use dens3r_heads::Backbone;
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct ModelArgs {
    /// Checkpoint: .safetensors, a .pth (read natively; nothing in it is executed), a
    /// Hugging Face model folder (model.safetensors + config.json), or a known name
    /// (`dens3r models`: downloaded into the cache when missing); default: the bundled dens3r-s
    /// (data-samples/models/dens3r-s).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// JSON with the head counts (enc_num_heads, dec_num_heads, or the converter's "args");
    /// default: a .pth's args.model or a folder's config.json, else head dim 64.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Long side of the network input (512, or 1024 for more detail; `512x384` is read as its
    /// long side).
    #[arg(long, default_value_t = 512, value_parser = parse_long_side)]
    pub size: u32,
    /// Keep portrait images as they are (upstream DUSt3R / MASt3R) instead of rotating them to
    /// landscape as the official Dens3R does (a model whose config says `"keep_portrait": true`,
    /// dens3r-s included, keeps them without it).
    #[arg(long)]
    pub keep_portrait: bool,
    /// What the network computes in: f32 (the reference), or f16 / bf16 for speed on a GPU;
    /// on the CPU bf16 takes the linear layers' and attention's products in bf16 (faster on CPUs with AVX-512
    /// BF16) and f16 is slower (`dens3r verify --precision` measures their error).
    #[arg(long, default_value_t = Precision::F32)]
    pub precision: Precision,
}

/// `--size` as a long side: `512`, or `WxH` (`512x384`: its longer side; the other follows
/// each photo's aspect), so the form `train` takes works here too.
pub fn parse_long_side(s: &str) -> Result<u32, String> {
    let t = s.trim();
    let num =
        |x: &str| x.trim().parse::<u32>().map_err(|_| format!("{s:?}: expected a long side (512) or WxH (512x384)"));
    match t.split_once(['x', 'X']) {
        Some((w, h)) => Ok(num(w)?.max(num(h)?)),
        None => num(t),
    }
}

/// `--size` in the range the network takes (checked before any image is read, so the error
/// names the flag, not an image).
pub fn check_size(size: u32) -> Result<()> {
    let sizes = dens3r_backbone::preprocess::SIZES;
    if !sizes.contains(&size) {
        bail!("--size {size}: the network input's long side must be in {sizes:?} (512, or 1024 for more detail)");
    }
    Ok(())
}

/// The checkpoint and its config: `weights` / `config` as given, a known name fetched with a
/// progress bar, or the bundled default model (dens3r-s), saying so in one line on stderr.
pub fn resolve_model(weights: Option<&Path>, config: Option<&Path>) -> Result<(PathBuf, Option<PathBuf>)> {
    let files = dens3r_recon::model::resolve(weights, config, &mut |k| {
        crate::models::fetch(k).map_err(|e| dens3r_recon::ReconError::Other(e.to_string()))
    })?;
    if let Some(n) = &files.default_notice {
        eprintln!("{n}");
    }
    Ok((files.weights, files.config))
}

impl ModelArgs {
    /// The checkpoint file and config this resolves to (see [`resolve_model`]).
    pub fn resolve(&self) -> Result<(PathBuf, Option<PathBuf>)> {
        resolve_model(self.weights.as_deref(), self.config.as_deref())
    }
}

/// Loads the network of [`resolve_model`]'s files on the CPU, or with `gpu` on the GPU, in
/// `precision` ([`dens3r_backbone::device::network_device_at`]), warning about unused
/// checkpoint keys.
pub fn load_network(weights: &Path, config: Option<&Path>, gpu: bool, precision: Precision) -> Result<Dens3r> {
    if let Some(note) = dens3r_backbone::device::precision_note(gpu, precision) {
        eprintln!("{note}");
    }
    let (model, unexpected) = dens3r_recon::model::load_network(weights, config, gpu, precision)?;
    if !unexpected.is_empty() {
        eprintln!("warning: {} checkpoint keys are not used by the model (first: {})", unexpected.len(), unexpected[0]);
    }
    Ok(model)
}

/// Opens the backbone named by a `--backbone` value (`config`: head counts of a Dens3R one).
pub fn open_backbone(spec: &str, config: Option<&Path>) -> Result<Box<dyn Backbone>> {
    let (kind, path) = spec.split_once(':').unwrap_or((spec, ""));
    Ok(match kind {
        "pixels" => Box::new(dens3r_heads::PixelBackbone { patch: 14 }),
        "dinov2" => Box::new(dens3r_heads::Dinov2Backbone::load(Path::new(path), None).map_err(|e| anyhow!(e))?),
        "dens3r" => {
            let (weights, config) = resolve_model((!path.is_empty()).then_some(Path::new(path)), config)?;
            Box::new(dens3r_heads::Dens3rBackbone::load(&weights, config.as_deref(), None).map_err(|e| anyhow!(e))?)
        }
        _ => bail!(
            "--backbone {spec:?}: expected dinov2:MODEL.onnx, dens3r:WEIGHTS.safetensors, dens3r (the bundled {}) or pixels",
            default_model::NAME
        ),
    })
}

#[cfg(test)]
mod tests {
    /// Issue 66, 10: `--size` takes a long side or `WxH` in every command: predict and
    /// reconstruct read `WxH` as its long side, train reads a long side as landscape 4:3.
    #[test]
    fn size_takes_both_forms() {
        assert_eq!(super::parse_long_side("512"), Ok(512));
        assert_eq!(super::parse_long_side("512x384"), Ok(512));
        assert_eq!(super::parse_long_side("288x512"), Ok(512));
        assert!(super::parse_long_side("big").is_err());
        assert_eq!(crate::train::parse_size("224").unwrap(), (224, 160));
        assert_eq!(crate::train::parse_size("512").unwrap(), (512, 384));
        assert_eq!(crate::train::parse_size("448x320").unwrap(), (448, 320));
    }
}
