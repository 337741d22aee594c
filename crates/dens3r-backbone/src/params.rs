//! The network's parameters as named host buffers under the official checkpoint names: what
//! a training run updates and saves. [`Params::model`] builds the one [`Dens3r`] forward from
//! them, tracked by autodiff on an autodiff device.

use crate::config::ModelConfig;
use crate::dinov2::Dinov2;
use crate::model::Dens3r;
use crate::weights::{is_layer_norm, Weights, WeightsError};
use burn::tensor::{Device, Tensor, TensorData};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

/// Named parameters of one network configuration, in [`Dens3r::parameter_layout`] order.
#[derive(Debug, Clone)]
pub struct Params {
    /// The architecture these parameters fill.
    pub config: ModelConfig,
    /// Checkpoint names.
    pub names: Vec<String>,
    /// Shapes (PyTorch layout).
    pub shapes: Vec<Vec<usize>>,
    /// Values, row-major.
    pub values: Vec<Vec<f32>>,
    /// The frozen DINOv2 of a network whose encoder is one (not a parameter: never trained or
    /// saved); [`Params::model`] attaches it.
    pub dinov2: Option<Arc<Dinov2>>,
}

/// Which parameters train; the others stay as loaded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Freeze {
    /// Everything trains.
    None,
    /// Patch embedding, encoder blocks and `enc_norm` are frozen.
    Encoder,
    /// The encoder is frozen except its last `k` blocks (and `enc_norm`).
    EncoderExceptLast(usize),
    /// Encoder and decoder are frozen: only the heads train.
    Backbone,
    /// Only the matching descriptors' MLPs (`*.head_local_features.*`) train: a matching
    /// stage that leaves depth, confidence and normals exactly as they were.
    Descriptors,
}

impl Freeze {
    /// Parses `none`, `encoder`, `encoder-but-N` (last N blocks train), `backbone` /
    /// `heads-only` or `descriptors`.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "none" => Self::None,
            "encoder" => Self::Encoder,
            "backbone" | "heads-only" | "encoder-decoder" => Self::Backbone,
            "descriptors" | "desc-only" => Self::Descriptors,
            _ => Self::EncoderExceptLast(s.strip_prefix("encoder-but-")?.parse().ok()?),
        })
    }

    /// Whether parameter `name` trains in a network of `enc_depth` encoder blocks.
    pub fn trains(self, name: &str, enc_depth: usize) -> bool {
        let top = name.split('.').next().unwrap_or("");
        let encoder = matches!(top, "patch_embed" | "enc_blocks" | "enc_norm" | "mask_token");
        let decoder = matches!(top, "decoder_embed" | "dec_blocks" | "dec_blocks2" | "dec_norm");
        match self {
            Self::None => true,
            Self::Encoder => !encoder,
            Self::Backbone => !encoder && !decoder,
            Self::Descriptors => name.split('.').nth(1) == Some("head_local_features"),
            Self::EncoderExceptLast(k) => {
                if top == "enc_blocks" {
                    let i: usize = name.split('.').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
                    i + k >= enc_depth
                } else {
                    !(top == "patch_embed" || top == "mask_token") || k >= enc_depth
                }
            }
        }
    }
}

impl Params {
    /// Fresh parameters, initialised as the official code does: LayerNorms at one / zero;
    /// linear layers from a truncated normal of std 0.02 with zero biases (CroCo's
    /// `_init_weights`); the patch embedding Xavier-uniform (CroCo's `PatchEmbed`); the DPT's
    /// convolutions with PyTorch's default `U(-1/sqrt(fan_in), 1/sqrt(fan_in))` for weights and
    /// biases. Seeded.
    pub fn init(config: &ModelConfig, seed: u64) -> Self {
        let layout = Dens3r::parameter_layout(config);
        let shape_of: HashMap<&str, &[usize]> = layout.iter().map(|(n, s)| (n.as_str(), s.as_slice())).collect();
        let mut rng = SplitMix(seed ^ 0xd1b5_4a32_d192_ed03);
        let mut values = Vec::with_capacity(layout.len());
        for (name, shape) in &layout {
            let n: usize = shape.iter().product();
            let norm = is_layer_norm(name);
            // The weight this tensor belongs to (itself, or the weight of a bias).
            let weight = name.strip_suffix(".bias").map(|p| format!("{p}.weight")).unwrap_or_else(|| name.clone());
            let wshape = shape_of.get(weight.as_str()).copied().unwrap_or(shape);
            let uniform = |rng: &mut SplitMix, bound: f64| -> Vec<f32> {
                (0..n).map(|_| ((2.0 * rng.uniform() - 1.0) * bound) as f32).collect()
            };
            values.push(if norm {
                vec![if name.ends_with(".weight") { 1.0 } else { 0.0 }; n]
            } else if crate::config::is_encoder_tap(name) {
                // Zero: a network with taps starts as the one without.
                vec![0.0; n]
            } else if wshape.len() == 4 {
                // Conv2d (out, in, k, k) and ConvTranspose2d (in, out, k, k): PyTorch takes
                // fan_in from dimension 1 in both.
                let fan_in = wshape[1] * wshape[2] * wshape[3];
                if name.starts_with("patch_embed.") && name.ends_with(".weight") {
                    uniform(&mut rng, (6.0 / (fan_in + wshape[0]) as f64).sqrt())
                } else if name.contains(".dpt.head.4.") {
                    // Each DPT's output layer a tenth of that, so the raw outputs start small
                    // (inside the normals' [-1, 1] clamp, exp() finite), as the parity
                    // fixtures' generator does.
                    uniform(&mut rng, 0.1 / (fan_in as f64).sqrt())
                } else {
                    uniform(&mut rng, 1.0 / (fan_in as f64).sqrt())
                }
            } else if name.ends_with(".bias") {
                vec![0.0; n]
            } else {
                (0..n).map(|_| rng.trunc_normal() * 0.02).collect()
            });
        }
        let (names, shapes) = layout.into_iter().unzip();
        Self { config: config.clone(), names, shapes, values, dinov2: None }
    }

    /// Reads every parameter of `config` from a checkpoint (missing or mis-shaped keys are
    /// one error naming the file and each key).
    pub fn from_weights(w: &Weights, config: &ModelConfig) -> Result<Self, WeightsError> {
        let layout = Dens3r::parameter_layout(config);
        let values: Vec<Vec<f32>> =
            layout.iter().map(|(n, s)| w.values(n, s).unwrap_or_else(|| vec![0.0; s.iter().product()])).collect();
        w.finish()?;
        let (names, shapes) = layout.into_iter().unzip();
        Ok(Self { config: config.clone(), names, shapes, values, dinov2: None })
    }

    /// These parameters with the encoder taps `taps` ([`ModelConfig::enc_taps`]): the
    /// parameters present keep their values, the taps' projections new to them start at zero,
    /// so the network computes exactly what it did. An error unless the encoder is a DINOv2,
    /// with at most 4 taps, increasing, each a block of it.
    pub fn with_taps(self, taps: &[usize]) -> Result<Self, String> {
        let c = &self.config;
        if c.encoder != crate::config::EncoderKind::Dinov2 {
            return Err("encoder taps need a DINOv2 encoder (`encoder = \"dinov2\"`)".into());
        }
        // Increasing, as the weights' keys are read back (block order gives the hooks).
        let increasing = taps.windows(2).all(|p| p[0] < p[1]);
        if !increasing || taps.len() > 4 || taps.iter().any(|&b| b == 0 || b > c.enc_depth) {
            return Err(format!(
                "encoder taps {taps:?}: at most 4 increasing blocks of 1..={} (the DPT reads 4 layers, in block order)",
                c.enc_depth
            ));
        }
        let config = ModelConfig { enc_taps: taps.to_vec(), ..c.clone() };
        let layout = Dens3r::parameter_layout(&config);
        let index = self.index();
        let values = layout
            .iter()
            .map(|(n, s)| match index.get(n.as_str()) {
                Some(&i) if self.shapes[i] == *s => Ok(self.values[i].clone()),
                Some(_) => Err(format!("parameter '{n}' has another shape in the network with taps {taps:?}")),
                None => Ok(vec![0.0; s.iter().product()]),
            })
            .collect::<Result<Vec<_>, _>>()?;
        let (names, shapes) = layout.into_iter().unzip();
        Ok(Self { config, names, shapes, values, dinov2: self.dinov2 })
    }

    /// Number of scalar parameters.
    pub fn count(&self) -> usize {
        self.values.iter().map(Vec::len).sum()
    }

    /// Index of each name.
    pub fn index(&self) -> HashMap<&str, usize> {
        self.names.iter().enumerate().map(|(i, n)| (n.as_str(), i)).collect()
    }

    /// Flat tensors on `device`, those with `grad[i]` marked to require gradients.
    pub fn tensors(&self, device: &Device, grad: &[bool]) -> Vec<Tensor<1>> {
        self.values
            .iter()
            .zip(grad)
            .map(|(v, &g)| {
                let t = Tensor::<1>::from_data(TensorData::new(v.clone(), [v.len()]), device);
                if g {
                    t.require_grad()
                } else {
                    t
                }
            })
            .collect()
    }

    /// The network on `tensors` (from [`Params::tensors`]): the inference model's layers and
    /// forward; on an autodiff device its outputs carry gradients to those tensors.
    pub fn model(&self, tensors: &[Tensor<1>], device: &Device) -> Dens3r {
        let index = self.index();
        let get = |name: &str| {
            let i = *index.get(name).unwrap_or_else(|| panic!("parameter layout has no '{name}'"));
            tensors[i].clone()
        };
        let mut model = Dens3r::from_flat(self.config.clone(), device, &get);
        if let Some(d) = &self.dinov2 {
            // Checked when the encoder was set (`Params::with_dinov2`).
            model.attach_dinov2(d.clone()).expect("DINOv2 checked by with_dinov2");
        }
        model
    }

    /// These parameters with the frozen DINOv2 encoder their configuration needs.
    pub fn with_dinov2(mut self, dinov2: Arc<Dinov2>) -> Result<Self, WeightsError> {
        crate::model::dinov2_fits(&self.config, &dinov2)?;
        self.dinov2 = Some(dinov2);
        Ok(self)
    }

    /// Writes the parameters as a safetensors checkpoint with the official key names
    /// (atomically), readable by `Weights::from_safetensors` and every command taking
    /// `--weights`.
    pub fn save(&self, path: &Path) -> Result<(), WeightsError> {
        self.save_as(path, Precision::F32)
    }

    /// [`Params::save`] at `precision`: half precision halves the file for shipping weights
    /// (training checkpoints stay f32 so a resumed run is exact).
    pub fn save_as(&self, path: &Path, precision: Precision) -> Result<(), WeightsError> {
        let dtype = match precision {
            Precision::F32 => safetensors::Dtype::F32,
            Precision::F16 => safetensors::Dtype::F16,
            Precision::BF16 => safetensors::Dtype::BF16,
        };
        let err = |m: String| WeightsError { path: path.to_path_buf(), message: m };
        let named: Vec<(String, Vec<usize>, &[f32])> = self
            .names
            .iter()
            .zip(&self.shapes)
            .zip(&self.values)
            .map(|((n, s), v)| (n.clone(), s.clone(), v.as_slice()))
            .collect();
        let data = dens3r_io::tensors::serialize(&named, dtype).map_err(|e| err(e.to_string()))?;
        dens3r_io::write_atomic(path, |w| std::io::Write::write_all(w, &data)).map_err(|e| err(e.to_string()))
    }
}

/// A float precision: how parameters are stored in a written checkpoint, or what the network
/// computes in ([`crate::device::network_device_at`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Precision {
    #[default]
    /// 32-bit float (exact).
    F32,
    /// IEEE half (10-bit mantissa, range +-65504).
    F16,
    /// bfloat16 (8-bit mantissa, f32's range).
    BF16,
}

impl Precision {
    /// `f32`, `f16` or `bf16`.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "f32" => Some(Self::F32),
            "f16" => Some(Self::F16),
            "bf16" => Some(Self::BF16),
            _ => None,
        }
    }

    /// Burn's float dtype for it.
    pub fn dtype(self) -> burn::tensor::FloatDType {
        match self {
            Self::F32 => burn::tensor::FloatDType::F32,
            Self::F16 => burn::tensor::FloatDType::F16,
            Self::BF16 => burn::tensor::FloatDType::BF16,
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::F16 => "f16",
            Self::BF16 => "bf16",
        })
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::parse(s).ok_or_else(|| format!("unknown precision '{s}': use f32, f16 or bf16"))
    }
}

/// SplitMix64 with Box-Muller normals (seeded, platform-independent).
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        ((self.next() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    /// A standard normal truncated to [-2, 2] (by rejection).
    fn trunc_normal(&mut self) -> f32 {
        loop {
            let (u1, u2) = (self.uniform(), self.uniform());
            let z = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
            if z.abs() <= 2.0 {
                return z as f32;
            }
        }
    }
}
