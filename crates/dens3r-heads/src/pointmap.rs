//! The `pointmap` head: the network's own DPT layout (DUSt3R's `DPTOutputAdapter`, as in
//! [`dens3r_backbone::model`]), so a head can start from the pointmap head of a Dens3R /
//! DUSt3R / MASt3R checkpoint ([`init_from_pointmap`]) and be fine-tuned on frozen features.
//!
//! Layout: per layer a 1x1 projection to `widths[l]`, then a 4x / 2x transposed conv (layers 0
//! and 1), nothing (layer 2) or a stride-2 3x3 conv (layer 3); a bias-free 3x3 conv to the
//! feature width; four fusion blocks (residual conv units `x + conv(relu(conv(relu(x))))`, a
//! 1x1 conv, bilinear x2 with aligned corners); head `conv3x3 -> x2 -> conv3x3 -> ReLU ->
//! conv1x1`; bilinear resize to the image. Parameter names are the checkpoint's, below the
//! head's `dpt.` prefix.
//!
//! Depth: the head predicts the pointmap's three channels and returns `ln z` of the point
//! through the network's `exp` depth mode (`p = v / |v| * expm1(|v|)`), so a head initialised
//! from a checkpoint starts out predicting that network's own depth. Segmentation: one
//! channel per class from the same trunk.

use crate::head::{conv, resize, HeadArch, HeadConfig, Task};
use burn::tensor::module::{conv_transpose2d, interpolate};
use burn::tensor::ops::{ConvTransposeOptions, InterpolateMode, InterpolateOptions};
use burn::tensor::{activation::relu, Tensor};
use std::path::Path;

/// Upsampling factors of the transposed convs of layers 0 and 1.
const UP: [usize; 2] = [4, 2];
/// Smallest depth whose logarithm is taken (points behind the camera clamp to it).
const MIN_DEPTH: f32 = 1e-6;

/// The `pointmap` architecture (see the module docs). `HeadConfig::widths` holds the four
/// reassembly widths, then the head's two widths (`head.0` and `head.2` outputs);
/// `HeadConfig::width` is the feature width.
pub struct PointmapDpt;

/// Widths `([reassembly; 4], head, last)` of a config.
fn widths(c: &HeadConfig) -> ([usize; 4], usize, usize) {
    let w = &c.widths;
    ([w[0], w[1], w[2], w[3]], w[4], w[5])
}

/// Output channels: x, y, z of the pointmap for depth, one per class for segmentation.
fn out_channels(c: &HeadConfig) -> usize {
    match c.task {
        Task::Depth => 3,
        Task::Seg { .. } => c.task.channels(),
    }
}

fn up2(x: Tensor<4>) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    interpolate(
        x,
        InterpolateOptions::new(InterpolateMode::Bilinear).with_align_corners(true).with_output_size([2 * h, 2 * w]),
    )
}

impl HeadArch for PointmapDpt {
    fn name(&self) -> &'static str {
        "pointmap"
    }
    fn check(&self, c: &HeadConfig) -> Result<(), String> {
        if c.layers.len() != 4 || c.in_dims.len() != 4 {
            return Err(format!("the pointmap head reads 4 layers, got {:?}", c.layers));
        }
        if c.widths.len() != 6 || c.widths.contains(&0) || c.width == 0 {
            return Err(format!(
                "the pointmap head needs 6 nonzero widths (4 reassembly, 2 head) and a feature width, got {:?} and {}",
                c.widths, c.width
            ));
        }
        Ok(())
    }
    fn param_shapes(&self, c: &HeadConfig) -> Vec<(String, Vec<usize>)> {
        let (ld, hd, last) = widths(c);
        let f = c.width;
        let mut s: Vec<(String, Vec<usize>)> = Vec::new();
        let mut add = |n: String, shape: Vec<usize>, bias: bool| {
            let out = shape[0];
            s.push((format!("{n}.weight"), shape));
            if bias {
                s.push((format!("{n}.bias"), vec![out]));
            }
        };
        for l in 0..4 {
            add(format!("act_postprocess.{l}.0"), vec![ld[l], c.in_dims[l], 1, 1], true);
            match l {
                0 | 1 => add(format!("act_postprocess.{l}.1"), vec![ld[l], ld[l], UP[l], UP[l]], true),
                3 => add("act_postprocess.3.1".into(), vec![ld[3], ld[3], 3, 3], true),
                _ => {}
            }
        }
        for (l, &d) in ld.iter().enumerate() {
            add(format!("scratch.layer{}_rn", l + 1), vec![f, d, 3, 3], false);
        }
        for r in 1..=4 {
            // refinenet4 has no skip input, so its first residual unit is never used.
            for u in if r == 4 { 2..=2 } else { 1..=2 } {
                for k in 1..=2 {
                    add(format!("scratch.refinenet{r}.resConfUnit{u}.conv{k}"), vec![f, f, 3, 3], true);
                }
            }
            add(format!("scratch.refinenet{r}.out_conv"), vec![f, f, 1, 1], true);
        }
        add("head.0".into(), vec![hd, f, 3, 3], true);
        add("head.2".into(), vec![last, hd, 3, 3], true);
        add("head.4".into(), vec![out_channels(c), last, 1, 1], true);
        s
    }
    fn forward(&self, c: &HeadConfig, p: &[Tensor<1>], feats: &[Tensor<4>], out: (usize, usize)) -> Tensor<4> {
        let (ld, hd, last) = widths(c);
        let f = c.width;
        let mut i = 0;
        let mut next = || {
            i += 1;
            &p[i - 1]
        };
        let mut levels = Vec::with_capacity(4);
        for (l, x) in feats.iter().enumerate() {
            let (w, b) = (next(), next());
            let mut x = conv(x.clone(), w, Some(b), ld[l], 1, 1);
            if l < 2 {
                let (w, b) = (next(), next());
                let k = UP[l];
                let w = w.clone().reshape([ld[l], ld[l], k, k]);
                x = conv_transpose2d(
                    x,
                    w,
                    Some(b.clone()),
                    ConvTransposeOptions::new([k; 2], [0, 0], [0, 0], [1, 1], 1),
                );
            } else if l == 3 {
                let (w, b) = (next(), next());
                x = conv(x, w, Some(b), ld[3], 3, 2);
            }
            levels.push(x);
        }
        let levels: Vec<Tensor<4>> = levels.into_iter().map(|x| conv(x, next(), None, f, 3, 1)).collect();
        let rcu = |x: Tensor<4>, w: [&Tensor<1>; 4]| {
            let y = conv(relu(x.clone()), w[0], Some(w[1]), f, 3, 1);
            x + conv(relu(y), w[2], Some(w[3]), f, 3, 1)
        };
        let mut fusion = Vec::new();
        for r in 1..=4 {
            let rcu1 = (r != 4).then(|| [next().clone(), next().clone(), next().clone(), next().clone()]);
            let rcu2 = [next().clone(), next().clone(), next().clone(), next().clone()];
            let out_conv = (next().clone(), next().clone());
            fusion.push((rcu1, rcu2, out_conv));
        }
        // Coarse to fine: refinenet4 on layer 3, then 3, 2, 1 with the skip of layers 2, 1, 0.
        let mut path: Option<Tensor<4>> = None;
        for l in (0..4).rev() {
            let (rcu1, rcu2, (ow, ob)) = &fusion[l];
            let x = match (path.take(), rcu1) {
                (Some(prev), Some(r1)) => {
                    // An odd grid makes the stride-2 conv round up: crop back to the skip's size.
                    let [b, ch, h, w] = levels[l].dims();
                    prev.slice([0..b, 0..ch, 0..h, 0..w]) + rcu(levels[l].clone(), [&r1[0], &r1[1], &r1[2], &r1[3]])
                }
                _ => levels[l].clone(),
            };
            let x = rcu(x, [&rcu2[0], &rcu2[1], &rcu2[2], &rcu2[3]]);
            path = Some(up2(conv(x, ow, Some(ob), f, 1, 1)));
        }
        let x = path.expect("four levels");
        let (w0, b0, w2, b2, w4, b4) = (next(), next(), next(), next(), next(), next());
        let x = up2(conv(x, w0, Some(b0), hd, 3, 1));
        let x = conv(relu(conv(x, w2, Some(b2), last, 3, 1)), w4, Some(b4), out_channels(c), 1, 1);
        let x = match c.task {
            Task::Depth => log_depth(x),
            Task::Seg { .. } => x,
        };
        resize(x, out)
    }
}

/// `ln z` of the points `v / |v| * expm1(|v|)` of a raw `(B, 3, H, W)` map, as `(B, 1, H, W)`.
fn log_depth(v: Tensor<4>) -> Tensor<4> {
    let d = v.clone().square().sum_dim(1).sqrt();
    let z = v.narrow(1, 2, 1) / d.clone().clamp_min(1e-8) * d.exp().sub_scalar(1.0);
    z.clamp_min(MIN_DEPTH).log()
}

/// The checkpoint's pointmap head prefix (`ptsmatch_local_head.dpt` for Dens3R,
/// `downstream_head1.dpt` for DUSt3R / MASt3R).
fn pointmap_prefix(w: &dens3r_backbone::Weights) -> Option<&'static str> {
    ["ptsmatch_local_head.dpt", "downstream_head1.dpt"].into_iter().find(|p| w.contains(&format!("{p}.head.4.weight")))
}

/// The widths `(feature, [reassembly; 4] + [head; 2])` of a checkpoint's pointmap head, for a
/// [`HeadConfig`] of kind `pointmap`.
pub fn pointmap_widths(weights: &Path) -> Result<(usize, Vec<usize>), String> {
    let w = dens3r_backbone::Weights::from_safetensors(weights).map_err(|e| e.to_string())?;
    let p = pointmap_prefix(&w).ok_or_else(|| {
        format!("{}: no DPT pointmap head (ptsmatch_local_head / downstream_head1)", weights.display())
    })?;
    let dim = |k: &str, i: usize| {
        w.shape(&format!("{p}.{k}.weight"))
            .and_then(|s| s.get(i).copied())
            .ok_or_else(|| format!("{}: {p}.{k}.weight is missing", weights.display()))
    };
    let mut ws = (0..4).map(|l| dim(&format!("act_postprocess.{l}.0"), 0)).collect::<Result<Vec<_>, _>>()?;
    ws.push(dim("head.0", 0)?);
    ws.push(dim("head.2", 0)?);
    Ok((dim("head.0", 1)?, ws))
}

/// Sets a `pointmap` head's parameters to the checkpoint's pointmap head. For depth every
/// parameter is copied (the last conv's x, y, z rows; the confidence row is dropped), so the
/// head predicts the network's own depth; for segmentation everything but the last conv,
/// which keeps its fresh initialisation. The head must read the network's DPT hooks
/// ([`crate::Dens3rBackbone`]'s default layers) for that to hold.
pub fn init_from_pointmap(head: &mut crate::Head, weights: &Path) -> Result<(), String> {
    if head.config.kind != "pointmap" {
        return Err(format!("only a pointmap head starts from the pointmap head, not {:?}", head.config.kind));
    }
    let w = dens3r_backbone::Weights::from_safetensors(weights).map_err(|e| e.to_string())?;
    let p = pointmap_prefix(&w).ok_or_else(|| {
        format!("{}: no DPT pointmap head (ptsmatch_local_head / downstream_head1)", weights.display())
    })?;
    let device = burn::tensor::Device::flex();
    let depth = head.config.task == Task::Depth;
    if depth && w.shape(&format!("{p}.head.4.weight")).is_none_or(|s| s[0] < 3) {
        return Err(format!("{}: the pointmap head has fewer than 3 output channels", weights.display()));
    }
    let mut values = Vec::with_capacity(head.values.len());
    for ((name, shape), fresh) in head.param_shapes().into_iter().zip(&head.values) {
        let last = name.starts_with("head.4.");
        if last && !depth {
            values.push(fresh.clone());
            continue;
        }
        let key = format!("{p}.{name}");
        // The last conv: the checkpoint's rows x, y, z (and confidence), of which three are kept.
        let rows = if last { w.shape(&key).map_or(shape[0], |s| s[0]) } else { shape[0] };
        let v = match shape.len() {
            1 => crate::features::to_vec(w.get(&key, [rows], &device)),
            _ => crate::features::to_vec(w.get(&key, [rows, shape[1], shape[2], shape[3]], &device)),
        };
        values.push(v[..shape.iter().product::<usize>()].to_vec());
    }
    w.finish().map_err(|e| format!("{e}; the head's widths or layers do not match this checkpoint's pointmap head"))?;
    head.values = values;
    Ok(())
}
