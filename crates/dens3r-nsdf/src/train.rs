//! Training: batches of rays from a few frames, NeuS rendering of depth (and colour), normals
//! and eikonal terms from numerical gradients, Adam with warm-up and cosine decay, coarse-to-fine
//! activation of the grid levels, checkpoints that resume to the same numbers.

use crate::checkpoint::{self, Checkpoint};
use crate::data::{ray_cube, TrainData};
use crate::field::{self, encode, Evaluated, FieldConfig, Params};
pub use crate::options::{DepthMode, TrainOptions};
use crate::render;
use crate::NsdfError;
use dens3r_optim::{AdamW, At, Decay, Schedule};

/// The field's Adam: betas 0.9 and 0.99 with a tiny epsilon, as hash-grid fields are trained
/// (the MLP's update runs on the device's tensors with these numbers, the table's on the host).
const ADAM: AdamW<f64> = AdamW { beta1: 0.9, beta2: 0.99, eps: 1e-15, weight_decay: 0.0 };
/// [`ADAM`] for the host table, in its f32.
const ADAM_TABLE: AdamW<f32> = AdamW { beta1: 0.9, beta2: 0.99, eps: 1e-15, weight_decay: 0.0 };
use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Loss terms of one iteration (weighted sum in `total`).
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
pub struct StepStats {
    /// Iteration just done (1-based).
    pub iter: usize,
    /// Weighted total.
    pub total: f32,
    /// Depth L1 (normalised units).
    pub depth: f32,
    /// Normal L1 + angular.
    pub normal: f32,
    /// Eikonal.
    pub eikonal: f32,
    /// Colour L1.
    pub color: f32,
    /// NeuS sharpness.
    pub sharpness: f32,
    /// Learning rate used.
    pub lr: f32,
}

/// Offsets of the four-point (tetrahedron) numerical gradient, in units of the step `h`.
pub const TETRA: [Vec3; 4] =
    [Vec3::new(1.0, -1.0, -1.0), Vec3::new(-1.0, -1.0, 1.0), Vec3::new(-1.0, 1.0, -1.0), Vec3::new(1.0, 1.0, 1.0)];

/// The points at which a numerical gradient at each of `points` is taken, four per point.
pub fn tetra_points(points: &[Vec3], h: f32) -> Vec<Vec3> {
    points.iter().flat_map(|&p| TETRA.iter().map(move |v| p + *v * h)).collect()
}

/// `(4, 3)` matrix taking the four SDF values at [`tetra_points`] to the gradient:
/// `grad = sum_k v_k f(x + h v_k) / (4 h)`, exact for linear functions.
pub fn tetra_matrix(h: f32, device: &Device) -> Tensor<2> {
    let v: Vec<f32> = TETRA.iter().flat_map(|v| v.to_array()).map(|x| x / (4.0 * h)).collect();
    tensor2(v, [4, 3], device)
}

/// Adam moments of one tensor.
struct Moments {
    m: Tensor<2>,
    v: Tensor<2>,
}

/// A field being trained, with its optimiser state.
pub struct Trainer {
    /// Field architecture.
    pub config: FieldConfig,
    /// Options.
    pub options: TrainOptions,
    /// MLP parameters (autodiff device).
    pub params: Params,
    /// The hash-grid table (host), `(levels * table, features)` row-major.
    pub table: Vec<f32>,
    table_m: Vec<f32>,
    table_v: Vec<f32>,
    /// The table's gradient, reused across steps (25 MB at the default size).
    table_grad: Vec<f32>,
    moments: Vec<Moments>,
    /// Iterations done.
    pub iter: usize,
    /// [`TrainData::fingerprint`] of the data, hashed once (checkpoints carry it).
    data_hash: u64,
    device: Device,
    frame_ranges: Vec<(usize, usize)>,
    occupied: Vec<glam::IVec3>,
}

fn tensor2(v: Vec<f32>, shape: [usize; 2], device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v, shape), device)
}

impl Trainer {
    /// A fresh field (geometric initialisation) for `data` on `device` (an autodiff device,
    /// e.g. `Device::autodiff(Device::flex())`).
    pub fn new(
        config: FieldConfig,
        options: TrainOptions,
        data: &TrainData,
        device: Device,
    ) -> Result<Self, NsdfError> {
        config.check().map_err(|e| NsdfError::Options(e.0))?;
        options.check().map_err(|e| NsdfError::Options(e.0))?;
        let values = field::init_values(&config, options.seed);
        Ok(Self::from_state(config, options, data, device, &values, None, 0, data.fingerprint()))
    }

    #[allow(clippy::too_many_arguments)]
    fn from_state(
        config: FieldConfig,
        options: TrainOptions,
        data: &TrainData,
        device: Device,
        values: &[(Vec<f32>, [usize; 2])],
        moments: Option<&[(Vec<f32>, Vec<f32>)]>,
        iter: usize,
        data_hash: u64,
    ) -> Self {
        let (table, params) = Params::from_values(values, &device, true);
        let inner = device.clone().inner();
        let (table_m, table_v) = match moments {
            Some(m) => (m[0].0.clone(), m[0].1.clone()),
            None => (vec![0.0; table.len()], vec![0.0; table.len()]),
        };
        let moments = values
            .iter()
            .enumerate()
            .skip(1)
            .map(|(i, (_, s))| match moments {
                Some(m) => Moments { m: tensor2(m[i].0.clone(), *s, &inner), v: tensor2(m[i].1.clone(), *s, &inner) },
                None => Moments { m: Tensor::zeros(*s, &inner), v: Tensor::zeros(*s, &inner) },
            })
            .collect();
        let mut frame_ranges = vec![(usize::MAX, 0usize); data.frames];
        for (i, &f) in data.rays.frame.iter().enumerate() {
            let r = &mut frame_ranges[f as usize];
            r.0 = r.0.min(i);
            r.1 = r.1.max(i + 1);
        }
        let frame_ranges = frame_ranges.into_iter().filter(|r| r.1 > r.0).collect();
        let occupied = data.occupancy.cells().collect();
        let table_grad = vec![0.0; table.len()];
        Self {
            config,
            options,
            params,
            table,
            table_m,
            table_v,
            table_grad,
            moments,
            iter,
            data_hash,
            device,
            frame_ranges,
            occupied,
        }
    }

    /// Saves parameters, optimiser state and progress to `path` (`.safetensors`, atomically,
    /// with a `.json` beside it).
    pub fn save(&self, path: &std::path::Path, data: &TrainData) -> Result<(), NsdfError> {
        let mut moments = vec![(self.table_m.clone(), self.table_v.clone())];
        moments.extend(self.moments.iter().map(|m| (field::to_vec(m.m.clone()), field::to_vec(m.v.clone()))));
        let ck = Checkpoint {
            config: self.config.clone(),
            options: self.options.clone(),
            bounds: data.bounds,
            iter: self.iter,
            data: Some(self.data_hash),
            values: self.values(),
            moments: Some(moments),
        };
        checkpoint::save(path, &ck)
    }

    /// Resumes from a checkpoint written by [`Trainer::save`] for the same field, data and
    /// options (only `iters` may differ).
    pub fn resume(
        path: &std::path::Path,
        config: &FieldConfig,
        options: TrainOptions,
        data: &TrainData,
        device: Device,
    ) -> Result<Self, NsdfError> {
        let ck = checkpoint::load(path)?;
        let data_hash = data.fingerprint();
        if ck.data.is_some_and(|h| h != data_hash) {
            return Err(NsdfError::Checkpoint(format!(
                "{}: written for other input (another scene, or its frames changed); rerun with --restart to start over from this input, or give another -o",
                path.display()
            )));
        }
        if ck.config != *config {
            return Err(NsdfError::Checkpoint(format!(
                "{}: written for another field configuration; delete it or rerun with the same options",
                path.display()
            )));
        }
        let same = TrainOptions { iters: options.iters, ..ck.options.clone() };
        if same != options {
            return Err(NsdfError::Checkpoint(format!(
                "{}: written with other training options; delete it or rerun with the same options",
                path.display()
            )));
        }
        let moments = ck.moments.ok_or_else(|| {
            NsdfError::Checkpoint(format!("{}: holds no optimiser state (an exported field?)", path.display()))
        })?;
        Ok(Self::from_state(ck.config, options, data, device, &ck.values, Some(&moments), ck.iter, data_hash))
    }

    /// All parameter values with shapes, table first (the checkpoint layout).
    pub fn values(&self) -> Vec<(Vec<f32>, [usize; 2])> {
        let mut v = vec![(self.table.clone(), [self.table.len() / self.config.features, self.config.features])];
        v.extend(self.params.values());
        v
    }

    /// Evaluates the field on points for training.
    fn eval(&self, points: &[Vec3], mask: &[f32]) -> Evaluated {
        self.params.forward(&self.config, &self.table, encode(&self.config, points), mask, true)
    }

    /// Levels active at iteration `it` as a per-level mask, and the finest active resolution.
    fn levels_at(&self, it: usize) -> (Vec<f32>, u32) {
        let l = self.config.levels;
        let start = self.options.start_levels.clamp(1, l);
        let span = (self.options.iters as f64 * 0.4).max(1.0);
        let active = if l == start { l } else { (start + ((it as f64 / span) * (l - start) as f64) as usize).min(l) };
        let mask = (0..l).map(|i| if i < active { 1.0 } else { 0.0 }).collect();
        (mask, self.config.level_res(active - 1))
    }

    /// Warm-up, then cosine decay to a tenth of the peak.
    fn lr_at(&self, it: usize) -> f64 {
        let o = &self.options;
        Schedule { peak: o.lr, end: 0.1 * o.lr, warmup_steps: o.warmup, total: o.iters, decay: Decay::Cosine }.at(it)
    }

    /// One iteration on `data`.
    pub fn step(&mut self, data: &TrainData) -> StepStats {
        let it = self.iter;
        let o = self.options.clone();
        let cfg = self.config.clone();
        let mut rng = ChaCha8Rng::seed_from_u64(o.seed ^ (it as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let (mask, res) = self.levels_at(it);
        // Numerical-gradient step: a quarter of the finest active cell (Neuralangelo).
        let h = 0.5 / res as f32;

        // Rays from a few frames.
        let mut rays: Vec<usize> = Vec::with_capacity(o.rays);
        let k = o.frames_per_batch.min(self.frame_ranges.len());
        let per = o.rays.div_ceil(k);
        for _ in 0..k {
            let (a, b) = self.frame_ranges[rng.gen_range(0..self.frame_ranges.len())];
            rays.extend((0..per).map(|_| rng.gen_range(a..b)));
        }
        rays.truncate(o.rays);
        let s = o.samples;
        let margin = 3.0 * data.occupancy.cell();
        let jitter: Vec<f32> = (0..rays.len() * s).map(|_| rng.gen()).collect();
        let samples: Vec<Option<Vec<f32>>> = rays
            .par_iter()
            .enumerate()
            .map(|(ri, &r)| {
                let mut segs = data.occupancy.segments(data.rays.origin[r], data.rays.dir[r]);
                if o.depth_mode == DepthMode::Metric {
                    // Depth-guided: the visible surface lies before the observed depth plus a
                    // margin, so the samples skip the far side of the object.
                    let end = data.rays.dist[r] + margin;
                    let front: Vec<(f32, f32)> =
                        segs.iter().filter(|s| s.0 < end).map(|&(a, b)| (a, b.min(end))).collect();
                    if !front.is_empty() {
                        segs = front;
                    }
                }
                let total: f32 = segs.iter().map(|(a, b)| b - a).sum();
                if total <= 0.0 {
                    return None;
                }
                // A quarter of the samples stratified over the whole ray up to the last occupied
                // stretch (so free space in front of the surface is seen and kept positive),
                // the rest stratified over the occupied stretches.
                let near = ray_cube(data.rays.origin[r], data.rays.dir[r]).map_or(0.0, |(t0, _)| t0);
                let far = segs[segs.len() - 1].1;
                let su = s / 4;
                let mut ts = Vec::with_capacity(s);
                for j in 0..su {
                    ts.push(near + (j as f32 + jitter[ri * s + j]) / su as f32 * (far - near));
                }
                let so = s - su;
                let (mut seg, mut acc) = (0, 0.0f32);
                for j in 0..so {
                    let u = (j as f32 + jitter[ri * s + su + j]) / so as f32 * total;
                    while seg + 1 < segs.len() && u > acc + (segs[seg].1 - segs[seg].0) {
                        acc += segs[seg].1 - segs[seg].0;
                        seg += 1;
                    }
                    ts.push((segs[seg].0 + (u - acc)).min(segs[seg].1));
                }
                ts.sort_by(f32::total_cmp);
                Some(ts)
            })
            .collect();
        let keep: Vec<usize> = (0..rays.len()).filter(|&i| samples[i].is_some()).collect();
        let n_rays = keep.len();
        if n_rays == 0 {
            // No ray of this batch crosses an occupied cell (observations outside the bounds).
            self.iter += 1;
            return StepStats { iter: it + 1, ..Default::default() };
        }
        let mut t_host = Vec::with_capacity(n_rays * s);
        let mut pts = Vec::with_capacity(n_rays * s);
        for &i in &keep {
            let r = rays[i];
            for &t in samples[i].as_ref().expect("kept") {
                t_host.push(t);
                pts.push(data.rays.origin[r] + data.rays.dir[r] * t);
            }
        }
        // Eikonal points: uniform in random occupied cells, at the tetrahedron's vertices.
        let cell = data.occupancy.cell();
        // Eikonal points: half in occupied cells, half anywhere in the cube.
        let eik: Vec<Vec3> = (0..o.eikonal_points)
            .map(|j| {
                let u = Vec3::new(rng.gen(), rng.gen(), rng.gen());
                if j % 2 == 0 {
                    let c = self.occupied[rng.gen_range(0..self.occupied.len())];
                    (c.as_vec3() + u) * cell - 1.0
                } else {
                    u * 2.0 - 1.0
                }
            })
            .collect();
        let eik = tetra_points(&eik, h);
        let device = self.device.clone();
        pts.extend_from_slice(&eik);
        let ev = self.eval(&pts, &mask);
        let out = ev.out.clone();
        let outs = cfg.outputs();
        let ns = n_rays * s;
        let sdf = out.clone().slice([0..ns, 0..1]).reshape([n_rays, s]);
        let t = tensor2(t_host, [n_rays, s], &device);
        let rendered = render::neus(sdf, t, self.params.sharpness());
        let mut total: Tensor<1> = Tensor::zeros([1], &device);
        let mut stats = StepStats { iter: it + 1, ..Default::default() };

        // Depth.
        let dist_host = field::to_vec(rendered.distance.clone());
        if o.depth_mode != DepthMode::Off && o.w_depth > 0.0 {
            let obs: Vec<f32> = keep.iter().map(|&i| data.rays.dist[rays[i]]).collect();
            let target = match o.depth_mode {
                DepthMode::ScaleShift => scale_shift_targets(
                    &keep.iter().map(|&i| data.rays.frame[rays[i]]).collect::<Vec<_>>(),
                    &obs,
                    &dist_host,
                ),
                _ => obs,
            };
            let target = tensor2(target, [n_rays, 1], &device);
            let l = (rendered.distance.clone() - target).abs().mean();
            stats.depth = field::to_vec(l.clone())[0];
            total = total + l * o.w_depth;
        }
        // Opacity.
        if o.w_opacity > 0.0 {
            let l = (rendered.opacity.clone().neg() + 1.0).abs().mean();
            total = total + l * o.w_opacity;
        }
        // Colour.
        if cfg.color && o.w_color > 0.0 {
            let rgb = burn::tensor::activation::sigmoid(out.clone().slice([0..ns, 1..outs])).reshape([n_rays, s, 3]);
            let c = render::weighted(&rendered.weights, &rendered.opacity, rgb);
            let obs: Vec<f32> = keep.iter().flat_map(|&i| data.rays.color[rays[i]]).collect();
            let l = (c - tensor2(obs, [n_rays, 3], &device)).abs().mean();
            stats.color = field::to_vec(l.clone())[0];
            total = total + l * o.w_color;
        }
        // Numerical gradients at the rendered surface points (normals, eikonal) and at the random
        // points (eikonal).
        let surf: Vec<Vec3> = keep
            .iter()
            .zip(&dist_host)
            .map(|(&i, &d)| data.rays.origin[rays[i]] + data.rays.dir[rays[i]] * d)
            .collect();
        let ev_s = self.eval(&tetra_points(&surf, h), &mask);
        let out_s = ev_s.out.clone();
        let vmat = tetra_matrix(h, &device);
        let grad_s = out_s.slice([0..n_rays * 4, 0..1]).reshape([n_rays, 4]).matmul(vmat.clone());
        let ne = o.eikonal_points;
        let grad_e = out.slice([ns..ns + 4 * ne, 0..1]).reshape([ne, 4]).matmul(vmat);
        let grads = Tensor::cat(vec![grad_s.clone(), grad_e], 0);
        let norm = grads.square().sum_dim(1).add_scalar(1e-12).sqrt();
        let l_eik = (norm - 1.0).square().mean();
        stats.eikonal = field::to_vec(l_eik.clone())[0];
        total = total + l_eik * o.w_eikonal;
        if o.w_normal > 0.0 && data.has_normals {
            let obs: Vec<f32> = keep.iter().flat_map(|&i| data.rays.normal[rays[i]].to_array()).collect();
            let valid: Vec<f32> =
                keep.iter().map(|&i| if data.rays.normal[rays[i]] != Vec3::ZERO { 1.0 } else { 0.0 }).collect();
            let count = valid.iter().sum::<f32>().max(1.0);
            let obs = tensor2(obs, [n_rays, 3], &device);
            let valid = tensor2(valid, [n_rays, 1], &device);
            let len = grad_s.clone().square().sum_dim(1).add_scalar(1e-12).sqrt();
            let n = grad_s / len;
            let l1 = (n.clone() - obs.clone()).abs().sum_dim(1);
            let ang = (n * obs).sum_dim(1).neg() + 1.0;
            let l = ((l1 + ang) * valid).sum() / count;
            stats.normal = field::to_vec(l.clone())[0];
            total = total + l * o.w_normal;
        }
        stats.total = field::to_vec(total.clone())[0];
        stats.sharpness = field::to_vec(self.params.sharpness())[0];
        let lr = self.lr_at(it);
        stats.lr = lr as f32;
        self.apply(total, lr, &[ev, ev_s], &mask);
        self.iter += 1;
        stats
    }

    /// Backward pass and one Adam update (MLP on the device, table on the host, where its
    /// gradient is scattered from the feature leaves of `evals`).
    fn apply(&mut self, loss: Tensor<1>, lr: f64, evals: &[Evaluated], mask: &[f32]) {
        let (b1, b2, eps) = (ADAM.beta1, ADAM.beta2, ADAM.eps);
        let grads = loss.backward();
        let (c1, c2) = ADAM.bias_corrections(self.iter);
        let gtable = &mut self.table_grad;
        gtable.par_iter_mut().for_each(|g| *g = 0.0);
        for ev in evals {
            if let Some(g) = ev.features.grad(&grads) {
                field::grid_backward(&self.config, &ev.enc, mask, &field::to_vec(g), gtable);
            }
        }
        let at = At::new(self.iter, lr as f32);
        ADAM_TABLE.update_par(at, &mut self.table, &mut self.table_m, &mut self.table_v, gtable, false);
        for (p, mo) in self.params.tensors.iter_mut().zip(self.moments.iter_mut()) {
            let Some(g) = p.grad(&grads) else { continue };
            let g = g.inner();
            mo.m = mo.m.clone().mul_scalar(b1) + g.clone().mul_scalar(1.0 - b1);
            mo.v = mo.v.clone().mul_scalar(b2) + g.square().mul_scalar(1.0 - b2);
            let upd = (mo.m.clone().div_scalar(c1)) / (mo.v.clone().div_scalar(c2).sqrt().add_scalar(eps));
            let new = p.clone().inner() - upd.mul_scalar(lr);
            *p = Tensor::from_inner(new).require_grad();
        }
    }

    /// Fits the field to a TSDF of the scene (SDF values in the normalised frame at `points`),
    /// L1, for `iters` iterations before rendering starts.
    pub fn fit_sdf(&mut self, points: &[Vec3], values: &[f32], iters: usize, mut progress: impl FnMut(usize, f32)) {
        let cfg = self.config.clone();
        let mask = vec![1.0; cfg.levels];
        let batch = (self.options.rays * 8).min(points.len());
        for i in 0..iters {
            let mut rng = ChaCha8Rng::seed_from_u64(self.options.seed ^ 0x5bd1_e995 ^ i as u64);
            let idx: Vec<usize> = (0..batch).map(|_| rng.gen_range(0..points.len())).collect();
            let p: Vec<Vec3> = idx.iter().map(|&j| points[j]).collect();
            let v: Vec<f32> = idx.iter().map(|&j| values[j]).collect();
            let ev = self.eval(&p, &mask);
            let l = (ev.out.clone().slice([0..batch, 0..1]) - tensor2(v, [batch, 1], &self.device)).abs().mean();
            progress(i, field::to_vec(l.clone())[0]);
            let lr = self.options.lr * 0.5;
            self.apply(l, lr, &[ev], &mask);
        }
        // The rendering phase starts its own Adam schedule.
        self.table_m.iter_mut().chain(self.table_v.iter_mut()).for_each(|x| *x = 0.0);
        for m in &mut self.moments {
            m.m = m.m.clone().zeros_like();
            m.v = m.v.clone().zeros_like();
        }
    }
}

/// MonoSDF's per-image least-squares `a * observed + b ~ rendered` (rendered held constant):
/// the targets `a * observed + b` per ray.
fn scale_shift_targets(frames: &[u32], obs: &[f32], rendered: &[f32]) -> Vec<f32> {
    let mut fit: std::collections::HashMap<u32, [f64; 5]> = Default::default();
    for ((&f, &o), &r) in frames.iter().zip(obs).zip(rendered) {
        let s = fit.entry(f).or_default();
        let (o, r) = (o as f64, r as f64);
        s[0] += o * o;
        s[1] += o;
        s[2] += 1.0;
        s[3] += o * r;
        s[4] += r;
    }
    let ab: std::collections::HashMap<u32, (f64, f64)> = fit
        .into_iter()
        .map(|(f, s)| {
            let det = s[0] * s[2] - s[1] * s[1];
            if det.abs() < 1e-12 {
                (f, (1.0, 0.0))
            } else {
                (f, ((s[2] * s[3] - s[1] * s[4]) / det, (s[0] * s[4] - s[1] * s[3]) / det))
            }
        })
        .collect();
    frames.iter().zip(obs).map(|(f, &o)| (ab[f].0 * o as f64 + ab[f].1) as f32).collect()
}

/// Where a run keeps its checkpoint.
pub fn checkpoint_path(dir: &std::path::Path) -> PathBuf {
    dir.join("nsdf.safetensors")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_shift_recovers_an_affine_map() {
        // rendered = 2 * obs + 0.5 on frame 0, 0.5 * obs - 1 on frame 1.
        let frames = [0, 0, 0, 1, 1, 1];
        let obs = [1.0, 2.0, 4.0, 1.0, 3.0, 5.0];
        let rendered: Vec<f32> =
            frames.iter().zip(&obs).map(|(&f, &o)| if f == 0 { 2.0 * o + 0.5 } else { 0.5 * o - 1.0 }).collect();
        let t = scale_shift_targets(&frames, &obs, &rendered);
        for (a, b) in t.iter().zip(&rendered) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }
}
