//! A head: a [`HeadConfig`] plus named parameters, its architecture found by name in the
//! registry ([`arch`]). Three are registered: `linear` and `dpt` ([`crate::arch`]) and
//! `pointmap` (the network's own DPT, which can start from a checkpoint's pointmap head:
//! [`Head::from_pointmap`]). A head saves as safetensors (parameters) + JSON (config).

use crate::HeadsError;
use burn::tensor::{Device, Tensor, TensorData};
use dens3r_backbone::{ModelConfig, Weights};
use rand::{Rng, SeedableRng};
use serde::Deserialize;
use std::path::Path;

pub use crate::arch::{resize, Dpt, HeadArch, HeadConfig, LinearProbe, Task};

/// The registered architectures.
pub static ARCHS: &[&dyn HeadArch] = &[&LinearProbe, &Dpt, &crate::pointmap::PointmapDpt];

/// Looks an architecture up by name.
pub fn arch(name: &str) -> Result<&'static dyn HeadArch, HeadsError> {
    ARCHS.iter().copied().find(|a| a.name() == name).ok_or_else(|| {
        let known: Vec<_> = ARCHS.iter().map(|a| a.name()).collect();
        HeadsError::invalid(format!("unknown head kind {name:?}; known: {}", known.join(", ")))
    })
}

/// A head: configuration and parameter values (host, f32).
#[derive(Debug, Clone)]
pub struct Head {
    /// Configuration.
    pub config: HeadConfig,
    /// Values in [`HeadArch::param_shapes`] order.
    pub values: Vec<Vec<f32>>,
}

impl Head {
    /// A freshly initialised head (uniform `+-1/sqrt(fan_in)` weights, zero biases, seeded).
    pub fn new(config: HeadConfig, seed: u64) -> Result<Self, HeadsError> {
        let a = arch(&config.kind)?;
        a.check(&config)?;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let values = a
            .param_shapes(&config)
            .iter()
            .map(|(name, s)| {
                let n: usize = s.iter().product();
                if name.ends_with(".bias") {
                    return vec![0.0; n];
                }
                let fan_in: usize = s[1..].iter().product::<usize>().max(1);
                let b = 1.0 / (fan_in as f32).sqrt();
                (0..n).map(|_| rng.gen_range(-b..b)).collect()
            })
            .collect();
        Ok(Self { config, values })
    }

    /// Names and shapes of the parameters.
    pub fn param_shapes(&self) -> Vec<(String, Vec<usize>)> {
        arch(&self.config.kind).map(|a| a.param_shapes(&self.config)).unwrap_or_default()
    }

    /// The parameters as flat tensors on `device` (autodiff devices track them).
    pub fn tensors(&self, device: &Device) -> Vec<Tensor<1>> {
        self.values.iter().map(|v| Tensor::from_data(TensorData::new(v.clone(), [v.len()]), device)).collect()
    }

    /// Runs the head on a feature batch with the given parameter tensors.
    pub fn forward_with(&self, params: &[Tensor<1>], feats: &[Tensor<4>], out: (usize, usize)) -> Tensor<4> {
        let a = arch(&self.config.kind).expect("registered kind");
        a.forward(&self.config, params, feats, out)
    }

    /// Inference on one image's features.
    pub fn predict(&self, features: &crate::FeatureMaps, out: (usize, usize), device: &Device) -> Tensor<4> {
        let feats: Vec<Tensor<4>> = self.config.layers.iter().map(|&l| features.tensor(l, device)).collect();
        self.forward_with(&self.tensors(device), &feats, out)
    }

    /// Writes `PATH.safetensors` and `PATH.json` (atomically; JSON last).
    pub fn save(&self, path: &Path) -> Result<(), HeadsError> {
        let named: Vec<(String, Vec<usize>, &[f32])> =
            self.param_shapes().into_iter().zip(&self.values).map(|((n, s), v)| (n, s, v.as_slice())).collect();
        dens3r_io::tensors::save(&path.with_extension("safetensors"), &named)?;
        let meta = serde_json::json!({ "format": FORMAT, "config": self.config });
        Ok(dens3r_io::tensors::save_json(&path.with_extension("json"), &meta)?)
    }

    /// Reads a head written by [`Head::save`] (either file's path, or the stem).
    pub fn load(path: &Path) -> Result<Self, HeadsError> {
        let json = path.with_extension("json");
        let text = std::fs::read_to_string(&json).map_err(|e| {
            HeadsError::file(&json, format!("cannot read the head ({e}); give the .json written by train-head"))
        })?;
        #[derive(Deserialize)]
        struct Meta {
            format: String,
            config: HeadConfig,
        }
        let meta: Meta = serde_json::from_str(&text)
            .map_err(|e| HeadsError::file(&json, format!("not a dens3r head ({e}); retrain or restore the file")))?;
        if meta.format != FORMAT {
            return Err(HeadsError::file(&json, format!("format {:?}, expected {FORMAT:?}", meta.format)));
        }
        let a = arch(&meta.config.kind).map_err(|e| HeadsError::file(&json, e.to_string()))?;
        a.check(&meta.config).map_err(|e| HeadsError::file(&json, e.to_string()))?;
        let shapes = a.param_shapes(&meta.config);
        let values = crate::io::load_tensors(&path.with_extension("safetensors"), &shapes)?;
        Ok(Self { config: meta.config, values })
    }
}

const FORMAT: &str = "dens3r-head/1";

impl Head {
    /// A `pointmap` head (`config.kind`) with the widths of the checkpoint's point head (Dens3R's
    /// `ptsmatch_local_head`, DUSt3R / MASt3R's `downstream_head1`), its parameters copied from
    /// it. For depth every parameter is copied (the last conv's x, y, z rows; the confidence row is
    /// dropped), so the head predicts the network's own depth; for segmentation everything but the
    /// last conv, which keeps its fresh initialisation from `seed`. The head must read the
    /// network's DPT hooks ([`crate::Dens3rBackbone`]'s default layers) for that to hold.
    pub fn from_pointmap(mut config: HeadConfig, weights: &Path, seed: u64) -> Result<Self, HeadsError> {
        if config.kind != "pointmap" {
            return Err(HeadsError::invalid(format!(
                "only a pointmap head starts from the pointmap head, not {:?}",
                config.kind
            )));
        }
        let w = Weights::from_safetensors(weights)?;
        // Head counts (1, 1) divide any width; they do not shape the DPT.
        let point = ModelConfig::from_weights(&w, Some((1, 1)))?.head1;
        let d = point.dpt().ok_or_else(|| {
            HeadsError::file(weights, "a linear-head checkpoint: a pointmap head starts only from a DPT point head")
        })?;
        config.width = d.feature_dim;
        config.widths = d.layer_dims.iter().copied().chain([d.head_dim, d.last_dim]).collect();
        let depth = config.task == Task::Depth;
        if depth && d.out_channels < 3 {
            return Err(HeadsError::file(weights, "the pointmap head has fewer than 3 output channels"));
        }
        let mut head = Head::new(config, seed)?;
        let device = burn::tensor::Device::flex();
        for ((name, shape), value) in head.param_shapes().into_iter().zip(head.values.iter_mut()) {
            let last = name.starts_with("dpt.head.4.");
            if last && !depth {
                continue;
            }
            let key = format!("{}.{name}", point.prefix);
            // The last conv: the checkpoint's rows x, y, z (and confidence), of which three are kept.
            let rows = if last { d.out_channels } else { shape[0] };
            let v = match shape.len() {
                1 => crate::features::to_vec(w.get(&key, [rows], &device)),
                _ => crate::features::to_vec(w.get(&key, [rows, shape[1], shape[2], shape[3]], &device)),
            };
            *value = v[..value.len()].to_vec();
        }
        w.finish().map_err(|e| {
            HeadsError::file(
                &e.path,
                format!("{}; the head's layers do not match this checkpoint's pointmap head", e.message),
            )
        })?;
        Ok(head)
    }
}
