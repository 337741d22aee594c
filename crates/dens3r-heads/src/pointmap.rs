//! The `pointmap` head: the network's own DPT ([`dens3r_backbone::model::Dpt`], DUSt3R's
//! `DPTOutputAdapter`) run on a head's trainable parameters, so a head can start from the
//! pointmap head of a Dens3R / DUSt3R / MASt3R checkpoint ([`crate::Head::from_pointmap`]) and be
//! fine-tuned on frozen features. Parameter names are the checkpoint's below the point head's
//! prefix (`dpt.act_postprocess.0.0.weight`, ...); the output is resized to the image.
//!
//! Depth: the head predicts the pointmap's three channels and returns `ln z` of the point
//! through the network's `exp` depth mode ([`exp_depth_mode`]), so a head started from a
//! checkpoint predicts that network's own depth. Segmentation: one channel per class from
//! the same trunk.

use crate::arch::{resize, HeadArch, HeadConfig, Task};
use crate::HeadsError;
use burn::tensor::Tensor;
use dens3r_backbone::config::DptConfig;
use dens3r_backbone::model::{exp_depth_mode, Dpt};
use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};

/// Upsampling factors of the transposed convs of layers 0 and 1.
const UP: [usize; 2] = [4, 2];
/// Smallest depth whose logarithm is taken (points behind the camera clamp to it).
const MIN_DEPTH: f32 = 1e-6;

/// The `pointmap` architecture (see the module docs). `HeadConfig::widths` holds the four
/// reassembly widths, then the head's two widths (`head.0` and `head.2` outputs);
/// `HeadConfig::width` is the feature width.
pub struct PointmapDpt;

/// The DPT widths of a config, its parameters named `dpt.*`.
fn dpt_config(c: &HeadConfig) -> DptConfig {
    let w = &c.widths;
    DptConfig {
        prefix: "dpt".into(),
        layer_dims: [w[0], w[1], w[2], w[3]],
        feature_dim: c.width,
        head_dim: w[4],
        last_dim: w[5],
        out_channels: match c.task {
            Task::Depth => 3, // x, y, z of the pointmap
            Task::Seg { .. } => c.task.channels(),
        },
        up: UP,
    }
}

/// Parameter names and shapes in storage order.
type Layout = Vec<(String, Vec<usize>)>;

/// The head's parameters: dens3r-backbone's DPT layout for its widths (names under `dpt.`),
/// computed once per configuration (it builds the DPT on zeros) and remembered.
fn layout(c: &HeadConfig) -> Layout {
    static LAYOUTS: OnceLock<Mutex<HashMap<String, Layout>>> = OnceLock::new();
    let d = dpt_config(c);
    let in_dims = [c.in_dims[0], c.in_dims[1], c.in_dims[2], c.in_dims[3]];
    let key = format!("{d:?} {in_dims:?}");
    let mut cache = LAYOUTS.get_or_init(Default::default).lock().unwrap_or_else(|e| e.into_inner());
    cache.entry(key).or_insert_with(|| Dpt::parameter_layout(&d, in_dims)).clone()
}

impl HeadArch for PointmapDpt {
    fn name(&self) -> &'static str {
        "pointmap"
    }
    fn check(&self, c: &HeadConfig) -> Result<(), HeadsError> {
        if c.layers.len() != 4 || c.in_dims.len() != 4 {
            return Err(HeadsError::invalid(format!("the pointmap head reads 4 layers, got {:?}", c.layers)));
        }
        if c.widths.len() != 6 || c.widths.contains(&0) || c.width == 0 {
            return Err(HeadsError::invalid(format!(
                "the pointmap head needs 6 nonzero widths (4 reassembly, 2 head) and a feature width, got {:?} and {}",
                c.widths, c.width
            )));
        }
        Ok(())
    }
    fn param_shapes(&self, c: &HeadConfig) -> Vec<(String, Vec<usize>)> {
        layout(c)
    }
    fn forward(&self, c: &HeadConfig, p: &[Tensor<1>], feats: &[Tensor<4>], out: (usize, usize)) -> Tensor<4> {
        let names = self.param_shapes(c);
        let by_name: HashMap<&str, &Tensor<1>> = names.iter().map(|(n, _)| n.as_str()).zip(p).collect();
        let get = |name: &str| by_name.get(name).map(|&t| t.clone()).expect("a pointmap head parameter");
        let in_dims = [c.in_dims[0], c.in_dims[1], c.in_dims[2], c.in_dims[3]];
        let dpt = Dpt::from_flat(&dpt_config(c), in_dims, &get);
        let x = dpt.forward_maps([feats[0].clone(), feats[1].clone(), feats[2].clone(), feats[3].clone()]);
        let x = match c.task {
            Task::Depth => exp_depth_mode(x, 1).narrow(1, 2, 1).clamp_min(MIN_DEPTH).log(),
            Task::Seg { .. } => x,
        };
        resize(x, out)
    }
}
