//! The network: config -> loader -> forward, in one file (candle-transformers style).

use crate::config::{DptConfig, EncoderKind, ModelConfig, PtsDecoder, PtsHeadConfig};
use crate::cpu;
use crate::dinov2::Dinov2;
use crate::ops::{
    gelu, grid_positions, pixel_shuffle, relu, sdpa, upsample2x, Conv, ConvTranspose, LayerNorm, Linear, Rope,
};
use crate::weights::{Weights, WeightsError};
use burn::tensor::{Device, Tensor};
use std::sync::Arc;

// ---------------------------------------------------------------------------------------------
// Loading helpers

/// Where a module's tensors come from.
enum Source<'a> {
    /// A checkpoint (missing and mis-shaped keys are collected by [`Weights::finish`]).
    Weights(&'a Weights, &'a Device),
    /// Flat tensors by name (a trainable head's or network's parameters).
    Flat(&'a dyn Fn(&str) -> Tensor<1>),
    /// Records every tensor's name and shape, handing out zeros (the parameter layout).
    Layout(std::cell::RefCell<Vec<(String, Vec<usize>)>>, &'a Device),
}

struct Loader<'a> {
    src: Source<'a>,
}

impl Loader<'_> {
    fn get<const D: usize>(&self, name: &str, shape: [usize; D]) -> Tensor<D> {
        match &self.src {
            Source::Weights(w, device) => w.get(name, shape, device),
            Source::Flat(f) => f(name).reshape(shape),
            Source::Layout(names, device) => {
                names.borrow_mut().push((name.to_string(), shape.to_vec()));
                Tensor::zeros(shape, *device)
            }
        }
    }
    fn linear(&self, p: &str, inp: usize, out: usize) -> Linear {
        Linear::new(self.get(&format!("{p}.weight"), [out, inp]), Some(self.get(&format!("{p}.bias"), [out])))
    }
    fn norm(&self, p: &str, d: usize) -> LayerNorm {
        LayerNorm { gamma: self.get(&format!("{p}.weight"), [d]), beta: self.get(&format!("{p}.bias"), [d]), eps: 1e-6 }
    }
    fn conv(&self, p: &str, inp: usize, out: usize, k: usize, stride: usize, bias: bool) -> Conv {
        Conv::new(
            self.get(&format!("{p}.weight"), [out, inp, k, k]),
            bias.then(|| self.get(&format!("{p}.bias"), [out])),
            stride,
            k / 2,
        )
    }
    fn conv_t(&self, p: &str, ch: usize, k: usize) -> ConvTranspose {
        ConvTranspose {
            weight: self.get(&format!("{p}.weight"), [ch, ch, k, k]),
            bias: self.get(&format!("{p}.bias"), [ch]),
            stride: k,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Transformer blocks

struct Mlp {
    fc1: Linear,
    fc2: Linear,
}

impl Mlp {
    fn load(l: &Loader, p: &str, d: usize, hidden: usize, out: usize) -> Self {
        Self { fc1: l.linear(&format!("{p}.fc1"), d, hidden), fc2: l.linear(&format!("{p}.fc2"), hidden, out) }
    }
    fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        self.fc2.forward(gelu(self.fc1.forward(x)))
    }
}

/// `(B, N, heads*Dh) -> (B, heads, N, Dh)`.
fn split_heads(x: Tensor<3>, heads: usize) -> Tensor<4> {
    let [b, n, d] = x.dims();
    x.reshape([b, n, heads, d / heads]).swap_dims(1, 2)
}

/// `(B, heads, N, Dh) -> (B, N, heads*Dh)`.
fn merge_heads(x: Tensor<4>) -> Tensor<3> {
    let [b, h, n, dh] = x.dims();
    x.swap_dims(1, 2).reshape([b, n, h * dh])
}

struct SelfAttention {
    qkv: Linear,
    proj: Linear,
    heads: usize,
}

impl SelfAttention {
    fn load(l: &Loader, p: &str, d: usize, heads: usize) -> Self {
        Self { qkv: l.linear(&format!("{p}.qkv"), d, 3 * d), proj: l.linear(&format!("{p}.proj"), d, d), heads }
    }

    fn forward(&self, x: Tensor<3>, rope: &Rope) -> Tensor<3> {
        let [b, n, d] = x.dims();
        let dh = d / self.heads;
        // (B, N, 3, heads, Dh) -> three (B, heads, N, Dh)
        let qkv = self.qkv.forward(x).reshape([b, n, 3, self.heads, dh]).permute([2, 0, 3, 1, 4]);
        let take = |i: usize| qkv.clone().narrow(0, i, 1).reshape([b, self.heads, n, dh]);
        let (q, k, v) = (rope.apply(take(0)), rope.apply(take(1)), take(2));
        self.proj.forward(merge_heads(sdpa(q, k, v, self.proj.is_bf16())))
    }
}

struct CrossAttention {
    q: Linear,
    k: Linear,
    v: Linear,
    proj: Linear,
    heads: usize,
}

impl CrossAttention {
    fn forward(&self, x: Tensor<3>, y: Tensor<3>, rope_q: &Rope, rope_k: &Rope) -> Tensor<3> {
        let q = rope_q.apply(split_heads(self.q.forward(x), self.heads));
        let k = rope_k.apply(split_heads(self.k.forward(y.clone()), self.heads));
        let v = split_heads(self.v.forward(y), self.heads);
        self.proj.forward(merge_heads(sdpa(q, k, v, self.proj.is_bf16())))
    }
}

struct EncoderBlock {
    norm1: LayerNorm,
    attn: SelfAttention,
    norm2: LayerNorm,
    mlp: Mlp,
}

impl EncoderBlock {
    fn load(l: &Loader, p: &str, d: usize, heads: usize, hidden: usize) -> Self {
        Self {
            norm1: l.norm(&format!("{p}.norm1"), d),
            attn: SelfAttention::load(l, &format!("{p}.attn"), d, heads),
            norm2: l.norm(&format!("{p}.norm2"), d),
            mlp: Mlp::load(l, &format!("{p}.mlp"), d, hidden, d),
        }
    }
    fn forward(&self, x: Tensor<3>, rope: &Rope) -> Tensor<3> {
        let x = x.clone() + self.attn.forward(self.norm1.forward(x), rope);
        x.clone() + self.mlp.forward(self.norm2.forward(x))
    }
}

struct DecoderBlock {
    norm1: LayerNorm,
    attn: SelfAttention,
    norm_y: LayerNorm,
    norm2: LayerNorm,
    cross: CrossAttention,
    norm3: LayerNorm,
    mlp: Mlp,
}

impl DecoderBlock {
    fn load(l: &Loader, p: &str, d: usize, heads: usize, hidden: usize) -> Self {
        let lin = |n: &str| l.linear(&format!("{p}.cross_attn.{n}"), d, d);
        Self {
            norm1: l.norm(&format!("{p}.norm1"), d),
            attn: SelfAttention::load(l, &format!("{p}.attn"), d, heads),
            norm_y: l.norm(&format!("{p}.norm_y"), d),
            norm2: l.norm(&format!("{p}.norm2"), d),
            cross: CrossAttention { q: lin("projq"), k: lin("projk"), v: lin("projv"), proj: lin("proj"), heads },
            norm3: l.norm(&format!("{p}.norm3"), d),
            mlp: Mlp::load(l, &format!("{p}.mlp"), d, hidden, d),
        }
    }
    fn forward(&self, x: Tensor<3>, y: Tensor<3>, rope_x: &Rope, rope_y: &Rope) -> Tensor<3> {
        let x = x.clone() + self.attn.forward(self.norm1.forward(x), rope_x);
        let y = self.norm_y.forward(y);
        let x = x.clone() + self.cross.forward(self.norm2.forward(x), y, rope_x, rope_y);
        x.clone() + self.mlp.forward(self.norm3.forward(x))
    }
}

// ---------------------------------------------------------------------------------------------
// DPT head

struct ResidualConvUnit {
    conv1: Conv,
    conv2: Conv,
}

impl ResidualConvUnit {
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.conv2.forward(relu(self.conv1.forward(relu(x.clone())))) + x
    }
}

struct FusionBlock {
    /// Applied to the skip input; `None` in refinenet4, which has none (its checkpoint
    /// tensors are never used).
    rcu1: Option<ResidualConvUnit>,
    rcu2: ResidualConvUnit,
    out_conv: Conv,
}

impl FusionBlock {
    fn forward(&self, x: Tensor<4>, skip: Option<Tensor<4>>) -> Tensor<4> {
        let x = match skip {
            Some(s) => x + self.rcu1.as_ref().expect("refinenets with a skip have rcu1").forward(s),
            None => x,
        };
        // PyTorch applies the 1x1 out_conv after the x2 upsampling; both are linear and the
        // bilinear weights of each output pixel sum to 1 (bias included), so they commute:
        // convolving first costs a quarter of the work for the same values (to rounding).
        upsample2x(self.out_conv.forward(self.rcu2.forward(x)))
    }
}

/// A DPT head (DUSt3R's `DPTOutputAdapter`): reassembly of four hooked layers, fusion coarse
/// to fine, the three-conv head. Built from a checkpoint inside [`Dens3r`], or from flat named
/// tensors ([`Dpt::from_flat`]) as a trainable head.
pub struct Dpt {
    /// Per hooked layer: 1x1 projection, then optional resampling.
    project: Vec<Conv>,
    up: Vec<Option<ConvTranspose>>,
    down: Option<Conv>,
    layer_rn: Vec<Conv>,
    refine: Vec<FusionBlock>,
    head0: Conv,
    head2: Conv,
    head4: Conv,
}

impl Dpt {
    fn load(l: &Loader, c: &DptConfig, in_dims: [usize; 4]) -> Self {
        let p = &c.prefix;
        let f = c.feature_dim;
        let project = (0..4)
            .map(|i| l.conv(&format!("{p}.act_postprocess.{i}.0"), in_dims[i], c.layer_dims[i], 1, 1, true))
            .collect();
        let up = (0..4)
            .map(|i| (i < 2).then(|| l.conv_t(&format!("{p}.act_postprocess.{i}.1"), c.layer_dims[i], c.up[i])))
            .collect();
        let down = Some(l.conv(&format!("{p}.act_postprocess.3.1"), c.layer_dims[3], c.layer_dims[3], 3, 2, true));
        let layer_rn = (0..4)
            .map(|i| l.conv(&format!("{p}.scratch.layer{}_rn", i + 1), c.layer_dims[i], f, 3, 1, false))
            .collect();
        let refine = (1..=4)
            .map(|i| {
                let r = format!("{p}.scratch.refinenet{i}");
                let rcu = |u: usize| ResidualConvUnit {
                    conv1: l.conv(&format!("{r}.resConfUnit{u}.conv1"), f, f, 3, 1, true),
                    conv2: l.conv(&format!("{r}.resConfUnit{u}.conv2"), f, f, 3, 1, true),
                };
                FusionBlock {
                    rcu1: (i != 4).then(|| rcu(1)),
                    rcu2: rcu(2),
                    out_conv: l.conv(&format!("{r}.out_conv"), f, f, 1, 1, true),
                }
            })
            .collect();
        Self {
            project,
            up,
            down,
            layer_rn,
            refine,
            head0: l.conv(&format!("{p}.head.0"), f, c.head_dim, 3, 1, true),
            head2: l.conv(&format!("{p}.head.2"), c.head_dim, c.last_dim, 3, 1, true),
            head4: l.conv(&format!("{p}.head.4"), c.last_dim, c.out_channels, 1, 1, true),
        }
    }

    /// Every tensor a DPT of `c` reads, `(name under c.prefix, shape)` in load order: the one
    /// description of its parameters (refinenet4's unused `resConfUnit1` is not among them).
    pub fn parameter_layout(c: &DptConfig, in_dims: [usize; 4]) -> Vec<(String, Vec<usize>)> {
        let device = Device::autodiff(Device::flex());
        let l = Loader { src: Source::Layout(Default::default(), &device) };
        drop(Self::load(&l, c, in_dims));
        match l.src {
            Source::Layout(names, _) => names.into_inner(),
            _ => unreachable!("a layout loader"),
        }
    }

    /// A DPT from flat tensors named as in a checkpoint (`{c.prefix}.act_postprocess.0.0.weight`
    /// and so on; refinenet4's unused `resConfUnit1` is not read), on their device.
    pub fn from_flat(c: &DptConfig, in_dims: [usize; 4], get: &dyn Fn(&str) -> Tensor<1>) -> Self {
        Self::load(&Loader { src: Source::Flat(get) }, c, in_dims)
    }

    /// Raw output `(B, C_out, H, W)` from the four hooked token maps `(B, N, C)`.
    fn forward(&self, layers: [Tensor<3>; 4], (h, w): (usize, usize)) -> Tensor<4> {
        self.forward_maps(layers.map(|t| {
            let [b, _, c] = t.dims();
            t.swap_dims(1, 2).reshape([b, c, h, w])
        }))
    }

    /// Raw output `(B, C_out, 16 h, 16 w)` from the four hooked layers as `(B, C, h, w)` maps.
    pub fn forward_maps(&self, layers: [Tensor<4>; 4]) -> Tensor<4> {
        let mut maps = Vec::with_capacity(4);
        for (i, t) in layers.into_iter().enumerate() {
            let mut x = self.project[i].forward(t);
            if let Some(u) = &self.up[i] {
                x = u.forward(x);
            }
            if i == 3 {
                x = self.down.as_ref().expect("layer 4 downsamples").forward(x);
            }
            maps.push(self.layer_rn[i].forward(x));
        }
        let l3 = maps[2].dims();
        let path4 = self.refine[3].forward(maps[3].clone(), None);
        // An odd grid makes the stride-2 conv round up: crop back to layer 3's size.
        let path4 = path4.slice([0..l3[0], 0..l3[1], 0..l3[2], 0..l3[3]]);
        let path3 = self.refine[2].forward(path4, Some(maps[2].clone()));
        let path2 = self.refine[1].forward(path3, Some(maps[1].clone()));
        let path1 = self.refine[0].forward(path2, Some(maps[0].clone()));
        self.tail(self.head0.forward(path1))
    }

    /// `head4(relu(head2(upsample2x(x))))`. On the CPU in bands of output rows, each from its
    /// rows of the upsampled map plus one above and below: the full-resolution map (128
    /// channels at the input's size, 100 MB at 512x384) is never made, and no tensor is
    /// copied in between.
    fn tail(&self, x: Tensor<4>) -> Tensor<4> {
        if !(cpu::serves(&x.device()) && self.head2.has_raw() && self.head4.has_raw()) {
            return self.head4.forward(relu(self.head2.forward(upsample2x(x))));
        }
        let device = x.device();
        let [b, c, h, w] = x.dims();
        let (ho, wo) = (2 * h, 2 * w);
        let data = cpu::to_vec(x);
        let out_ch = self.head4.out_ch;
        let mut out = vec![0.0f32; b * out_ch * ho * wo];
        for (img, dst) in data.chunks_exact(c * h * w).zip(out.chunks_exact_mut(out_ch * ho * wo)) {
            for r0 in (0..ho).step_by(TAIL_BAND) {
                let r1 = (r0 + TAIL_BAND).min(ho);
                // Rows a..e of the upsampled map: the band and its 3x3 neighbours (zero padding
                // only at the image's own edges, as the whole-image convolution has).
                let (a, e) = (r0.saturating_sub(1), (r1 + 1).min(ho));
                let up = cpu::resample::upsample2x_rows(img, c, h, w, a..e);
                let mut y = self.head2.forward_raw(&up, e - a, wo).expect("a CPU kernel");
                cpu::resample::relu_in_place(&mut y);
                // The 1x1 convolution over the whole band (its few output channels cost less
                // than copying the wide ones), then rows r0..r1 of each output channel.
                let z = self.head4.forward_raw(&y, e - a, wo).expect("a CPU kernel");
                let skip = (r0 - a) * wo;
                for (o, zc) in dst.chunks_exact_mut(ho * wo).zip(z.chunks_exact((e - a) * wo)) {
                    o[r0 * wo..r1 * wo].copy_from_slice(&zc[skip..skip + (r1 - r0) * wo]);
                }
            }
        }
        cpu::from_vec(out, [b, out_ch, ho, wo], &device)
    }
}

/// Output rows per band of [`Dpt::tail`].
const TAIL_BAND: usize = 64;

/// The pointmap activation (`depth_mode` 'exp'): `v / max(|v|, 1e-8) * expm1(|v|)` for the
/// three raw channels `v` along `dim`.
///
/// The norm is `sqrt(max(|v|^2, 1e-30))`: the same values, but a zero vector (a ReLU-dead
/// region) has a zero gradient instead of NaN, as PyTorch's norm has.
pub fn exp_depth_mode(v: Tensor<4>, dim: usize) -> Tensor<4> {
    let d = v.clone().square().sum_dim(dim).clamp_min(1e-30).sqrt();
    v / d.clone().clamp_min(1e-8) * d.exp().sub_scalar(1.0)
}

/// A point head's way to pixels: a DPT, or DUSt3R's linear projection.
enum ToPixels {
    Dpt(Box<Dpt>),
    Linear(Linear),
}

/// Per-token outputs `(B, N, C p^2)` on a `grid` of tokens as pixel maps `(B, C, H, W)`: the
/// official `transpose`, `view` to the grid, then `pixel_shuffle` by the patch size `p`.
fn tokens_to_pixels(t: Tensor<3>, (h, w): (usize, usize), p: usize) -> Tensor<4> {
    let [b, _, ch] = t.dims();
    pixel_shuffle(t.swap_dims(1, 2).reshape([b, ch, h, w]), p)
}

struct PtsHead {
    to_pixels: ToPixels,
    mlp: Option<Mlp>,
}

// ---------------------------------------------------------------------------------------------
// Public API

/// Backbone output for one view; reusable by any head without re-running the backbone.
#[derive(Debug, Clone)]
pub struct ViewFeatures {
    /// Encoder tokens after `enc_norm`, `(B, N, D_enc)`.
    pub enc: Tensor<3>,
    /// The encoder's tapped blocks' tokens ([`ModelConfig::enc_taps`]), `(B, N, D_enc)` each.
    pub taps: Vec<Tensor<3>>,
    /// Decoder block outputs, `(B, N, D_dec)` each; the last one after `dec_norm`.
    pub dec: Vec<Tensor<3>>,
    /// Token grid `(h, w)`.
    pub grid: (usize, usize),
}

impl ViewFeatures {
    /// The head input list of spec 1.3: encoder output, then every decoder layer.
    pub fn layer(&self, i: usize) -> Tensor<3> {
        if i == 0 {
            self.enc.clone()
        } else {
            self.dec[i - 1].clone()
        }
    }

    /// Image size `(H, W)` in pixels for patch size `p`.
    pub fn image_size(&self, p: usize) -> (usize, usize) {
        (self.grid.0 * p, self.grid.1 * p)
    }
}

/// Features of a pair (view 1 is the reference frame).
#[derive(Debug, Clone)]
pub struct Features {
    /// View 1 then view 2.
    pub views: [ViewFeatures; 2],
}

/// Post-processed outputs of one view, `(B, H, W[, C])` (spec 1.6).
#[derive(Debug, Clone)]
pub struct ViewPrediction {
    /// Pointmap in camera 1's OpenCV frame (view 2: `pts3d_in_other_view`), `(B, H, W, 3)`.
    pub pts3d: Tensor<4>,
    /// Confidence `1 + exp(x)`, `(B, H, W)`, if the model predicts one.
    pub conf: Option<Tensor<3>>,
    /// Unit descriptors `(B, H, W, 24)`, if the model has a descriptor MLP.
    pub desc: Option<Tensor<4>>,
    /// Descriptor confidence `(B, H, W)` (a copy of `conf` without desc_conf).
    pub desc_conf: Option<Tensor<3>>,
    /// Unit normals in the view's own camera frame, **Dens3R raw convention**, `(B, H, W, 3)`.
    pub normal: Option<Tensor<4>>,
    /// Raw DPT output of the point head `(B, C, H, W)` and of the normal head, and the raw
    /// descriptor MLP output `(B, N, C*P^2)`: kept for parity checks.
    pub raw_pts: Tensor<4>,
    /// See `raw_pts`.
    pub raw_normal: Option<Tensor<4>>,
    /// See `raw_pts`.
    pub raw_mlp: Option<Tensor<3>>,
}

/// Which optional outputs [`Dens3r::heads_with`] computes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeadOutputs {
    /// The normal head.
    pub normal: bool,
    /// Descriptors and their confidence (the local-feature MLP).
    pub desc: bool,
}

impl HeadOutputs {
    /// Every output.
    pub const ALL: Self = Self { normal: true, desc: true };
}

/// Predictions of a pair.
#[derive(Debug, Clone)]
pub struct Predictions {
    /// View 1 then view 2.
    pub views: [ViewPrediction; 2],
}

/// Whether `dinov2` can be the encoder of a network of `config`: the network's encoder must be
/// a DINOv2 ([`EncoderKind::Dinov2`]) of the width its decoder reads.
pub fn dinov2_fits(config: &ModelConfig, dinov2: &Dinov2) -> Result<(), WeightsError> {
    if config.encoder != EncoderKind::Dinov2 {
        return Err(WeightsError::new(
            &dinov2.path,
            "the network has its own ViT encoder; a DINOv2 is only for a DINOv2-encoder network",
        ));
    }
    if dinov2.config.dim != config.enc_dim {
        return Err(WeightsError::new(
            &dinov2.path,
            format!(
                "a {}-wide DINOv2, but the decoder reads {}-wide tokens; use the encoder the network was trained with",
                dinov2.config.dim, config.enc_dim
            ),
        ));
    }
    Ok(())
}

/// The encoder: the checkpoint's ViT, or a frozen DINOv2 attached after loading.
enum Encoder {
    Vit { patch: Box<Conv>, blocks: Vec<EncoderBlock>, norm: Box<LayerNorm> },
    Dinov2(Option<Arc<Dinov2>>),
}

/// A loaded Dens3R / DUSt3R / MASt3R network.
pub struct Dens3r {
    /// The configuration read from the weights.
    pub config: ModelConfig,
    device: Device,
    encoder: Encoder,
    decoder_embed: Linear,
    dec_blocks: Vec<DecoderBlock>,
    dec_blocks2: Option<Vec<DecoderBlock>>,
    dec_norm: LayerNorm,
    head1: PtsHead,
    head2: PtsHead,
    normal_head: Option<Dpt>,
    /// Projections of the encoder's taps onto the hooked layers ([`ModelConfig::enc_taps`]).
    enc_taps: Vec<Linear>,
}

impl Dens3r {
    /// Builds the network from checkpoint tensors. A missing or mis-shaped key is an error
    /// listing every such key; the returned list holds unexpected (unused) keys.
    pub fn load(w: &Weights, config: ModelConfig, device: &Device) -> Result<(Self, Vec<String>), WeightsError> {
        let model = Self::build(&Loader { src: Source::Weights(w, device) }, config, device);
        let unexpected = w.finish()?;
        Ok((model, unexpected))
    }

    /// The network from flat tensors named as in a checkpoint (`enc_blocks.0.attn.qkv.weight`
    /// and so on; see [`Dens3r::parameter_layout`]), on `device`. On an autodiff device with
    /// tensors that require gradients this is the trainable network: the same layers and
    /// forward as inference.
    pub fn from_flat(config: ModelConfig, device: &Device, get: &dyn Fn(&str) -> Tensor<1>) -> Self {
        Self::build(&Loader { src: Source::Flat(get) }, config, device)
    }

    /// Every tensor the network reads, `(checkpoint name, shape)` in load order: its
    /// parameters. (Builds the network once on zeros, on an autodiff flex device so that no
    /// CPU kernel is prepared.)
    pub fn parameter_layout(config: &ModelConfig) -> Vec<(String, Vec<usize>)> {
        let device = Device::autodiff(Device::flex());
        let l = Loader { src: Source::Layout(Default::default(), &device) };
        drop(Self::build(&l, config.clone(), &device));
        match l.src {
            Source::Layout(names, _) => names.into_inner(),
            _ => unreachable!("a layout loader"),
        }
    }

    fn build(l: &Loader, config: ModelConfig, device: &Device) -> Self {
        let c = &config;
        let encoder = match c.encoder {
            EncoderKind::Vit => {
                let (wp, bp) = ("patch_embed.proj.weight", "patch_embed.proj.bias");
                let patch =
                    Conv::new(l.get(wp, [c.enc_dim, 3, c.patch, c.patch]), Some(l.get(bp, [c.enc_dim])), c.patch, 0);
                Encoder::Vit {
                    patch: Box::new(patch),
                    blocks: (0..c.enc_depth)
                        .map(|i| {
                            EncoderBlock::load(l, &format!("enc_blocks.{i}"), c.enc_dim, c.enc_heads, c.mlp_hidden.0)
                        })
                        .collect(),
                    norm: Box::new(l.norm("enc_norm", c.enc_dim)),
                }
            }
            EncoderKind::Dinov2 => Encoder::Dinov2(None),
        };
        let dec = |name: &str| {
            (0..c.dec_depth)
                .map(|i| DecoderBlock::load(l, &format!("{name}.{i}"), c.dec_dim, c.dec_heads, c.mlp_hidden.1))
                .collect::<Vec<_>>()
        };
        let in_dims = [c.enc_dim, c.dec_dim, c.dec_dim, c.dec_dim];
        let pts_head = |h: &PtsHeadConfig| PtsHead {
            to_pixels: match &h.decoder {
                PtsDecoder::Dpt(d) => ToPixels::Dpt(Box::new(Dpt::load(l, d, in_dims))),
                PtsDecoder::Linear { out_channels } => ToPixels::Linear(l.linear(
                    &format!("{}.proj", h.prefix),
                    c.dec_dim,
                    out_channels * c.patch * c.patch,
                )),
            },
            mlp: h.mlp_hidden.map(|hidden| {
                let out = (c.desc_dim + c.desc_conf as usize) * c.patch * c.patch;
                Mlp::load(l, &format!("{}.head_local_features", h.prefix), c.enc_dim + c.dec_dim, hidden, out)
            }),
        };
        Self {
            device: device.clone(),
            encoder,
            decoder_embed: l.linear("decoder_embed", c.enc_dim, c.dec_dim),
            dec_blocks: dec("dec_blocks"),
            dec_blocks2: (!c.shared_decoder).then(|| dec("dec_blocks2")),
            dec_norm: l.norm("dec_norm", c.dec_dim),
            head1: pts_head(&c.head1),
            head2: pts_head(&c.head2),
            normal_head: c.normal_head.as_ref().map(|d| Dpt::load(l, d, in_dims)),
            enc_taps: c
                .enc_taps
                .iter()
                .zip(in_dims)
                .map(|(b, d)| l.linear(&format!("{}.{b}", crate::config::ENC_TAPS), c.enc_dim, d))
                .collect(),
            config,
        }
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// [`Dens3r::encode_image`]'s tokens split into the encoder's output and its taps.
    fn split_taps(&self, e: Tensor<3>) -> (Tensor<3>, Vec<Tensor<3>>) {
        let d = self.config.enc_dim;
        let taps = (1..=self.config.enc_taps.len()).map(|k| e.clone().narrow(2, k * d, d)).collect();
        let e = if self.config.enc_taps.is_empty() { e } else { e.narrow(2, 0, d) };
        (e, taps)
    }

    /// The DPT heads' four hooked layers of a view: [`ViewFeatures::layer`] at
    /// [`ModelConfig::hooks`], each tap's projection added to its layer.
    fn hooked_layers(&self, v: &ViewFeatures) -> [Tensor<3>; 4] {
        let mut layers = self.config.hooks().map(|i| v.layer(i));
        for ((layer, proj), tap) in layers.iter_mut().zip(&self.enc_taps).zip(&v.taps) {
            *layer = layer.clone() + proj.forward(tap.clone());
        }
        layers
    }

    fn rope(&self, grid: (usize, usize), head_dim: usize) -> Rope {
        Rope::new(&grid_positions(grid.0, grid.1), head_dim, self.config.rope_base, self.config.rope, &self.device)
    }

    /// Attaches the frozen DINOv2 of a network whose encoder is one
    /// ([`EncoderKind::Dinov2`]); an error when the widths differ or the network has its own.
    pub fn attach_dinov2(&mut self, dinov2: Arc<Dinov2>) -> Result<(), WeightsError> {
        dinov2_fits(&self.config, &dinov2)?;
        if let Encoder::Dinov2(slot) = &mut self.encoder {
            *slot = Some(dinov2);
        }
        Ok(())
    }

    /// Encoder tokens `(B, N, D_enc)` of normalised images `(B, 3, H, W)` (H, W multiples of
    /// the patch size); with [`ModelConfig::enc_taps`], the tapped blocks' tokens follow along
    /// the channels, `(B, N, D_enc * (1 + taps))` ([`Dens3r::decode`] splits them).
    ///
    /// # Panics
    /// For a DINOv2-encoder network whose DINOv2 was never attached
    /// ([`Dens3r::attach_dinov2`]; `verify::load_model` attaches it).
    pub fn encode_image(&self, img: Tensor<4>) -> (Tensor<3>, (usize, usize)) {
        let [b, _, h, w] = img.dims();
        let p = self.config.patch;
        let grid = (h / p, w / p);
        match &self.encoder {
            Encoder::Vit { patch, blocks, norm } => {
                let x = patch.forward(img); // (B, D, h, w)
                let d = self.config.enc_dim;
                let mut x = x.reshape([b, d, grid.0 * grid.1]).swap_dims(1, 2);
                let rope = self.rope(grid, d / self.config.enc_heads);
                for blk in blocks {
                    x = blk.forward(x, &rope);
                }
                (norm.forward(x), grid)
            }
            Encoder::Dinov2(Some(d)) => d.encode_dens3r(img, p, &self.config.enc_taps),
            Encoder::Dinov2(None) => panic!("the network's DINOv2 encoder was not attached (Dens3r::attach_dinov2)"),
        }
    }

    /// The attached DINOv2 encoder, if the network has one.
    pub fn dinov2(&self) -> Option<&Arc<Dinov2>> {
        match &self.encoder {
            Encoder::Dinov2(d) => d.as_ref(),
            Encoder::Vit { .. } => None,
        }
    }

    /// Runs encoder and decoder on a pair of normalised images `(B, 3, H, W)` in `[-1, 1]`.
    pub fn encode(&self, img1: Tensor<4>, img2: Tensor<4>) -> Features {
        let [(e1, g1), (e2, g2)] = self.encode_images(img1, img2);
        self.decode(e1, g1, e2, g2)
    }

    /// [`Dens3r::encode_image`] of both images of a pair: as one batch when they have the same
    /// size, as the official `_encode_symmetrized` does (the encoder's products then take both
    /// views' tokens as rows).
    pub fn encode_images(&self, img1: Tensor<4>, img2: Tensor<4>) -> [(Tensor<3>, (usize, usize)); 2] {
        if img1.dims() != img2.dims() {
            return [self.encode_image(img1), self.encode_image(img2)];
        }
        let b = img1.dims()[0];
        let (e, g) = self.encode_image(Tensor::cat(vec![img1, img2], 0));
        let [_, n, d] = e.dims();
        [(e.clone().slice([0..b, 0..n, 0..d]), g), (e.slice([b..2 * b, 0..n, 0..d]), g)]
    }

    /// The decoder on two views' encoder tokens ([`Dens3r::encode_image`] outputs and their
    /// patch grids): `encode(a, b)` is `decode(encode_image(a), encode_image(b))`, so an image
    /// in several pairs needs encoding once.
    pub fn decode(&self, e1: Tensor<3>, g1: (usize, usize), e2: Tensor<3>, g2: (usize, usize)) -> Features {
        let dh = self.config.dec_dim / self.config.dec_heads;
        let (r1, r2) = (self.rope(g1, dh), self.rope(g2, dh));
        let dev = e1.device();
        let ((e1, t1), (e2, t2)) = (self.split_taps(e1), self.split_taps(e2));
        let (mut f1, mut f2) =
            both(&dev, || self.decoder_embed.forward(e1.clone()), || self.decoder_embed.forward(e2.clone()));
        let (mut out1, mut out2) = (Vec::new(), Vec::new());
        let blocks2 = self.dec_blocks2.as_ref().unwrap_or(&self.dec_blocks);
        for (b1, b2) in self.dec_blocks.iter().zip(blocks2) {
            (f1, f2) = both(
                &dev,
                || b1.forward(f1.clone(), f2.clone(), &r1, &r2),
                || b2.forward(f2.clone(), f1.clone(), &r2, &r1),
            );
            out1.push(f1.clone());
            out2.push(f2.clone());
        }
        for out in [&mut out1, &mut out2] {
            let last = out.pop().expect("decoder has blocks");
            out.push(self.dec_norm.forward(last));
        }
        Features {
            views: [
                ViewFeatures { enc: e1, taps: t1, dec: out1, grid: g1 },
                ViewFeatures { enc: e2, taps: t2, dec: out2, grid: g2 },
            ],
        }
    }

    /// [`Dens3r::encode`] of the self-pair `(img, img)` (the single-image mode) without the
    /// redundant work: the encoder runs once, and with a shared decoder both views' states are
    /// equal at every layer, so the decoder runs once too (cross-attending to itself). The
    /// result equals `encode(img, img)`.
    pub fn encode_self(&self, img: Tensor<4>) -> Features {
        if self.dec_blocks2.is_some() {
            let (e, g) = self.encode_image(img);
            return self.decode(e.clone(), g, e, g);
        }
        let (e, g) = self.encode_image(img);
        let (e, taps) = self.split_taps(e);
        let dh = self.config.dec_dim / self.config.dec_heads;
        let r = self.rope(g, dh);
        let mut f = self.decoder_embed.forward(e.clone());
        let mut out = Vec::new();
        for b in &self.dec_blocks {
            f = b.forward(f.clone(), f, &r, &r);
            out.push(f.clone());
        }
        let last = out.pop().expect("decoder has blocks");
        out.push(self.dec_norm.forward(last));
        let v = ViewFeatures { enc: e, taps, dec: out, grid: g };
        Features { views: [v.clone(), v] }
    }

    /// View 1 of the self-pair (`pred1` of `forward(img, img)`), the single-image prediction,
    /// at about half the cost: [`Dens3r::encode_self`] and view 1's heads only.
    pub fn forward_mono(&self, img: Tensor<4>) -> ViewPrediction {
        self.mono_heads(&self.encode_self(img).views[0])
    }

    /// View 1's heads on self-pair features ([`Dens3r::encode_self`]): with the features
    /// kept, other heads can read the same backbone pass.
    pub fn mono_heads(&self, v: &ViewFeatures) -> ViewPrediction {
        self.mono_heads_with(v, HeadOutputs::ALL)
    }

    /// [`Dens3r::mono_heads`] computing only the optional outputs in `want`.
    pub fn mono_heads_with(&self, v: &ViewFeatures, want: HeadOutputs) -> ViewPrediction {
        self.view_heads(&self.head1, v, want, true)
    }

    /// Runs the heads on backbone features.
    pub fn heads(&self, f: &Features) -> Predictions {
        self.heads_with(f, HeadOutputs::ALL)
    }

    /// [`Dens3r::heads`] computing only the optional outputs in `want` (the pointmap and
    /// confidence always): training skips what its stage's losses do not read.
    pub fn heads_with(&self, f: &Features, want: HeadOutputs) -> Predictions {
        let [v1, v2] = &f.views;
        let (p1, p2) = both(
            &v1.enc.device(),
            || self.view_heads(&self.head1, v1, want, false),
            || self.view_heads(&self.head2, v2, want, false),
        );
        Predictions { views: [p1, p2] }
    }

    /// Encoder + decoder + heads on a pair.
    pub fn forward(&self, img1: Tensor<4>, img2: Tensor<4>) -> Predictions {
        self.heads(&self.encode(img1, img2))
    }

    /// One view's heads; `side_by_side`: the point and normal DPTs run side by side on the CPU
    /// (the single-image path; a pair's two views already run so).
    fn view_heads(&self, head: &PtsHead, v: &ViewFeatures, want: HeadOutputs, side_by_side: bool) -> ViewPrediction {
        let c = &self.config;
        let hooked = self.hooked_layers(v);
        let layers = || hooked.clone();
        let pts = || match &head.to_pixels {
            ToPixels::Dpt(d) => d.forward(layers(), v.grid),
            // DUSt3R's LinearPts3d: the last decoder layer, projected and pixel-shuffled.
            ToPixels::Linear(proj) => tokens_to_pixels(proj.forward(v.layer(c.dec_depth)), v.grid, c.patch),
        };
        let normal = || self.normal_head.as_ref().filter(|_| want.normal).map(|d| d.forward(layers(), v.grid));
        let (raw_pts, raw_normal) = if side_by_side { both(&v.enc.device(), pts, normal) } else { (pts(), normal()) };
        let raw_mlp = head
            .mlp
            .as_ref()
            .filter(|_| want.desc)
            .map(|m| m.forward(Tensor::cat(vec![v.layer(0), v.layer(c.dec_depth)], 2)));
        // (B, C, H, W) -> (B, H, W, C)
        let fmap = raw_pts.clone().permute([0, 2, 3, 1]);
        let [b, h, w, _] = fmap.dims();
        let pts3d = exp_depth_mode(fmap.clone().narrow(3, 0, 3), 3);
        let conf = c.has_conf.then(|| fmap.clone().narrow(3, 3, 1).exp().add_scalar(1.0).reshape([b, h, w]));
        let (desc, desc_conf) = match &raw_mlp {
            Some(m) => {
                let [_, n, ch] = m.dims();
                let per = ch / (c.patch * c.patch);
                let maps = tokens_to_pixels(m.clone(), v.grid, c.patch);
                let maps = maps.permute([0, 2, 3, 1]); // (B, H, W, per)
                debug_assert_eq!(n, v.grid.0 * v.grid.1);
                let raw = maps.clone().narrow(3, 0, c.desc_dim);
                let norm = raw.clone().square().sum_dim(3).sqrt();
                let desc = raw / norm;
                let dc = if c.desc_conf && per > c.desc_dim {
                    Some(maps.narrow(3, c.desc_dim, 1).exp().reshape([b, h, w]))
                } else {
                    conf.clone()
                };
                (Some(desc), dc)
            }
            None => (None, None),
        };
        let normal = raw_normal.as_ref().map(|r| {
            let n = r.clone().permute([0, 2, 3, 1]).clamp(-1.0, 1.0);
            // max(|n|, 1e-12), with a zero gradient (not NaN) at a zero vector.
            let len = n.clone().square().sum_dim(3).clamp_min(1e-24).sqrt();
            n / len
        });
        ViewPrediction { pts3d, conf, desc, desc_conf, normal, raw_pts, raw_normal, raw_mlp }
    }
}

/// `(a(), b())`, the two run side by side on rayon on the plain CPU device; elsewhere (GPU,
/// autodiff) one after the other. The two views of a pair are independent within each decoder
/// block and in the heads, and a core each with whole products beats every product split
/// across the cores (full-size pair at 512x384 on 2 cores: decoder 2.20 -> 2.00 s, each DPT
/// 1.48 -> 1.04-1.12 s). The encoder takes both images as one batch instead
/// ([`Dens3r::encode_images`]). The heads side by side hold both views' maps at once, which
/// [`Dpt::tail`]'s bands pay for.
fn both<A: Send, B: Send>(device: &Device, a: impl FnOnce() -> A + Send, b: impl FnOnce() -> B + Send) -> (A, B) {
    if crate::cpu::serves(device) {
        rayon::join(a, b)
    } else {
        (a(), b())
    }
}

/// The DPT head on the CPU kernels (its full-resolution tail in bands of rows) against burn's
/// own convolution and interpolation on the same weights.
#[cfg(test)]
mod tests {
    use super::Dpt;
    use crate::config::DptConfig;
    use crate::cpu::test_values;
    use burn::tensor::{Device, Tensor, TensorData};

    /// A grid of 9 x 3 tokens gives a 144 x 48 output: the CPU tail runs it as bands of 64, 64 and
    /// 16 rows, each with a row of the upsampled map above and below. A misplaced or missing
    /// neighbour row changes whole rows of the output; the reference (burn's ops, on the autodiff
    /// device, where the CPU kernels never serve) does not band.
    #[test]
    fn banded_tail_equals_burns_dpt() {
        let c = DptConfig {
            prefix: "t".into(),
            layer_dims: [8, 16, 24, 32],
            feature_dim: 16,
            head_dim: 8,
            last_dim: 12,
            out_channels: 4,
            up: [4, 2],
        };
        let (dim, h, w) = (20, 9, 3);
        let in_dims = [dim; 4];
        // Weights scaled by 1 / sqrt(fan-in) so activations stay of order 1 through the layers.
        let params: Vec<(String, Vec<f32>)> = Dpt::parameter_layout(&c, in_dims)
            .into_iter()
            .enumerate()
            .map(|(k, (name, shape))| {
                let n: usize = shape.iter().product();
                let scale = if shape.len() > 1 { 1.0 / ((n / shape[0]) as f32).sqrt() } else { 0.1 };
                (name, test_values(n, k as u64 + 1, scale * 3f32.sqrt()))
            })
            .collect();
        let maps: Vec<Vec<f32>> = (0..4).map(|i| test_values(dim * h * w, 100 + i, 1.0)).collect();
        let run = |device: &Device| -> Vec<f32> {
            let dpt = Dpt::from_flat(&c, in_dims, &|name: &str| {
                let v = &params.iter().find(|(n, _)| n == name).unwrap_or_else(|| panic!("{name} not in the layout")).1;
                Tensor::<1>::from_data(TensorData::new(v.clone(), [v.len()]), device)
            });
            let layers = std::array::from_fn(|i| {
                Tensor::<4>::from_data(TensorData::new(maps[i].clone(), [1, dim, h, w]), device)
            });
            let out = dpt.forward_maps(layers);
            assert_eq!(out.dims(), [1, 4, 16 * h, 16 * w]);
            out.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
        };
        let ours = run(&Device::flex());
        let reference = run(&Device::autodiff(Device::flex()));
        let scale = reference.iter().fold(0f32, |m, v| m.max(v.abs()));
        let worst = ours.iter().zip(&reference).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(scale > 1e-2, "a degenerate reference (largest |value| {scale})");
        assert!(worst <= 1e-5 * scale.max(1.0), "largest difference {worst} (reference's largest |value| {scale})");
    }
}
