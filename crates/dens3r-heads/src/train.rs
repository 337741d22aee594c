//! Head training on cached frozen features: AdamW with linear warm-up and cosine decay,
//! mini-batches, augmentation (left-right flip and token-aligned random crops in feature space,
//! as many per image and epoch as tile it once, each with a band of unlabelled context
//! features around it; colour jitter, which needs the backbone re-run,
//! when a backbone is given), validation after every epoch (mIoU and pixel accuracy, or AbsRel
//! and delta1), checkpoints and resume.
//!
//! Determinism: the sample order of an epoch is drawn from `(seed, epoch)` and a step's
//! augmentation from `(seed, step)`, so a run resumed from a checkpoint takes the same steps as
//! one never interrupted.

use crate::cache::StoredFeatures;
use crate::data::{Sample, Target};
use crate::features::{to_vec, Backbone, FeatureMaps};
use crate::head::{Head, Task};
use crate::loss::{affine_invariant, cross_entropy, silog, IGNORE};
use crate::metrics::{Confusion, DepthStats};
use crate::HeadsError;
use burn::tensor::{Device, Tensor};
use dens3r_geom::metrics::DepthAlign;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// Depth loss.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DepthLoss {
    /// Scale-invariant log (metric-ish depth up to a global scale).
    Silog,
    /// Affine-invariant (relative depth).
    AffineInvariant,
}

impl DepthLoss {
    /// How a head trained with this loss is scored: as predicted (SILog), or after the
    /// per-image least-squares scale and shift (affine-invariant).
    pub fn align(self) -> DepthAlign {
        match self {
            DepthLoss::Silog => DepthAlign::None,
            DepthLoss::AffineInvariant => DepthAlign::ScaleShift,
        }
    }
}

/// Training settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainOptions {
    /// Passes over the training set.
    pub epochs: usize,
    /// Samples per step.
    pub batch: usize,
    /// Peak learning rate.
    pub lr: f32,
    /// Decoupled weight decay (AdamW).
    pub weight_decay: f32,
    /// Warm-up as a fraction of all steps.
    pub warmup: f32,
    /// Random crop size in tokens `(rows, cols)`; `None` trains on whole images.
    pub crop: Option<(usize, usize)>,
    /// Crops drawn from each training image per epoch; `None`: enough to cover its token grid
    /// once (`ceil(rows / crop rows) * ceil(cols / crop cols)`), so an epoch is a pass over the
    /// pixels whatever the crop size (1 without cropping).
    #[serde(default)]
    pub crops_per_image: Option<usize>,
    /// Tokens of real features kept on each side of a crop (as far as the image goes), their
    /// pixels left out of the loss: convolutions at a crop's edge then see the neighbours they
    /// see on whole images at inference, not zero padding. Unused by per-token heads.
    #[serde(default)]
    pub crop_context: usize,
    /// Random left-right flips.
    pub flip: bool,
    /// Colour jitter strength (brightness / contrast / saturation factors in `1 +- jitter`);
    /// needs the backbone at every step.
    pub jitter: f32,
    /// Per-class loss weights.
    pub class_weights: Option<Vec<f32>>,
    /// Depth loss.
    pub depth_loss: DepthLoss,
    /// Seed of initialisation, order and augmentation.
    pub seed: u64,
    /// Checkpoint every this many steps (and after every epoch).
    pub checkpoint_every: usize,
    /// Largest global gradient norm: a step's gradient is scaled down to it when longer (as
    /// PyTorch's `clip_grad_norm_`); `None` never clips (checkpoints written before the option).
    #[serde(default)]
    pub clip_grad_norm: Option<f32>,
}

impl Default for TrainOptions {
    fn default() -> Self {
        Self {
            epochs: 20,
            batch: 4,
            lr: 1e-3,
            weight_decay: 1e-4,
            warmup: 0.05,
            crop: None,
            crops_per_image: None,
            crop_context: 2,
            flip: true,
            jitter: 0.0,
            class_weights: None,
            depth_loss: DepthLoss::Silog,
            seed: 0,
            checkpoint_every: 50,
            clip_grad_norm: Some(1.0),
        }
    }
}

impl TrainOptions {
    /// Rejects settings that cannot train.
    pub fn check(&self) -> Result<(), HeadsError> {
        if self.epochs == 0 || self.batch == 0 {
            return Err(HeadsError::invalid("epochs and batch must be at least 1"));
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr < 1.0) {
            return Err(HeadsError::invalid(format!("learning rate {} must be in (0, 1)", self.lr)));
        }
        if !(0.0..1.0).contains(&self.warmup) || !(0.0..1.0).contains(&self.jitter) {
            return Err(HeadsError::invalid("warm-up and jitter must be in [0, 1)"));
        }
        if self.crop.is_some_and(|(r, c)| r == 0 || c == 0) {
            return Err(HeadsError::invalid("crop sizes must be at least one token"));
        }
        if self.crops_per_image == Some(0) {
            return Err(HeadsError::invalid("crops per image must be at least 1"));
        }
        if let Some(m) = self.clip_grad_norm.filter(|m| !(m.is_finite() && *m > 0.0)) {
            return Err(HeadsError::invalid(format!("gradient-norm limit {m} must be positive (0 = no clipping)")));
        }
        Ok(())
    }
}

/// A training or validation example: an image's features and its target.
#[derive(Debug, Clone)]
pub struct Example {
    /// The sample (image and full-resolution target).
    pub sample: Sample,
    /// Its frozen features.
    pub features: Features,
}

/// Where an example's features are.
#[derive(Debug, Clone)]
pub enum Features {
    /// In memory.
    Held(FeatureMaps),
    /// A feature-cache entry, read at each use: what `train-head` gives, so a set of any size
    /// trains without its features in memory.
    Stored(StoredFeatures),
}

impl From<FeatureMaps> for Features {
    fn from(f: FeatureMaps) -> Self {
        Features::Held(f)
    }
}

impl From<StoredFeatures> for Features {
    fn from(f: StoredFeatures) -> Self {
        Features::Stored(f)
    }
}

impl Features {
    /// Token grid `(rows, cols)`.
    pub fn grid(&self) -> (usize, usize) {
        match self {
            Features::Held(f) => f.grid,
            Features::Stored(s) => s.grid(),
        }
    }

    /// The values (read from the cache entry when stored).
    pub fn load(&self) -> Result<Cow<'_, FeatureMaps>, HeadsError> {
        Ok(match self {
            Features::Held(f) => Cow::Borrowed(f),
            Features::Stored(s) => Cow::Owned(s.read()?),
        })
    }
}

/// One augmented training draw: cropped (and flipped) features and target.
#[derive(Debug, Clone)]
pub struct Draw {
    /// Features of the crop and its context band.
    pub features: FeatureMaps,
    /// Target at those pixels (ignored / invalid in the context band).
    pub target: Target,
    /// Size in pixels `(rows, cols)` of the crop with its band.
    pub size: (usize, usize),
}

/// Validation result of one epoch.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    /// Epoch (1-based).
    pub epoch: usize,
    /// Mean IoU (segmentation).
    pub miou: f64,
    /// Pixel accuracy (segmentation).
    pub pixel_accuracy: f64,
    /// AbsRel (depth).
    pub abs_rel: f64,
    /// delta < 1.25 (depth).
    pub delta1: f64,
}

/// Progress report after each step.
#[derive(Debug, Clone, Copy)]
pub struct Progress {
    /// Steps done / total.
    pub step: usize,
    /// Total steps.
    pub steps: usize,
    /// This step's loss.
    pub loss: f32,
    /// Learning rate used.
    pub lr: f32,
    /// Set after an epoch's validation.
    pub validation: Option<Validation>,
}

/// The trainer's saved state beside the head.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    format: String,
    options: TrainOptions,
    step: usize,
    history: Vec<Validation>,
}

const STATE_FORMAT: &str = "dens3r-head-train/1";

/// A head being trained, with AdamW moments.
pub struct Trainer {
    /// The head.
    pub head: Head,
    /// Settings.
    pub options: TrainOptions,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    /// Steps done.
    pub step: usize,
    /// Validation after each finished epoch.
    pub history: Vec<Validation>,
    /// Confusion matrix of the last validation this trainer ran (segmentation; per-class IoU).
    pub confusion: Option<Confusion>,
    device: Device,
}

/// Checkpoint files in `dir`: the head (`head.json` / `head.safetensors`), the AdamW moments
/// and the trainer state.
fn ck_paths(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    (dir.join("head"), dir.join("adam.safetensors"), dir.join("state.json"))
}

impl Trainer {
    /// A fresh trainer on `device` (an autodiff device, e.g. `Device::autodiff(Device::flex())`).
    pub fn new(head: Head, options: TrainOptions, device: Device) -> Result<Self, HeadsError> {
        options.check()?;
        let zeros: Vec<Vec<f32>> = head.values.iter().map(|v| vec![0.0; v.len()]).collect();
        Ok(Self { head, options, m: zeros.clone(), v: zeros, step: 0, history: Vec::new(), confusion: None, device })
    }

    /// Resumes from a checkpoint folder written by [`Trainer::save`], if one is there and was
    /// made with the same head configuration and options; `Ok(None)` when the folder has none.
    pub fn resume(dir: &Path, head: &Head, options: &TrainOptions, device: Device) -> Result<Option<Self>, HeadsError> {
        let (hp, ap, sp) = ck_paths(dir);
        if !sp.is_file() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&sp).map_err(|e| HeadsError::file(&sp, e.to_string()))?;
        let state: State = serde_json::from_str(&text)
            .map_err(|e| HeadsError::file(&sp, format!("damaged checkpoint ({e}); delete the folder to start over")))?;
        if state.format != STATE_FORMAT || &state.options != options {
            return Err(HeadsError::file(
                &sp,
                "the checkpoint was made with other training options; delete the folder to start over, or rerun with the same options",
            ));
        }
        let saved = Head::load(&hp)?;
        if saved.config != head.config {
            return Err(HeadsError::file(
                &hp.with_extension("json"),
                "the checkpoint is for another head or backbone; delete the folder to start over",
            ));
        }
        let shapes = saved.param_shapes();
        let moment_shapes: Vec<(String, Vec<usize>)> =
            ["m", "v"].iter().flat_map(|k| shapes.iter().map(move |(n, s)| (format!("{k}.{n}"), s.clone()))).collect();
        let mut mv = crate::io::load_tensors(&ap, &moment_shapes)?;
        let v = mv.split_off(shapes.len());
        let mut t = Self::new(saved, options.clone(), device)?;
        (t.m, t.v, t.step, t.history) = (mv, v, state.step, state.history);
        Ok(Some(t))
    }

    /// Writes the checkpoint (head and moments first, the state last, each atomically).
    pub fn save(&self, dir: &Path) -> Result<(), HeadsError> {
        std::fs::create_dir_all(dir).map_err(|e| HeadsError::file(dir, format!("cannot create ({e})")))?;
        let (hp, ap, sp) = ck_paths(dir);
        self.head.save(&hp)?;
        let shapes = self.head.param_shapes();
        let named: Vec<(String, Vec<usize>, &[f32])> = ["m", "v"]
            .iter()
            .zip([&self.m, &self.v])
            .flat_map(|(k, vals)| {
                shapes.iter().zip(vals).map(move |((n, s), v)| (format!("{k}.{n}"), s.clone(), v.as_slice()))
            })
            .collect();
        dens3r_io::tensors::save(&ap, &named)?;
        let state = State {
            format: STATE_FORMAT.into(),
            options: self.options.clone(),
            step: self.step,
            history: self.history.clone(),
        };
        Ok(dens3r_io::tensors::save_json(&sp, &state)?)
    }

    /// Crops drawn from an example per epoch (see [`TrainOptions::crops_per_image`]).
    pub fn crops_per_epoch(&self, ex: &Example) -> usize {
        let (gh, gw) = ex.features.grid();
        match (self.options.crops_per_image, self.options.crop) {
            (Some(k), _) => k,
            (None, Some((r, c))) => gh.div_ceil(r.min(gh)) * gw.div_ceil(c.min(gw)),
            (None, None) => 1,
        }
    }

    /// An epoch's draws: example indices, each repeated [`Trainer::crops_per_epoch`] times,
    /// shuffled by `(seed, epoch)`.
    fn epoch_order(&self, train: &[Example], epoch: usize) -> Vec<usize> {
        let mut order: Vec<usize> =
            train.iter().enumerate().flat_map(|(i, ex)| std::iter::repeat_n(i, self.crops_per_epoch(ex))).collect();
        order.shuffle(&mut ChaCha8Rng::seed_from_u64(self.options.seed ^ (0x9e37_79b9 * (epoch as u64 + 1))));
        order
    }

    /// Optimiser steps per epoch on `train`.
    pub fn steps_per_epoch(&self, train: &[Example]) -> usize {
        train.iter().map(|ex| self.crops_per_epoch(ex)).sum::<usize>().div_ceil(self.options.batch)
    }

    /// Learning rate at a step: linear warm-up, then cosine decay to zero.
    pub fn lr_at(&self, step: usize, total: usize) -> f32 {
        dens3r_optim::WarmupCosine { lr: self.options.lr, warmup: self.options.warmup, total }.at(step)
    }

    /// The loss of one (augmented) example with parameter tensors `params`.
    pub fn example_loss(&self, params: &[Tensor<1>], d: &Draw) -> Option<Tensor<1>> {
        let (f, target, size) = (&d.features, &d.target, d.size);
        let feats: Vec<Tensor<4>> = self.head.config.layers.iter().map(|&l| f.tensor(l, &self.device)).collect();
        let out = self.head.forward_with(params, &feats, size);
        match (target, &self.head.config.task) {
            (Target::Labels(l), Task::Seg { .. }) => cross_entropy(out, l, self.options.class_weights.as_deref()),
            (Target::Depth(d), Task::Depth) => match self.options.depth_loss {
                DepthLoss::Silog => silog(out, d),
                DepthLoss::AffineInvariant => affine_invariant(out, d),
            },
            _ => None,
        }
    }

    /// One AdamW step on a batch of examples; returns the mean loss (`None` when no example
    /// had a usable target).
    fn train_step(&mut self, batch: &[Draw], lr: f32) -> Option<f32> {
        let (value, grads) = if dens3r_backbone::device::is_gpu(&self.device) {
            self.batch_gradients(batch)?
        } else {
            self.example_gradients(batch)?
        };
        let opt = dens3r_optim::AdamW { weight_decay: self.options.weight_decay, ..Default::default() };
        let shapes = self.head.param_shapes();
        let norm = dens3r_optim::global_norm(&grads);
        let at =
            dens3r_optim::At::new(self.step, lr).scaled(dens3r_optim::clip_scale(norm, self.options.clip_grad_norm));
        for (i, g) in grads.iter().enumerate() {
            let Some(g) = g else { continue };
            let decay = !shapes[i].0.ends_with(".bias");
            let (vals, m, v) = (&mut self.head.values[i], &mut self.m[i], &mut self.v[i]);
            opt.update(at, vals, m, v, g, decay);
        }
        Some(value)
    }

    /// The batch's mean loss and its gradients, the batch as one graph.
    fn batch_gradients(&self, batch: &[Draw]) -> Option<(f32, Vec<Option<Vec<f32>>>)> {
        let params: Vec<Tensor<1>> = self.head.tensors(&self.device).into_iter().map(|t| t.require_grad()).collect();
        let losses: Vec<Tensor<1>> = batch.iter().filter_map(|d| self.example_loss(&params, d)).collect();
        if losses.is_empty() {
            return None;
        }
        let k = losses.len() as f32;
        let loss = Tensor::cat(losses, 0).sum().div_scalar(k);
        let value = to_vec(loss.clone())[0];
        let grads = loss.backward();
        Some((value, params.iter().map(|p| p.grad(&grads).map(to_vec)).collect()))
    }

    /// The batch's mean loss and its gradients, each example a graph of its own (its own
    /// parameter leaves), as many side by side as there are threads: burn's autodiff and
    /// element-wise ops run on one core, so with the batch as one graph the other core sat
    /// idle for much of a step. The examples' gradients, added in order and divided by the
    /// number with a usable target, are the mean's (to rounding) however many threads ran.
    fn example_gradients(&self, batch: &[Draw]) -> Option<(f32, Vec<Option<Vec<f32>>>)> {
        let one = |d: &Draw| {
            let params: Vec<Tensor<1>> =
                self.head.tensors(&self.device).into_iter().map(|t| t.require_grad()).collect();
            let loss = self.example_loss(&params, d)?;
            let value = to_vec(loss.clone())[0];
            let grads = loss.backward();
            Some((value, params.iter().map(|p| p.grad(&grads).map(to_vec)).collect::<Vec<_>>()))
        };
        let (mut sum, mut value, mut k) = (vec![None; self.head.values.len()], 0.0f32, 0usize);
        let Ok(()) = dens3r_optim::side_by_side(batch, one, |r| {
            if let Some((v, g)) = r {
                value += v;
                k += 1;
                dens3r_optim::add_gradients(&mut sum, g);
            }
            Ok::<(), std::convert::Infallible>(())
        });
        if k == 0 {
            return None;
        }
        let inv = 1.0 / k as f32;
        sum.iter_mut().flatten().for_each(|g| g.iter_mut().for_each(|x| *x *= inv));
        Some((value * inv, sum))
    }

    /// An augmented copy of an example (crop with its context band, flip, jitter), drawn
    /// from `rng`; fails only when a stored example's cache entry cannot be read.
    pub fn augment(
        &self,
        ex: &Example,
        rng: &mut ChaCha8Rng,
        backbone: Option<&dyn Backbone>,
    ) -> Result<Draw, HeadsError> {
        let o = &self.options;
        let p = self.head.config.patch;
        let (gh, gw) = ex.features.grid();
        let (rows, cols) = o.crop.map_or((gh, gw), |(r, c)| (r.min(gh), c.min(gw)));
        let r0 = rng.gen_range(0..=gh - rows);
        let c0 = rng.gen_range(0..=gw - cols);
        let flip = o.flip && rng.gen_bool(0.5);
        // The labelled crop is tokens [r0, r0 + rows) x [c0, c0 + cols); the features span
        // `crop_context` more tokens on each side where the image has them (none without a
        // crop, which is the whole image).
        let inner = (r0 * p..(r0 + rows) * p, c0 * p..(c0 + cols) * p);
        let m = o.crop_context;
        let (r1, c1) = ((r0 + rows + m).min(gh), (c0 + cols + m).min(gw));
        let (r0, c0) = (r0.saturating_sub(m), c0.saturating_sub(m));
        let (rows, cols) = (r1 - r0, c1 - c0);
        let features = match backbone {
            Some(bb) if o.jitter > 0.0 => {
                bb.extract(&jitter(&ex.sample.image, o.jitter, rng)).crop(r0, c0, rows, cols, flip)
            }
            _ => ex.features.load()?.crop(r0, c0, rows, cols, flip),
        };
        let w = ex.sample.image.width() as usize;
        let (ph, pw) = (rows * p, cols * p);
        // Source pixel of draw pixel `i`, or None in the context band.
        let pick = |i: usize| {
            let (sx, sy) = (c0 * p + if flip { pw - 1 - i % pw } else { i % pw }, r0 * p + i / pw);
            (inner.0.contains(&sy) && inner.1.contains(&sx)).then_some(sy * w + sx)
        };
        let target = match &ex.sample.target {
            Target::Labels(l) => Target::Labels((0..ph * pw).map(|i| pick(i).map_or(IGNORE, |j| l[j])).collect()),
            Target::Depth(d) => Target::Depth((0..ph * pw).map(|i| pick(i).map_or(0.0, |j| d[j])).collect()),
        };
        Ok(Draw { features, target, size: (ph, pw) })
    }

    /// Trains to the end of `options.epochs`, validating after every epoch, checkpointing to
    /// `checkpoint` (if given) every `checkpoint_every` steps and after each epoch. `stop_after`
    /// ends early after that many steps in total (as an interruption would). `backbone` is
    /// needed only for colour jitter.
    pub fn fit(
        &mut self,
        train: &[Example],
        val: &[Example],
        backbone: Option<&dyn Backbone>,
        checkpoint: Option<&Path>,
        stop_after: Option<usize>,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<(), HeadsError> {
        if train.is_empty() {
            return Err(HeadsError::invalid("no training examples"));
        }
        let per_epoch = self.steps_per_epoch(train);
        let total = per_epoch * self.options.epochs;
        let mut order: Option<(usize, Vec<usize>)> = None; // (epoch, its draws)
        while self.step < total {
            if stop_after.is_some_and(|s| self.step >= s) {
                return Ok(());
            }
            let epoch = self.step / per_epoch;
            if order.as_ref().is_none_or(|(e, _)| *e != epoch) {
                order = Some((epoch, self.epoch_order(train, epoch)));
            }
            let order = &order.as_ref().expect("set above").1;
            let within = self.step % per_epoch;
            let idx = &order[within * self.options.batch..((within + 1) * self.options.batch).min(order.len())];
            let mut rng =
                ChaCha8Rng::seed_from_u64(self.options.seed.wrapping_mul(6364136223846793005) ^ self.step as u64);
            let batch =
                idx.iter().map(|&i| self.augment(&train[i], &mut rng, backbone)).collect::<Result<Vec<_>, _>>()?;
            let lr = self.lr_at(self.step, total);
            let loss = self.train_step(&batch, lr);
            self.step += 1;
            let mut validation = None;
            if self.step.is_multiple_of(per_epoch) {
                let (mut v, confusion) = evaluate_confusion(&self.head, val, self.options.depth_loss.align())?;
                self.confusion = Some(confusion);
                v.epoch = self.step / per_epoch;
                self.history.push(v);
                validation = Some(v);
            }
            if let Some(dir) = checkpoint {
                if self.step.is_multiple_of(self.options.checkpoint_every.max(1)) || validation.is_some() {
                    self.save(dir)?;
                }
            }
            progress(Progress { step: self.step, steps: total, loss: loss.unwrap_or(f32::NAN), lr, validation });
        }
        Ok(())
    }
}

/// Segmentation or depth metrics of a head on examples (whole images, plain CPU device).
/// Depth is scored as predicted for SILog heads, and after the per-image least-squares scale
/// and shift for affine-invariant ones.
pub fn evaluate(head: &Head, examples: &[Example], depth_loss: DepthLoss) -> Result<Validation, HeadsError> {
    Ok(evaluate_confusion(head, examples, depth_loss.align())?.0)
}

/// [`evaluate`] with depth aligned by `align` before scoring, and the segmentation confusion
/// matrix (rows = ground truth) for per-class IoU.
pub fn evaluate_confusion(
    head: &Head,
    examples: &[Example],
    align: DepthAlign,
) -> Result<(Validation, Confusion), HeadsError> {
    let device = Device::flex();
    let params = head.tensors(&device);
    let mut conf = Confusion::new(head.config.task.channels());
    let mut depth = DepthStats::default();
    for ex in examples {
        let (w, h) = (ex.sample.image.width() as usize, ex.sample.image.height() as usize);
        let f = ex.features.load()?;
        let feats: Vec<Tensor<4>> = head.config.layers.iter().map(|&l| f.tensor(l, &device)).collect();
        let out = head.forward_with(&params, &feats, (h, w));
        match &ex.sample.target {
            Target::Labels(l) => conf.add(&argmax_channels(&to_vec(out), conf.k, h * w), l),
            Target::Depth(d) => depth.add(to_vec(out.exp()), d, w, h, align),
        }
    }
    let v = Validation {
        epoch: 0,
        miou: conf.miou(),
        pixel_accuracy: conf.pixel_accuracy(),
        abs_rel: depth.abs_rel(),
        delta1: depth.delta1(),
    };
    Ok((v, conf))
}

/// Per-pixel argmax over `k` channel planes of `n` pixels.
pub fn argmax_channels(v: &[f32], k: usize, n: usize) -> Vec<u16> {
    (0..n)
        .map(|px| {
            let mut best = 0;
            for c in 1..k {
                if v[c * n + px] > v[best * n + px] {
                    best = c;
                }
            }
            best as u16
        })
        .collect()
}

/// Brightness, contrast and saturation jitter by factors in `1 +- s`.
pub fn jitter(img: &image::RgbImage, s: f32, rng: &mut ChaCha8Rng) -> image::RgbImage {
    let (b, c, sat) = (1.0 + rng.gen_range(-s..s), 1.0 + rng.gen_range(-s..s), 1.0 + rng.gen_range(-s..s));
    let mean: f32 = img.pixels().map(|p| (p[0] as f32 + p[1] as f32 + p[2] as f32) / 3.0).sum::<f32>()
        / (img.len() / 3).max(1) as f32;
    let mut out = img.clone();
    for p in out.pixels_mut() {
        let grey = (p[0] as f32 + p[1] as f32 + p[2] as f32) / 3.0;
        for ch in 0..3 {
            let mut v = p[ch] as f32 * b;
            v = grey * b + (v - grey * b) * sat;
            v = mean + (v - mean) * c;
            p[ch] = v.round().clamp(0.0, 255.0) as u8;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::HeadConfig;

    /// The CPU step's examples as graphs of their own give the batch mean's loss and
    /// gradients (the batch as one graph), for a DPT head on a segmentation batch with one
    /// example that has no usable target (it counts in neither), and for a depth head.
    #[test]
    fn examples_apart_give_the_batch_mean() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (grid, dims) = ((4usize, 5usize), vec![6usize]);
        let features = |rng: &mut ChaCha8Rng| FeatureMaps {
            grid,
            dims: dims.clone(),
            layers: vec![(0..6 * grid.0 * grid.1).map(|_| rng.gen_range(-1.0f32..1.0)).collect()],
            pixel_layers: Vec::new(),
        };
        let n = grid.0 * grid.1 * 4;
        for task in [Task::Seg { classes: (0..3).map(|i| format!("c{i}")).collect() }, Task::Depth] {
            let seg = matches!(task, Task::Seg { .. });
            let config = HeadConfig {
                kind: "dpt".into(),
                task,
                backbone: "test".into(),
                patch: 2,
                layers: vec![0, 0, 0, 0],
                in_dims: vec![6; 4],
                width: 8,
                widths: Vec::new(),
                size: 0,
            };
            let trainer =
                Trainer::new(Head::new(config, 5).unwrap(), TrainOptions::default(), Device::autodiff(Device::flex()))
                    .unwrap();
            let batch: Vec<Draw> = (0..5)
                .map(|i| {
                    let target = match (seg, i) {
                        (true, 2) => Target::Labels(vec![IGNORE; n]),
                        (true, _) => Target::Labels((0..n).map(|_| rng.gen_range(0..3u16)).collect()),
                        (false, _) => Target::Depth((0..n).map(|_| rng.gen_range(0.5f32..3.0)).collect()),
                    };
                    Draw { features: features(&mut rng), target, size: (grid.0 * 2, grid.1 * 2) }
                })
                .collect();
            let (v1, g1) = trainer.batch_gradients(&batch).unwrap();
            let (v2, g2) = trainer.example_gradients(&batch).unwrap();
            assert!((v1 - v2).abs() <= 1e-5 * v1.abs(), "loss {v1} vs {v2}");
            let largest = g1.iter().flatten().flatten().fold(0f32, |m, x| m.max(x.abs()));
            assert!(largest > 0.0);
            for (a, b) in g1.iter().zip(&g2) {
                let (a, b) = (a.as_ref().unwrap(), b.as_ref().unwrap());
                for (x, y) in a.iter().zip(b) {
                    assert!((x - y).abs() <= 1e-5 * largest, "gradient {x} as one graph vs {y} apart");
                }
            }
        }
    }
}
