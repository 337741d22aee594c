//! A network architecture described by the official constructor's keywords (`--arch
//! small.toml`), turned into the [`ModelConfig`] the backbone builds.

use crate::TrainError;
use dens3r_backbone::config::{Blocks, Dens3rSizes, DptWidths, EncoderKind};
use dens3r_backbone::ModelConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Widths and depths of a Dens3R network (unify mode: two point + descriptor heads and a
/// normal head). Field names follow the official constructor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Arch {
    /// The encoder: `vit` (trained with the network, stored in its checkpoint) or `dinov2`
    /// (a frozen DINOv2 read from its `.onnx`, `--dinov2`; then `enc_*` must describe it:
    /// ViT-S/14 is 384 wide, 12 blocks, 6 heads).
    #[serde(default)]
    pub encoder: ArchEncoder,
    /// Patch size.
    #[serde(default = "patch")]
    pub patch_size: usize,
    /// Encoder width.
    pub enc_embed_dim: usize,
    /// Encoder blocks.
    pub enc_depth: usize,
    /// Encoder heads.
    pub enc_num_heads: usize,
    /// Decoder width.
    pub dec_embed_dim: usize,
    /// Decoder blocks.
    pub dec_depth: usize,
    /// Decoder heads.
    pub dec_num_heads: usize,
    /// MLP hidden width over block width.
    #[serde(default = "mlp_ratio")]
    pub mlp_ratio: usize,
    /// One decoder shared by both views.
    #[serde(default = "yes")]
    pub symmetrize_dec: bool,
    /// DPT reassembly widths (full size 96, 192, 384, 768).
    pub layer_dims: [usize; 4],
    /// DPT fusion width (full size 256).
    pub feature_dim: usize,
    /// DPT last hidden width (full size 128).
    pub last_dim: usize,
    /// Descriptor MLP hidden width over its input width (full size 4).
    #[serde(default = "mlp_ratio")]
    pub desc_mlp_ratio: usize,
    /// Descriptor dimension (24).
    #[serde(default = "desc_dim")]
    pub desc_dim: usize,
    /// A separate descriptor confidence channel.
    #[serde(default)]
    pub desc_conf: bool,
}

/// [`Arch::encoder`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ArchEncoder {
    /// The CroCo ViT.
    #[default]
    Vit,
    /// A frozen DINOv2.
    Dinov2,
}

fn patch() -> usize {
    16
}
fn mlp_ratio() -> usize {
    4
}
fn yes() -> bool {
    true
}
fn desc_dim() -> usize {
    24
}

impl Arch {
    /// Reads a TOML (or JSON, by extension) architecture file.
    pub fn read(path: &Path) -> Result<Self, TrainError> {
        let text = std::fs::read_to_string(path).map_err(|e| TrainError::file(path, format!("cannot read ({e})")))?;
        let arch: Self = if path.extension().is_some_and(|e| e == "json") {
            serde_json::from_str(&text).map_err(|e| TrainError::file(path, format!("invalid architecture ({e})")))?
        } else {
            toml::from_str(&text).map_err(|e| TrainError::file(path, format!("invalid architecture ({e})")))?
        };
        arch.check().map_err(|e| TrainError::file(path, format!("{e}")))?;
        Ok(arch)
    }

    /// Checks the widths fit together (heads divide widths, the heads' hooks exist).
    pub fn check(&self) -> Result<(), TrainError> {
        let ok_heads = |d: usize, h: usize| h > 0 && d.is_multiple_of(h) && (d / h).is_multiple_of(4);
        if !ok_heads(self.enc_embed_dim, self.enc_num_heads) || !ok_heads(self.dec_embed_dim, self.dec_num_heads) {
            return Err(TrainError::invalid(
                "each width must split into heads whose dimension is a multiple of 4 (RoPE-2D)",
            ));
        }
        if self.enc_depth == 0 || self.dec_depth < 4 {
            return Err(TrainError::invalid("the encoder needs a block and the decoder at least 4 (the DPT hooks)"));
        }
        if self.patch_size < 2 || self.layer_dims.contains(&0) || self.feature_dim < 2 || self.last_dim == 0 {
            return Err(TrainError::invalid("patch size and DPT widths must be positive"));
        }
        Ok(())
    }

    /// The configuration the backbone builds.
    pub fn config(&self) -> ModelConfig {
        ModelConfig::dens3r(&Dens3rSizes {
            encoder: match self.encoder {
                ArchEncoder::Vit => EncoderKind::Vit,
                ArchEncoder::Dinov2 => EncoderKind::Dinov2,
            },
            patch: self.patch_size,
            enc: Blocks {
                dim: self.enc_embed_dim,
                depth: self.enc_depth,
                heads: self.enc_num_heads,
                mlp_hidden: self.mlp_ratio * self.enc_embed_dim,
            },
            dec: Blocks {
                dim: self.dec_embed_dim,
                depth: self.dec_depth,
                heads: self.dec_num_heads,
                mlp_hidden: self.mlp_ratio * self.dec_embed_dim,
            },
            dpt: DptWidths {
                layer_dims: self.layer_dims,
                feature_dim: self.feature_dim,
                head_dim: self.feature_dim / 2,
                last_dim: self.last_dim,
            },
            desc_hidden: self.desc_mlp_ratio * (self.enc_embed_dim + self.dec_embed_dim),
            desc_dim: self.desc_dim,
            desc_conf: self.desc_conf,
        })
    }
}

/// The `config.json` written beside a trained checkpoint: the constructor keywords the
/// official loader and `--config` read (head counts cannot be recovered from shapes), and
/// `"keep_portrait": true`: training feeds portrait frames upright, so `predict` and
/// `reconstruct` must not turn portrait photos on their side as they do for the official
/// Dens3R.
pub fn config_json(c: &ModelConfig) -> serde_json::Value {
    let mut v = serde_json::json!({
        "output_mode": "unify",
        "head_type": "catmlp+dpt",
        "depth_mode": ["exp", "-inf", "inf"],
        "conf_mode": ["exp", 1, "inf"],
        "normal_mode": ["linear", -1.0, 1.0],
        "desc_conf": c.desc_conf,
        "desc_conf_mode": ["exp", 0, "inf"],
        "pos_embed": "RoPE100",
        "patch_embed_cls": "PatchEmbedDust3R",
        "patch_size": c.patch,
        "enc_embed_dim": c.enc_dim,
        "enc_depth": c.enc_depth,
        "enc_num_heads": c.enc_heads,
        "dec_embed_dim": c.dec_dim,
        "dec_depth": c.dec_depth,
        "dec_num_heads": c.dec_heads,
        "landscape_only": false,
        "symmetrize_dec": c.shared_decoder,
        "keep_portrait": true,
    });
    if c.encoder == EncoderKind::Dinov2 {
        // The encoder is not in the weights: its file, looked up beside them (or $DENS3R_DINOV2).
        v["encoder"] = "dinov2".into();
        v["dinov2_onnx"] = dens3r_backbone::verify::DINOV2_FILE.into();
    }
    v
}
