//! What a head is: its configuration ([`HeadConfig`]: the feature layers it reads, its task and
//! widths), the [`HeadArch`] an architecture implements (its parameter shapes and its forward
//! pass on burn tensors, so autodiff gives the gradients), the layers architectures share, and
//! the two general ones: `linear` (the DINOv2-style linear probe: a per-token linear map of the
//! concatenated layers, upsampled bilinearly) and `dpt` (reassemble four layers at 4x, 2x, 1x
//! and 1/2x the token grid, fuse coarse to fine with residual conv units, a conv head,
//! bilinear upsampling).

use crate::HeadsError;
use burn::tensor::module::{conv2d, interpolate};
use burn::tensor::ops::{ConvOptions, InterpolateMode, InterpolateOptions};
use burn::tensor::{activation::relu, Tensor};
use serde::{Deserialize, Serialize};

/// What a head predicts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Task {
    /// Per-pixel class logits.
    Seg {
        /// Class names, index = class id.
        classes: Vec<String>,
    },
    /// Per-pixel log depth (one channel; depth = `exp(output)`).
    Depth,
}

impl Task {
    /// Output channels.
    pub fn channels(&self) -> usize {
        match self {
            Task::Seg { classes } => classes.len(),
            Task::Depth => 1,
        }
    }
}

/// A head's architecture and the features it reads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeadConfig {
    /// Registered architecture name (`linear`, `dpt`).
    pub kind: String,
    /// Task.
    pub task: Task,
    /// [`crate::Backbone::id`] of the backbone it was trained on.
    pub backbone: String,
    /// Pixels per token.
    pub patch: usize,
    /// Indices of the feature layers read (repeats allowed: a one-layer backbone feeds all
    /// four DPT branches).
    pub layers: Vec<usize>,
    /// Channels of each read layer.
    pub in_dims: Vec<usize>,
    /// Hidden width (DPT features; unused by the linear probe).
    pub width: usize,
    /// Further widths of architectures that have several (`pointmap`: the four reassembly
    /// widths, then the head's two); empty for the others.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub widths: Vec<usize>,
    /// Long side of the training inputs in pixels (0: not recorded); inference without the
    /// Dens3R network resizes images to it.
    #[serde(default)]
    pub size: u32,
}

/// An architecture: parameter shapes and the forward pass.
pub trait HeadArch: Sync {
    /// Registry name.
    fn name(&self) -> &'static str;
    /// Checks a configuration (layer count and so on).
    fn check(&self, config: &HeadConfig) -> Result<(), HeadsError>;
    /// Parameter names and shapes, in storage order.
    fn param_shapes(&self, config: &HeadConfig) -> Vec<(String, Vec<usize>)>;
    /// Output `(B, channels, H, W)` at image size `out` from the read layers `(B, C, h, w)`
    /// (in `config.layers` order), with `params` in [`HeadArch::param_shapes`] order.
    fn forward(&self, config: &HeadConfig, params: &[Tensor<1>], feats: &[Tensor<4>], out: (usize, usize))
        -> Tensor<4>;
}

/// Bilinear resize (`align_corners=False`) to `size`.
pub fn resize(x: Tensor<4>, size: (usize, usize)) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    if (h, w) == size {
        return x;
    }
    interpolate(x, InterpolateOptions::new(InterpolateMode::Bilinear).with_output_size([size.0, size.1]))
}

/// Convolution with a flat weight `(out, in, k, k)` and bias.
pub(crate) fn conv(
    x: Tensor<4>,
    w: &Tensor<1>,
    b: Option<&Tensor<1>>,
    out: usize,
    k: usize,
    stride: usize,
) -> Tensor<4> {
    let inp = x.dims()[1];
    let w = w.clone().reshape([out, inp, k, k]);
    conv2d(x, w, b.cloned(), ConvOptions::new([stride; 2], [k / 2; 2], [1, 1], 1))
}

/// The linear probe: logits = `W [f_l1; f_l2; ...] + b` per token, bilinearly upsampled.
pub struct LinearProbe;

impl HeadArch for LinearProbe {
    fn name(&self) -> &'static str {
        "linear"
    }
    fn check(&self, c: &HeadConfig) -> Result<(), HeadsError> {
        if c.layers.is_empty() || c.layers.len() != c.in_dims.len() {
            return Err(HeadsError::invalid("the linear probe reads at least one layer, with one width per layer"));
        }
        Ok(())
    }
    fn param_shapes(&self, c: &HeadConfig) -> Vec<(String, Vec<usize>)> {
        let k = c.task.channels();
        let d: usize = c.in_dims.iter().sum();
        vec![("linear.weight".into(), vec![k, d, 1, 1]), ("linear.bias".into(), vec![k])]
    }
    fn forward(&self, c: &HeadConfig, p: &[Tensor<1>], feats: &[Tensor<4>], out: (usize, usize)) -> Tensor<4> {
        let x = Tensor::cat(feats.to_vec(), 1);
        resize(conv(x, &p[0], Some(&p[1]), c.task.channels(), 1, 1), out)
    }
}

/// A DPT-style head on four layers (Ranftl et al. 2021, reduced): per layer a 1x1 projection to
/// `width`, resampling to 4x, 2x, 1x and 1/2x the token grid (bilinear up, a strided 3x3 conv
/// down), a 3x3 conv; fusion from the coarsest level with residual conv units
/// `x + conv3x3(relu(x))`; head conv3x3 -> ReLU -> conv1x1; bilinear upsampling to the image.
pub struct Dpt;

const DPT_SCALES: [f32; 4] = [4.0, 2.0, 1.0, 0.5];

impl HeadArch for Dpt {
    fn name(&self) -> &'static str {
        "dpt"
    }
    fn check(&self, c: &HeadConfig) -> Result<(), HeadsError> {
        if c.layers.len() != 4 || c.in_dims.len() != 4 {
            return Err(HeadsError::invalid(format!(
                "the DPT head reads 4 layers (repeats allowed), got {:?}",
                c.layers
            )));
        }
        if c.width < 2 {
            return Err(HeadsError::invalid("the DPT width must be at least 2"));
        }
        Ok(())
    }
    fn param_shapes(&self, c: &HeadConfig) -> Vec<(String, Vec<usize>)> {
        let w = c.width;
        let mut s: Vec<(String, Vec<usize>)> = Vec::new();
        for (l, &d) in c.in_dims.iter().enumerate() {
            s.push((format!("reassemble.{l}.proj.weight"), vec![w, d, 1, 1]));
            s.push((format!("reassemble.{l}.proj.bias"), vec![w]));
            if l == 3 {
                s.push(("reassemble.3.down.weight".into(), vec![w, w, 3, 3]));
                s.push(("reassemble.3.down.bias".into(), vec![w]));
            }
            s.push((format!("reassemble.{l}.rn.weight"), vec![w, w, 3, 3]));
        }
        for l in 0..4 {
            s.push((format!("fusion.{l}.rcu1.weight"), vec![w, w, 3, 3]));
            s.push((format!("fusion.{l}.rcu1.bias"), vec![w]));
            s.push((format!("fusion.{l}.rcu2.weight"), vec![w, w, 3, 3]));
            s.push((format!("fusion.{l}.rcu2.bias"), vec![w]));
        }
        let h = (w / 2).max(1);
        s.push(("head.conv.weight".into(), vec![h, w, 3, 3]));
        s.push(("head.conv.bias".into(), vec![h]));
        s.push(("head.out.weight".into(), vec![c.task.channels(), h, 1, 1]));
        s.push(("head.out.bias".into(), vec![c.task.channels()]));
        s
    }
    fn forward(&self, c: &HeadConfig, p: &[Tensor<1>], feats: &[Tensor<4>], out: (usize, usize)) -> Tensor<4> {
        let w = c.width;
        let mut i = 0;
        let mut next = || {
            i += 1;
            &p[i - 1]
        };
        let [_, _, gh, gw] = feats[0].dims();
        let mut levels = Vec::with_capacity(4);
        for (l, f) in feats.iter().enumerate() {
            let (pw, pb) = (next(), next());
            let mut x = conv(f.clone(), pw, Some(pb), w, 1, 1);
            if l == 3 {
                let (dw, db) = (next(), next());
                x = conv(x, dw, Some(db), w, 3, 2);
            } else {
                let s = DPT_SCALES[l];
                x = resize(x, ((gh as f32 * s) as usize, (gw as f32 * s) as usize));
            }
            levels.push(conv(x, next(), None, w, 3, 1));
        }
        let rcu = |x: Tensor<4>, wt: &Tensor<1>, b: &Tensor<1>| x.clone() + conv(relu(x), wt, Some(b), w, 3, 1);
        let mut fusion = Vec::with_capacity(4);
        for _ in 0..4 {
            fusion.push((next().clone(), next().clone(), next().clone(), next().clone()));
        }
        // Coarse to fine: level 3 (1/2x) up to level 2's size, and so on to level 0 (4x).
        let mut path: Option<Tensor<4>> = None;
        for l in (0..4).rev() {
            let (w1, b1, w2, b2) = &fusion[l];
            let x = levels[l].clone();
            let [_, _, h, wd] = x.dims();
            let x = match path.take() {
                Some(prev) => resize(prev, (h, wd)) + rcu(x, w1, b1),
                None => rcu(x, w1, b1),
            };
            path = Some(rcu(x, w2, b2));
        }
        let x = path.expect("four levels");
        let (hw, hb, ow, ob) = (next(), next(), next(), next());
        let x = relu(conv(x, hw, Some(hb), (w / 2).max(1), 3, 1));
        resize(conv(x, ow, Some(ob), c.task.channels(), 1, 1), out)
    }
}
