//! The SDF field: a multiresolution hash-grid encoding (Instant-NGP) of the normalised position,
//! concatenated with the position itself, into a small ReLU MLP whose first output is the signed
//! distance and the next three (optional) a colour. Geometric initialisation (SAL / IGR): the
//! grid features start near zero with zero input weights, and the MLP starts as the distance to
//! a sphere, so training begins from a valid SDF.
//!
//! The encoding's corner indices and trilinear weights are computed on the host (they depend on
//! the points only), so the differentiable part is one `select` from the table plus the MLP, and
//! gradients with respect to the position are taken numerically (Neuralangelo) by evaluating
//! offset points.

use crate::OptionError;
use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Field architecture. Positions are in the normalised cube `[-1, 1]^3`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldConfig {
    /// Hash-grid levels.
    pub levels: usize,
    /// Features per level.
    pub features: usize,
    /// log2 of the table size per level.
    pub log2_table: u32,
    /// Coarsest grid resolution (cells per axis over the cube).
    pub base_res: u32,
    /// Finest grid resolution.
    pub max_res: u32,
    /// Hidden width of the MLP.
    pub hidden: usize,
    /// Hidden layers.
    pub layers: usize,
    /// Predict a colour as well.
    pub color: bool,
    /// Radius of the initial sphere.
    pub init_radius: f32,
}

impl Default for FieldConfig {
    fn default() -> Self {
        Self {
            levels: 12,
            features: 2,
            log2_table: 17,
            base_res: 16,
            max_res: 512,
            hidden: 64,
            layers: 2,
            color: true,
            init_radius: 0.6,
        }
    }
}

impl FieldConfig {
    /// Grid resolution of level `l` (geometric progression from `base_res` to `max_res`).
    pub fn level_res(&self, l: usize) -> u32 {
        if self.levels <= 1 {
            return self.base_res;
        }
        let b = ((self.max_res as f64).ln() - (self.base_res as f64).ln()) / (self.levels - 1) as f64;
        ((self.base_res as f64) * (b * l as f64).exp()).round() as u32
    }

    /// Entries per level table.
    pub fn table_size(&self) -> usize {
        1 << self.log2_table
    }

    /// Width of the MLP input: position (3) plus the grid features.
    pub fn input_width(&self) -> usize {
        3 + self.levels * self.features
    }

    /// MLP outputs: SDF (+ RGB).
    pub fn outputs(&self) -> usize {
        if self.color {
            4
        } else {
            1
        }
    }

    /// Checks the numbers are usable.
    pub fn check(&self) -> Result<(), OptionError> {
        if self.levels == 0 || self.levels > 32 {
            return Err(OptionError(format!("levels {} must be in 1..=32", self.levels)));
        }
        if self.features == 0 || self.features > 8 {
            return Err(OptionError(format!("features per level {} must be in 1..=8", self.features)));
        }
        if !(8..=24).contains(&self.log2_table) {
            return Err(OptionError(format!("log2 table size {} must be in 8..=24", self.log2_table)));
        }
        if self.base_res < 2 || self.max_res < self.base_res || self.max_res > 1 << 16 {
            return Err(OptionError(format!(
                "resolutions {}..{} must satisfy 2 <= base <= max <= 65536",
                self.base_res, self.max_res
            )));
        }
        if self.hidden == 0 || self.hidden > 1024 || self.layers == 0 || self.layers > 8 {
            return Err(OptionError(format!(
                "MLP {} x {} must have 1..=8 layers of width 1..=1024",
                self.layers, self.hidden
            )));
        }
        if !(self.init_radius > 0.0 && self.init_radius < 1.0) {
            return Err(OptionError(format!("initial sphere radius {} must be in (0, 1)", self.init_radius)));
        }
        Ok(())
    }
}

/// Host-side encoding of a batch of points: per point, level and cube corner, the table row
/// and the trilinear weight.
#[derive(Debug, Clone)]
pub struct Encoded {
    /// Points.
    pub n: usize,
    /// Table rows, `n * levels * 8`.
    pub rows: Vec<u32>,
    /// Trilinear weights, same layout.
    pub weights: Vec<f32>,
    /// The points themselves, `n * 3`.
    pub pos: Vec<f32>,
}

/// Spatial hash of a grid vertex (Instant-NGP's primes).
#[inline]
fn hash(x: u32, y: u32, z: u32) -> u32 {
    x ^ y.wrapping_mul(2_654_435_761) ^ z.wrapping_mul(805_459_861)
}

/// Computes table rows and weights for `points` (normalised coordinates; clamped to the cube).
pub fn encode(cfg: &FieldConfig, points: &[Vec3]) -> Encoded {
    let l = cfg.levels;
    let t = cfg.table_size();
    let res: Vec<u32> = (0..l).map(|i| cfg.level_res(i)).collect();
    let mut rows = vec![0u32; points.len() * l * 8];
    let mut weights = vec![0f32; points.len() * l * 8];
    rows.par_chunks_mut(l * 8).zip(weights.par_chunks_mut(l * 8)).zip(points.par_iter()).for_each(|((r, w), p)| {
        let u = ((*p + 1.0) * 0.5).clamp(Vec3::ZERO, Vec3::ONE);
        for (lv, &n) in res.iter().enumerate() {
            let g = u * n as f32;
            let c = g.floor().min(Vec3::splat((n - 1) as f32));
            let f = g - c;
            let (cx, cy, cz) = (c.x as u32, c.y as u32, c.z as u32);
            let side = n as u64 + 1;
            let dense = side * side * side <= t as u64;
            for k in 0..8u32 {
                let (dx, dy, dz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
                let (x, y, z) = (cx + dx, cy + dy, cz + dz);
                let idx = if dense {
                    (x as u64 + side * (y as u64 + side * z as u64)) as usize
                } else {
                    hash(x, y, z) as usize & (t - 1)
                };
                let wx = if dx == 1 { f.x } else { 1.0 - f.x };
                let wy = if dy == 1 { f.y } else { 1.0 - f.y };
                let wz = if dz == 1 { f.z } else { 1.0 - f.z };
                r[lv * 8 + k as usize] = (lv * t + idx) as u32;
                w[lv * 8 + k as usize] = wx * wy * wz;
            }
        }
    });
    let pos = points.iter().flat_map(|p| p.to_array()).collect();
    Encoded { n: points.len(), rows, weights, pos }
}

/// The MLP's trainable tensors, all 2-D so one optimiser loop serves them: per layer a weight
/// `(in, out)` and a bias `(1, out)`, and last NeuS's sharpness parameter `(1, 1)`
/// (`s = exp(10 v)`). The feature table `(levels * table, features)` lives on the host: its
/// lookup and the scatter of its gradient are [`grid_features`] / [`grid_backward`] (one pass
/// each, where burn's `select` and its backward made several over the whole table).
#[derive(Debug, Clone)]
pub struct Params {
    /// The tensors, in the order above.
    pub tensors: Vec<Tensor<2>>,
}

/// Names of the table and the tensors in [`Params`] (checkpoint keys).
pub fn param_names(cfg: &FieldConfig) -> Vec<String> {
    let mut names = vec!["grid.table".to_string()];
    for i in 0..=cfg.layers {
        names.push(format!("mlp.{i}.weight"));
        names.push(format!("mlp.{i}.bias"));
    }
    names.push("neus.variance".into());
    names
}

/// Shapes of the table and the tensors in [`Params`].
pub fn param_shapes(cfg: &FieldConfig) -> Vec<[usize; 2]> {
    let mut shapes = vec![[cfg.levels * cfg.table_size(), cfg.features]];
    let mut fan_in = cfg.input_width();
    for i in 0..=cfg.layers {
        let fan_out = if i == cfg.layers { cfg.outputs() } else { cfg.hidden };
        shapes.push([fan_in, fan_out]);
        shapes.push([1, fan_out]);
        fan_in = cfg.hidden;
    }
    shapes.push([1, 1]);
    shapes
}

/// Initial values (host), shapes as in [`Params`]: geometric initialisation.
pub fn init_values(cfg: &FieldConfig, seed: u64) -> Vec<(Vec<f32>, [usize; 2])> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut gauss = |sd: f32| -> f32 {
        let (u1, u2): (f32, f32) = (rng.gen_range(1e-7..1.0), rng.gen());
        sd * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    };
    let shapes = param_shapes(cfg);
    let mut out = Vec::with_capacity(shapes.len());
    let [rows, features] = shapes[0];
    let mut r2 = ChaCha8Rng::seed_from_u64(seed ^ 0x9e37_79b9);
    out.push(((0..rows * features).map(|_| r2.gen_range(-1e-4..1e-4)).collect(), shapes[0]));
    for i in 0..=cfg.layers {
        let last = i == cfg.layers;
        let [fan_in, fan_out] = shapes[1 + 2 * i];
        let mut w = vec![0f32; fan_in * fan_out];
        for r in 0..fan_in {
            for c in 0..fan_out {
                // Grid features enter with zero weight at first; the position carries the sphere.
                let v = if i == 0 && r >= 3 {
                    0.0
                } else if last && c == 0 {
                    (std::f32::consts::PI / fan_in as f32).sqrt() + gauss(1e-4)
                } else if last {
                    gauss(1e-2)
                } else {
                    gauss((2.0 / fan_out as f32).sqrt())
                };
                w[r * fan_out + c] = v;
            }
        }
        let mut b = vec![0f32; fan_out];
        if last {
            b[0] = -cfg.init_radius;
        }
        out.push((w, shapes[1 + 2 * i]));
        out.push((b, shapes[2 + 2 * i]));
    }
    out.push((vec![0.3], shapes[shapes.len() - 1]));
    out
}

/// Grid features of encoded points, `n * levels * features` (level-major per point), each
/// level scaled by `level_mask`.
pub fn grid_features(cfg: &FieldConfig, table: &[f32], enc: &Encoded, level_mask: &[f32]) -> Vec<f32> {
    let (l, f) = (cfg.levels, cfg.features);
    let mut out = vec![0f32; enc.n * l * f];
    out.par_chunks_mut(l * f).enumerate().for_each(|(p, o)| {
        for lv in 0..l {
            let m = level_mask[lv];
            if m == 0.0 {
                continue;
            }
            for k in 0..8 {
                let e = (p * l + lv) * 8 + k;
                let (row, w) = (enc.rows[e] as usize * f, enc.weights[e] * m);
                for c in 0..f {
                    o[lv * f + c] += w * table[row + c];
                }
            }
        }
    });
    out
}

/// Adds the table gradient of `d loss / d features` (layout of [`grid_features`]) to `grad`.
/// Levels own disjoint table ranges, so they accumulate in parallel.
pub fn grid_backward(cfg: &FieldConfig, enc: &Encoded, level_mask: &[f32], dfeat: &[f32], grad: &mut [f32]) {
    let (l, f, t) = (cfg.levels, cfg.features, cfg.table_size());
    grad.par_chunks_mut(t * f).enumerate().for_each(|(lv, g)| {
        let m = level_mask[lv];
        if m == 0.0 {
            return;
        }
        let base = lv * t;
        for p in 0..enc.n {
            for k in 0..8 {
                let e = (p * l + lv) * 8 + k;
                let (row, w) = ((enc.rows[e] as usize - base) * f, enc.weights[e] * m);
                for c in 0..f {
                    g[row + c] += w * dfeat[(p * l + lv) * f + c];
                }
            }
        }
    });
}

/// A field evaluation: the MLP output and the grid-feature leaf its gradient flows into.
pub struct Evaluated {
    /// `(n, outputs)`: SDF, then raw colour.
    pub out: Tensor<2>,
    /// The grid features fed to the MLP, `(n, levels * features)`.
    pub features: Tensor<2>,
    /// The encoding, kept for the table's backward pass.
    pub enc: Encoded,
}

impl Params {
    /// Uploads host values to `device` (the table stays on the host in `table`), marked as
    /// requiring gradients when `train`.
    pub fn from_values(values: &[(Vec<f32>, [usize; 2])], device: &Device, train: bool) -> (Vec<f32>, Self) {
        let tensors = values[1..]
            .iter()
            .map(|(v, s)| {
                let t = Tensor::<2>::from_data(TensorData::new(v.clone(), *s), device);
                if train {
                    t.require_grad()
                } else {
                    t
                }
            })
            .collect();
        (values[0].0.clone(), Self { tensors })
    }

    /// Host copies of the MLP and sharpness values with their shapes.
    pub fn values(&self) -> Vec<(Vec<f32>, [usize; 2])> {
        self.tensors.iter().map(|t| (to_vec(t.clone()), t.dims())).collect()
    }

    /// NeuS sharpness `s = exp(10 v)`, shape `(1, 1)`.
    pub fn sharpness(&self) -> Tensor<2> {
        self.tensors.last().expect("params").clone().mul_scalar(10.0).exp()
    }

    /// Evaluates the field on encoded points. `level_mask` scales each level's features
    /// (coarse-to-fine: 0 for levels not yet active). With `train` the features are a leaf that
    /// receives its gradient in the backward pass.
    pub fn forward(
        &self,
        cfg: &FieldConfig,
        table: &[f32],
        enc: Encoded,
        level_mask: &[f32],
        train: bool,
    ) -> Evaluated {
        let device = self.tensors[0].device();
        let n = enc.n;
        let lf = cfg.levels * cfg.features;
        let feats = grid_features(cfg, table, &enc, level_mask);
        let mut features = Tensor::<2>::from_data(TensorData::new(feats, [n, lf]), &device);
        if train {
            features = features.require_grad();
        }
        let pos = Tensor::<2>::from_data(TensorData::new(enc.pos.clone(), [n, 3]), &device);
        let out = self.mlp(cfg, pos, features.clone());
        Evaluated { out, features, enc }
    }

    /// The MLP on positions `(n, 3)` and grid features `(n, levels * features)`.
    pub fn mlp(&self, cfg: &FieldConfig, pos: Tensor<2>, features: Tensor<2>) -> Tensor<2> {
        let mut h = Tensor::cat(vec![pos, features], 1);
        for i in 0..=cfg.layers {
            let (wt, b) = (&self.tensors[2 * i], &self.tensors[2 * i + 1]);
            h = h.matmul(wt.clone()) + b.clone();
            if i < cfg.layers {
                h = burn::tensor::activation::relu(h);
            }
        }
        h
    }
}

/// A tensor's values on the host.
pub fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor")
}
