//! Model configuration read from the weight shapes (model spec section 1.7).

use crate::weights::{Weights, WeightsError};

/// Key prefix of the encoder taps' projections ([`ModelConfig::enc_taps`]): `enc_taps.{block}`.
pub const ENC_TAPS: &str = "enc_taps";

/// Whether checkpoint key `name` belongs to an encoder tap's projection.
pub fn is_encoder_tap(name: &str) -> bool {
    name.strip_prefix(ENC_TAPS).is_some_and(|r| r.starts_with('.'))
}

/// How RoPE-2D positions are scaled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RopeScaling {
    /// Dens3R: positions scaled by `32 / S` per call, `S = max(position) + 1`.
    Interpolated,
    /// Upstream DUSt3R / MASt3R / CroCo: integer positions as they are.
    Plain,
}

/// Which encoder turns images into tokens.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum EncoderKind {
    /// The CroCo ViT of the official checkpoints (`patch_embed`, `enc_blocks`, `enc_norm`),
    /// RoPE-2D, stored in the checkpoint.
    #[default]
    Vit,
    /// A frozen DINOv2 ViT read from its own ONNX file ([`crate::dinov2`]), not stored in the
    /// checkpoint: it sees the image resized by 14 / `patch`, so that each of its tokens
    /// covers `patch` x `patch` input pixels as a ViT token does.
    Dinov2,
}

/// Widths of a DPT head.
#[derive(Debug, Clone, PartialEq)]
pub struct DptConfig {
    /// Key prefix, e.g. `ptsmatch_local_head.dpt`.
    pub prefix: String,
    /// act_postprocess output widths (4 layers).
    pub layer_dims: [usize; 4],
    /// Fusion width (256 full size).
    pub feature_dim: usize,
    /// Width of `head.0` output (feature_dim / 2 full size).
    pub head_dim: usize,
    /// Width of `head.2` output (128 full size).
    pub last_dim: usize,
    /// Output channels.
    pub out_channels: usize,
    /// Upsampling factors of act_postprocess 0 and 1 (ConvTranspose kernel = stride).
    pub up: [usize; 2],
}

/// The widths of a DPT, shared by a network's heads (each has its own prefix and outputs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DptWidths {
    /// act_postprocess output widths (4 layers).
    pub layer_dims: [usize; 4],
    /// Fusion width.
    pub feature_dim: usize,
    /// Width after the first head conv.
    pub head_dim: usize,
    /// Width after the second head conv.
    pub last_dim: usize,
}

impl DptWidths {
    /// The DPT of the head `head` (keys under `{head}.dpt`) with `out_channels` outputs and the
    /// official upsampling (4x, 2x).
    pub fn dpt(&self, head: &str, out_channels: usize) -> DptConfig {
        DptConfig {
            prefix: format!("{head}.dpt"),
            layer_dims: self.layer_dims,
            feature_dim: self.feature_dim,
            head_dim: self.head_dim,
            last_dim: self.last_dim,
            out_channels,
            up: [4, 2],
        }
    }
}

/// Dens3R's two point heads (`ptsmatch_local_head`, `ptsmatch_global_head`): x, y, z and
/// confidence from a DPT of `widths`, and a descriptor MLP of `mlp_hidden` when given.
pub fn pts_heads(widths: DptWidths, mlp_hidden: Option<usize>) -> [PtsHeadConfig; 2] {
    ["ptsmatch_local_head", "ptsmatch_global_head"].map(|prefix| PtsHeadConfig {
        prefix: prefix.into(),
        decoder: PtsDecoder::Dpt(widths.dpt(prefix, 4)),
        mlp_hidden,
    })
}

/// How a point head turns decoder tokens into per-pixel outputs.
#[derive(Debug, Clone, PartialEq)]
pub enum PtsDecoder {
    /// A DPT over the four hooked layers (Dens3R, MASt3R, DUSt3R `_dpt`).
    Dpt(DptConfig),
    /// DUSt3R's linear head (`{prefix}.proj`): the last decoder layer's tokens projected to
    /// `out_channels` values for each of a token's patch x patch pixels, pixel-shuffled.
    Linear {
        /// Outputs per pixel (x, y, z and the confidence).
        out_channels: usize,
    },
}

/// A point (+ descriptor) head.
#[derive(Debug, Clone, PartialEq)]
pub struct PtsHeadConfig {
    /// Key prefix, e.g. `ptsmatch_local_head`.
    pub prefix: String,
    /// Its decoder to pixels.
    pub decoder: PtsDecoder,
    /// Descriptor MLP hidden width (`head_local_features.fc1`), if the head has one.
    pub mlp_hidden: Option<usize>,
}

impl PtsHeadConfig {
    /// The DPT, when the head has one.
    pub fn dpt(&self) -> Option<&DptConfig> {
        match &self.decoder {
            PtsDecoder::Dpt(d) => Some(d),
            PtsDecoder::Linear { .. } => None,
        }
    }

    /// Outputs per pixel before the activations: 3 (x, y, z) or 4 (with the confidence).
    pub fn out_channels(&self) -> usize {
        match &self.decoder {
            PtsDecoder::Dpt(d) => d.out_channels,
            PtsDecoder::Linear { out_channels } => *out_channels,
        }
    }
}

/// Everything needed to build the network.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelConfig {
    /// The encoder.
    pub encoder: EncoderKind,
    /// Encoder taps (a DINOv2 encoder only; empty in the official networks): the 1-based
    /// blocks whose tokens (through the encoder's final LayerNorm), projected by
    /// `enc_taps.{block}` (a linear layer to the hooked layer's width), are added to the DPT
    /// heads' hooked layers 0, 1, ... in block order, as Depth Anything reads DINOv2's
    /// intermediate blocks. Read from the weights' `enc_taps.*` keys.
    pub enc_taps: Vec<usize>,
    /// Patch size (16): input pixels per token side.
    pub patch: usize,
    /// Encoder width.
    pub enc_dim: usize,
    /// Encoder blocks.
    pub enc_depth: usize,
    /// Encoder attention heads.
    pub enc_heads: usize,
    /// Decoder width.
    pub dec_dim: usize,
    /// Decoder blocks.
    pub dec_depth: usize,
    /// Decoder attention heads.
    pub dec_heads: usize,
    /// MLP hidden widths (encoder, decoder).
    pub mlp_hidden: (usize, usize),
    /// One decoder shared by both views (no `dec_blocks2.*`).
    pub shared_decoder: bool,
    /// RoPE base frequency (100).
    pub rope_base: f64,
    /// RoPE position scaling.
    pub rope: RopeScaling,
    /// Head for view 1 (`ptsmatch_local_head` or `downstream_head1`).
    pub head1: PtsHeadConfig,
    /// Head for view 2 (`ptsmatch_global_head` or `downstream_head2`).
    pub head2: PtsHeadConfig,
    /// Normal head (`normal_local_head`), shared by both views; Dens3R only.
    pub normal_head: Option<DptConfig>,
    /// The DPT predicts a confidence channel.
    pub has_conf: bool,
    /// Descriptor dimension (24), 0 without descriptors.
    pub desc_dim: usize,
    /// The descriptor MLP predicts a separate descriptor confidence.
    pub desc_conf: bool,
}

impl ModelConfig {
    /// Reads the configuration from the tensor shapes. Head counts are not recoverable from
    /// weights: pass them (from the checkpoint's config) or `None` for head dim 64.
    pub fn from_weights(w: &Weights, heads: Option<(usize, usize)>) -> Result<Self, WeightsError> {
        let err = |m: String| WeightsError { path: w.path().to_path_buf(), message: m };
        let shape = |k: &str| {
            w.shape(k)
                .map(<[usize]>::to_vec)
                .ok_or_else(|| err(format!("missing key '{k}': not a Dens3R / DUSt3R / MASt3R checkpoint")))
        };
        let count = |prefix: &str| (0..).take_while(|i| w.contains(&format!("{prefix}.{i}.norm1.weight"))).count();
        let dec_depth = count("dec_blocks");
        let de = shape("decoder_embed.weight")?;
        // No encoder in the file but a decoder: the encoder is a frozen DINOv2 kept apart.
        let encoder = if w.contains("patch_embed.proj.weight") || w.contains("enc_blocks.0.norm1.weight") {
            EncoderKind::Vit
        } else {
            EncoderKind::Dinov2
        };
        let (pe, enc_depth) = match encoder {
            EncoderKind::Vit => (shape("patch_embed.proj.weight")?, count("enc_blocks")),
            // DINOv2-S/B/L: 64-wide heads, 12 / 12 / 24 blocks (informational: the ONNX file
            // holds the encoder).
            EncoderKind::Dinov2 => (vec![de[1], 3, 16, 16], if de[1] >= 1024 { 24 } else { 12 }),
        };
        if pe.len() != 4 || pe[1] != 3 || pe[2] != pe[3] {
            return Err(err(format!("patch_embed.proj.weight has shape {pe:?}, expected (D, 3, P, P)")));
        }
        if enc_depth == 0 || dec_depth == 0 {
            return Err(err("no enc_blocks.* or dec_blocks.* keys: not a Dens3R / DUSt3R / MASt3R checkpoint".into()));
        }
        let enc_dim = pe[0];
        let dec_dim = de[0];
        let (enc_heads, dec_heads) = match (heads, encoder) {
            (Some((_, d)), EncoderKind::Dinov2) => (enc_dim / 64, d),
            (Some(h), _) => h,
            (None, _) => (enc_dim / 64, dec_dim / 64),
        };
        if enc_heads == 0 || enc_dim % enc_heads != 0 || dec_heads == 0 || dec_dim % dec_heads != 0 {
            return Err(err(format!(
                "head counts ({enc_heads}, {dec_heads}) do not divide the widths ({enc_dim}, {dec_dim})"
            )));
        }
        let enc_hidden = match encoder {
            EncoderKind::Vit => shape("enc_blocks.0.mlp.fc1.weight")?[0],
            EncoderKind::Dinov2 => 4 * enc_dim,
        };
        let mlp_hidden = (enc_hidden, shape("dec_blocks.0.mlp.fc1.weight")?[0]);
        let dens3r = w.contains("ptsmatch_local_head.dpt.head.4.weight");
        let (p1, p2) = if dens3r {
            ("ptsmatch_local_head", "ptsmatch_global_head")
        } else {
            ("downstream_head1", "downstream_head2")
        };
        if !w.contains(&format!("{p1}.dpt.head.4.weight")) && !w.contains(&format!("{p1}.proj.weight")) {
            return Err(err(format!(
                "no point head found ({p1}.dpt.* or {p1}.proj.*): not a Dens3R / DUSt3R / MASt3R checkpoint"
            )));
        }
        let dpt = |prefix: &str| -> Result<DptConfig, WeightsError> {
            let p = format!("{prefix}.dpt");
            let l = |i: usize| shape(&format!("{p}.act_postprocess.{i}.0.weight")).map(|s| s[0]);
            let up = |i: usize| shape(&format!("{p}.act_postprocess.{i}.1.weight")).map(|s| s[2]);
            let h0 = shape(&format!("{p}.head.0.weight"))?;
            let h2 = shape(&format!("{p}.head.2.weight"))?;
            let h4 = shape(&format!("{p}.head.4.weight"))?;
            Ok(DptConfig {
                prefix: p.clone(),
                layer_dims: [l(0)?, l(1)?, l(2)?, l(3)?],
                feature_dim: h0[1],
                head_dim: h0[0],
                last_dim: h2[0],
                out_channels: h4[0],
                up: [up(0)?, up(1)?],
            })
        };
        let pts = |prefix: &str| -> Result<PtsHeadConfig, WeightsError> {
            let mlp = w.shape(&format!("{prefix}.head_local_features.fc1.weight")).map(|s| s[0]);
            let decoder = match w.shape(&format!("{prefix}.proj.weight")) {
                Some(s) if !w.contains(&format!("{prefix}.dpt.head.4.weight")) => {
                    PtsDecoder::Linear { out_channels: s[0] / (pe[2] * pe[2]).max(1) }
                }
                _ => PtsDecoder::Dpt(dpt(prefix)?),
            };
            Ok(PtsHeadConfig { prefix: prefix.into(), decoder, mlp_hidden: mlp })
        };
        let head1 = pts(p1)?;
        let head2 = pts(p2)?;
        let has_conf = head1.out_channels() == 4;
        let (desc_dim, desc_conf) = match w.shape(&format!("{p1}.head_local_features.fc2.weight")) {
            Some(s) => {
                let per_pixel = s[0] / (pe[2] * pe[2]);
                // 24-d descriptors, plus one channel when desc_conf is on.
                (24, per_pixel == 25)
            }
            None => (0, false),
        };
        let normal_head =
            if w.contains("normal_local_head.dpt.head.4.weight") { Some(dpt("normal_local_head")?) } else { None };
        // The encoder's taps, by block (DINOv2 encoders only).
        let enc_taps = match encoder {
            EncoderKind::Dinov2 => (1..=enc_depth).filter(|b| w.contains(&format!("{ENC_TAPS}.{b}.weight"))).collect(),
            EncoderKind::Vit => Vec::new(),
        };
        if enc_taps.len() > 4 {
            return Err(err(format!("{} enc_taps.* layers; the DPT reads at most 4", enc_taps.len())));
        }
        Ok(Self {
            encoder,
            enc_taps,
            patch: pe[2],
            enc_dim,
            enc_depth,
            enc_heads,
            dec_dim,
            dec_depth,
            dec_heads,
            mlp_hidden,
            shared_decoder: !w.contains("dec_blocks2.0.norm1.weight"),
            rope_base: 100.0,
            rope: if dens3r { RopeScaling::Interpolated } else { RopeScaling::Plain },
            head1,
            head2,
            normal_head,
            has_conf,
            desc_dim,
            desc_conf,
        })
    }

    /// Decoder layers fed to the DPT heads: `[0, L*2/4, L*3/4, L]` of the layer list.
    pub fn hooks(&self) -> [usize; 4] {
        let l = self.dec_depth;
        [0, l * 2 / 4, l * 3 / 4, l]
    }
}

/// One transformer's size: width, blocks, attention heads and MLP hidden width.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Blocks {
    /// Width.
    pub dim: usize,
    /// Blocks.
    pub depth: usize,
    /// Attention heads.
    pub heads: usize,
    /// MLP hidden width.
    pub mlp_hidden: usize,
}

/// The sizes of a Dens3R-family network; the rest is the architecture's (one decoder
/// shared by both views, RoPE100 with position interpolation, a confidence channel, the two
/// point heads and the normal head).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dens3rSizes {
    /// The encoder kind (a ViT trained with the rest, or a frozen DINOv2 kept apart).
    pub encoder: EncoderKind,
    /// Input pixels per token side (16).
    pub patch: usize,
    /// Encoder size.
    pub enc: Blocks,
    /// Decoder size.
    pub dec: Blocks,
    /// The DPT widths of every head.
    pub dpt: DptWidths,
    /// Descriptor MLP hidden width (`head_local_features.fc1`).
    pub desc_hidden: usize,
    /// Descriptor dimension.
    pub desc_dim: usize,
    /// A separate descriptor confidence channel.
    pub desc_conf: bool,
}

impl ModelConfig {
    /// A Dens3R of the given sizes.
    pub fn dens3r(s: &Dens3rSizes) -> Self {
        let [head1, head2] = pts_heads(s.dpt, Some(s.desc_hidden));
        Self {
            encoder: s.encoder,
            enc_taps: Vec::new(),
            patch: s.patch,
            enc_dim: s.enc.dim,
            enc_depth: s.enc.depth,
            enc_heads: s.enc.heads,
            dec_dim: s.dec.dim,
            dec_depth: s.dec.depth,
            dec_heads: s.dec.heads,
            mlp_hidden: (s.enc.mlp_hidden, s.dec.mlp_hidden),
            shared_decoder: true,
            rope_base: 100.0,
            rope: RopeScaling::Interpolated,
            head1,
            head2,
            normal_head: Some(s.dpt.dpt("normal_local_head", 3)),
            has_conf: true,
            desc_dim: s.desc_dim,
            desc_conf: s.desc_conf,
        }
    }

    /// The full-size Dens3R of the paper (ViT-L/16 encoder, 12-block ViT-B decoder shared by
    /// both views, full DPT widths, conf, 24-d descriptors, normal head): for benchmarks and
    /// synthetic weights.
    pub fn dens3r_full() -> Self {
        Self::dens3r(&Dens3rSizes {
            encoder: EncoderKind::Vit,
            patch: 16,
            enc: Blocks { dim: 1024, depth: 24, heads: 16, mlp_hidden: 4096 },
            dec: Blocks { dim: 768, depth: 12, heads: 12, mlp_hidden: 3072 },
            dpt: DptWidths { layer_dims: [96, 192, 384, 768], feature_dim: 256, head_dim: 128, last_dim: 128 },
            desc_hidden: 4 * (1024 + 768),
            desc_dim: 24,
            desc_conf: false,
        })
    }
}
