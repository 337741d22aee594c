//! The training loop: pairs drawn from scene folders, the stage's weighted losses on the
//! network's one forward (every parameter tracked by autodiff unless frozen), AdamW with
//! warm-up and cosine decay, global gradient-norm clipping, checkpoints that resume exactly
//! (each step's draw and augmentation are seeded by its index), and a JSONL log.

use crate::augment::{jitter, to_grey, Degradation};
use crate::loss::{conf_regr3d, matching_loss, normal_l1, pointmap_normal_loss, ssi_depth_l1, Matches, RegrView};
use crate::pair::{covisibility, crop_window, missing_depth, pair_target, PairTarget, View};
use crate::TrainError;
use burn::tensor::{Device, Tensor, TensorData};
use dens3r_backbone::{Dens3r, Freeze, HeadOutputs, Params, Weights};
use dens3r_optim::{AdamW, At, WarmupCosine};
use dens3r_scene::{Layer, Scene};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Which of the paper's two stages runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Stage {
    /// Scale-invariant pointmaps with matching: `1.0 pts_glb + 0.1 pts_n + 0.075 match`.
    One,
    /// Intrinsic-invariant pointmaps with normal supervision: `1.0 pts_glb + 0.1 pts_n + 1.0 n`.
    Two,
}

impl Stage {
    /// Loss weights `(pts_glb, pts_n, match, n)`.
    pub fn weights(self) -> [f32; 4] {
        match self {
            Self::One => [1.0, 0.1, 0.075, 0.0],
            Self::Two => [1.0, 0.1, 0.0, 1.0],
        }
    }
}

/// The camera frame view 2's ground truth is regressed in (spec section 5, Regr3D's
/// `align_pts`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PointsFrame {
    /// View 1's ('global': the released model; `reconstruct` reads view 2's points there).
    #[default]
    First,
    /// Its own ('local', `align_pts=False`): each view's points in its own camera frame, view
    /// 2's normal target its own too.
    Own,
}

impl PointsFrame {
    /// `first` or `own`.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "first" => Some(Self::First),
            "own" => Some(Self::Own),
            _ => None,
        }
    }
}

fn is_first(f: &PointsFrame) -> bool {
    *f == PointsFrame::First
}

fn is_zero(x: &f32) -> bool {
    *x == 0.0
}

fn is_one(x: &f32) -> bool {
    *x == 1.0
}

fn one_f32() -> f32 {
    1.0
}

/// How far from straight down a view may look for [`TrainConfig::roll_top_down`] (degrees).
pub const TOP_DOWN_DEG: f64 = 40.0;

/// Settings of a run; a resumed run must have the same.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Stage.
    pub stage: Stage,
    /// Network input `(W, H)`, multiples of the patch size.
    pub size: (usize, usize),
    /// Optimiser steps.
    pub steps: usize,
    /// Pairs per step.
    pub batch: usize,
    /// Peak learning rate.
    pub lr: f32,
    /// Fraction of the steps spent warming up linearly.
    pub warmup: f32,
    /// Decoupled weight decay (AdamW) on weight matrices.
    pub weight_decay: f32,
    /// Global gradient-norm limit (0 = off).
    pub clip: f32,
    /// ConfLoss alpha of the 3-D regression (0.2).
    pub alpha: f32,
    /// InfoNCE temperature (0.05) and ConfMatchingLoss alpha (10).
    pub match_temperature: f32,
    /// See `match_temperature`.
    pub match_alpha: f32,
    /// Ground-truth correspondences sampled per pair.
    pub n_corres: usize,
    /// The matching loss's InfoNCE blocks: correspondences beyond this many per pair are
    /// scored in block-diagonal chunks (MASt3R's `blocksize`, 8192).
    #[serde(default = "match_block")]
    pub match_block: usize,
    /// Loss weights `(pts_glb, pts_n, match, n)` replacing the stage's (e.g. a matching
    /// warm-up: `0,0,1,0`); `None` = the paper's for the stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_weights: Option<[f32; 4]>,
    /// Pairs are drawn among ordered frame pairs of one scene whose co-visibility lies in
    /// this range.
    pub covis: (f64, f64),
    /// Colour jitter amplitude (brightness / contrast / saturation, multiplicative).
    pub jitter: f32,
    /// Random crops: each view's window is the largest of the step's aspect scaled by a
    /// factor drawn in `[crop, 1]` at a random place (1 = centre crops only).
    #[serde(default = "one")]
    pub crop: f32,
    /// Random aspect ratios: each step's size keeps the long side of `size` and draws the
    /// short side among multiples of the patch size from half to all of it, transposed
    /// when the first pair's first frame is portrait (false = always `size`).
    #[serde(default)]
    pub aspects: bool,
    /// Fraction of pairs that are one view paired with itself (the same window), as a single
    /// image runs at inference (`predict`); 0 = distinct views only.
    #[serde(default)]
    pub self_pairs: f32,
    /// Probability of turning a pair upside down (both views, cameras rolled 180 degrees)
    /// when its first view looks down within [`TOP_DOWN_DEG`] of vertical: such views (a
    /// table or a tote from above) have no upright, and without it the network learns the
    /// rooms' "higher in the image is farther" (0 = never).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub roll_top_down: f32,
    /// Probability that a view gets a camera's degradations ([`Degradation::draw`]:
    /// vignetting, white balance, blur, tone curve, noise) after its colour jitter; renders
    /// lack them and photographs have them (0 = never).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub degrade: f32,
    /// Probability that a pair is shown in grey (both views, as a monochrome camera gives
    /// them, after their jitter and degradations: [`to_grey`]) (0 = never).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub grey: f32,
    /// Strength of the encoder tokens' statistics jitter on half the pairs ([`style_jitter`]:
    /// each channel's mean and spread over the tokens moved by this times Gaussian draws),
    /// so the decoder and heads do not lean on the renders' feature statistics (0 = off).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub style_jitter: f32,
    /// Weight of a scale-and-shift-invariant depth loss on view 1 ([`loss::ssi_depth_l1`]),
    /// added to the stage's terms (0 = off, as the paper).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub depth_ssi: f32,
    /// Learning-rate factor of the encoder taps' projections (`enc_taps.*`, which start at
    /// zero when added to a trained network) over `lr` (1 = the same).
    #[serde(default = "one_f32", skip_serializing_if = "is_one")]
    pub taps_lr_mult: f32,
    /// Frozen parameters.
    pub freeze: Freeze,
    /// Steps between checkpoints.
    pub checkpoint_every: usize,
    /// Seed of the draws and augmentations.
    pub seed: u64,
    /// The frame of view 2's regression target.
    #[serde(default, skip_serializing_if = "is_first")]
    pub frame: PointsFrame,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            stage: Stage::One,
            size: (224, 160),
            steps: 1000,
            batch: 2,
            lr: 1e-4,
            warmup: 0.05,
            weight_decay: 0.05,
            clip: 1.0,
            alpha: 0.2,
            match_temperature: 0.05,
            match_alpha: 10.0,
            n_corres: 256,
            match_block: 8192,
            loss_weights: None,
            covis: (0.1, 0.98),
            jitter: 0.2,
            crop: 1.0,
            aspects: false,
            self_pairs: 0.0,
            roll_top_down: 0.0,
            degrade: 0.0,
            grey: 0.0,
            style_jitter: 0.0,
            depth_ssi: 0.0,
            taps_lr_mult: 1.0,
            freeze: Freeze::None,
            checkpoint_every: 50,
            seed: 0,
            frame: PointsFrame::First,
        }
    }
}

impl TrainConfig {
    /// Loss weights `(pts_glb, pts_n, match, n)`: the override, else the stage's.
    pub fn weights(&self) -> [f32; 4] {
        self.loss_weights.unwrap_or_else(|| self.stage.weights())
    }

    /// Checks the settings against the network's patch size.
    pub fn check(&self, patch: usize) -> Result<(), TrainError> {
        let (w, h) = self.size;
        if w == 0 || h == 0 || !w.is_multiple_of(patch) || !h.is_multiple_of(patch) || w.max(h) > 2048 {
            return Err(TrainError::invalid(format!(
                "--size {w}x{h}: width and height must be multiples of {patch}, at most 2048"
            )));
        }
        if self.batch == 0 || self.steps == 0 || !(self.lr > 0.0 && self.lr.is_finite()) {
            return Err(TrainError::invalid("steps, batch and lr must be positive"));
        }
        if !(self.crop > 0.0 && self.crop <= 1.0) {
            return Err(TrainError::invalid(format!("--crop {}: expected a fraction in (0, 1]", self.crop)));
        }
        if !(0.0..=1.0).contains(&self.self_pairs) {
            return Err(TrainError::invalid(format!(
                "--self-pairs {}: expected a fraction in [0, 1]",
                self.self_pairs
            )));
        }
        if !(0.0..=1.0).contains(&self.roll_top_down) {
            return Err(TrainError::invalid(format!(
                "--roll-top-down {}: expected a probability in [0, 1]",
                self.roll_top_down
            )));
        }
        if !(0.0..=1.0).contains(&self.degrade) {
            return Err(TrainError::invalid(format!("--degrade {}: expected a probability in [0, 1]", self.degrade)));
        }
        if !(0.0..=1.0).contains(&self.grey) {
            return Err(TrainError::invalid(format!("--grey {}: expected a probability in [0, 1]", self.grey)));
        }
        if !(0.0..=1.0).contains(&self.style_jitter) {
            return Err(TrainError::invalid(format!(
                "--style-jitter {}: expected a strength in [0, 1]",
                self.style_jitter
            )));
        }
        if !(self.taps_lr_mult.is_finite() && self.taps_lr_mult > 0.0) {
            return Err(TrainError::invalid(format!(
                "--taps-lr-mult {}: expected a positive factor",
                self.taps_lr_mult
            )));
        }
        if !(self.depth_ssi.is_finite() && self.depth_ssi >= 0.0) {
            return Err(TrainError::invalid(format!("--depth-ssi {}: expected a non-negative weight", self.depth_ssi)));
        }
        if self.match_block == 0 {
            return Err(TrainError::invalid("the matching block size must be positive"));
        }
        if !(self.clip.is_finite() && self.clip >= 0.0) {
            return Err(TrainError::invalid(format!("gradient-norm limit {}: expected 0 (off) or more", self.clip)));
        }
        if let Some(w) = self.loss_weights {
            if w.iter().any(|x| !x.is_finite() || *x < 0.0) || w.iter().all(|x| *x == 0.0) {
                return Err(TrainError::invalid(format!(
                    "loss weights {w:?}: expected four finite, non-negative numbers, not all 0"
                )));
            }
            if self.stage == Stage::One && w[3] > 0.0 {
                return Err(TrainError::invalid("stage 1 has no normal-head loss: its weight must be 0"));
            }
        }
        if self.checkpoint_every == 0 {
            return Err(TrainError::invalid("checkpoint interval must be positive"));
        }
        Ok(())
    }
}

fn one() -> f32 {
    1.0
}

fn match_block() -> usize {
    8192
}

/// The loss terms of one step (unweighted) and their weighted total.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LossTerms {
    /// Weighted total.
    pub loss: f32,
    /// ConfLoss 3-D regression, view 2 in view 1's frame.
    pub pts_glb: f32,
    /// Normals of the predicted pointmaps against the ground truth.
    pub pts_n: f32,
    /// Matching (stage 1).
    #[serde(rename = "match")]
    pub matching: Option<f32>,
    /// Normal head L1 (stage 2).
    pub n: Option<f32>,
    /// Scale-and-shift-invariant depth of view 1 (when weighted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ssi: Option<f32>,
}

/// A batch on the device.
pub struct Batch {
    /// Normalised images `(B, 3, H, W)` of view 1 and view 2.
    pub images: [Tensor<4>; 2],
    /// Ground truth per sample.
    pub targets: Vec<PairTarget>,
    /// Per sample, the seed of its encoder-statistics jitter when it gets one
    /// ([`TrainConfig::style_jitter`]); empty = none.
    pub style: Vec<Option<u64>>,
}

impl Batch {
    /// Each pair as a batch of its own.
    pub fn pairs(&self) -> Vec<Batch> {
        (0..self.targets.len())
            .map(|k| Batch {
                images: self.images.clone().map(|t| t.narrow(0, k, 1)),
                targets: vec![self.targets[k].clone()],
                style: self.style.get(k).map(|s| vec![*s]).unwrap_or_default(),
            })
            .collect()
    }
}

/// The denominators of a batch's loss terms, counted on its ground truth: the valid pixels of
/// each view (3-D regression), those of them with a ground-truth normal (pointmap normals in
/// view 1's frame; the normal head's, in each view's own), the pairs and the correspondences.
/// Given with a shard of the batch, they make the shard's terms its share of the batch's
/// means, so the shards' terms and gradients add up to the whole batch's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BatchCounts {
    valid: [f32; 2],
    pts_n: [f32; 2],
    normals: [f32; 2],
    pairs: usize,
    matches: usize,
}

impl BatchCounts {
    /// The counts of the batch with these targets under `cfg` (which frame view 2's targets
    /// are in).
    pub fn of(targets: &[PairTarget], cfg: &TrainConfig) -> Self {
        let own2 = cfg.frame == PointsFrame::Own;
        let count = |f: &dyn Fn(&PairTarget, usize) -> bool, k: usize| {
            targets.iter().map(|t| (0..t.valid[k].len()).filter(|&i| f(t, i)).count()).sum::<usize>() as f32
        };
        let has = |n: &[Vec3], i: usize| n[i].abs().element_sum() > 0.0;
        fn in1(t: &PairTarget, k: usize, own2: bool) -> &[Vec3] {
            if k == 1 && own2 {
                &t.normals[1]
            } else {
                &t.normals_in1[k]
            }
        }
        Self {
            valid: [0, 1].map(|k| count(&|t, i| t.valid[k][i], k)),
            pts_n: [0, 1].map(|k| count(&|t, i| t.valid[k][i] && has(in1(t, k, own2), i), k)),
            normals: [0, 1].map(|k| count(&|t, i| t.valid[k][i] && has(&t.normals[k], i), k)),
            pairs: targets.len(),
            matches: targets.iter().map(|t| t.matches.idx1.len()).sum(),
        }
    }
}

impl LossTerms {
    /// Adds `other`'s terms (a term present in either is present in the sum).
    pub fn add(&mut self, other: &LossTerms) {
        let add = |a: Option<f32>, b: Option<f32>| match (a, b) {
            (None, None) => None,
            (a, b) => Some(a.unwrap_or(0.0) + b.unwrap_or(0.0)),
        };
        self.loss += other.loss;
        self.pts_glb += other.pts_glb;
        self.pts_n += other.pts_n;
        self.matching = add(self.matching, other.matching);
        self.n = add(self.n, other.n);
        self.ssi = add(self.ssi, other.ssi);
    }
}

fn vec3_tensor(v: &[&[Vec3]], (h, w): (usize, usize), device: &Device) -> Tensor<4> {
    let flat: Vec<f32> = v.iter().flat_map(|s| s.iter().flat_map(|p| p.to_array())).collect();
    Tensor::from_data(TensorData::new(flat, [v.len(), h, w, 3]), device)
}

fn mask_tensor(v: &[&[bool]], (h, w): (usize, usize), device: &Device) -> Tensor<3> {
    let flat: Vec<f32> = v.iter().flat_map(|s| s.iter().map(|&b| b as u8 as f32)).collect();
    Tensor::from_data(TensorData::new(flat, [v.len(), h, w]), device)
}

/// `(x / 255 - 0.5) / 0.5` of RGB pixels as `(3, H, W)`: the network's input normalisation.
pub fn normalise(img: &image::RgbImage) -> Vec<f32> {
    use dens3r_backbone::preprocess::{normalised_planes, DENS3R_MEAN, DENS3R_STD};
    normalised_planes(img, DENS3R_MEAN, DENS3R_STD)
}

/// Whether any term with a positive weight entered the batch's loss (the matching term needs
/// correspondences, so a batch without any has none).
fn trained_term(cfg: &TrainConfig, t: &LossTerms) -> bool {
    let [w_glb, w_n, w_match, w_normal] = cfg.weights();
    w_glb > 0.0
        || w_n > 0.0
        || (w_match > 0.0 && t.matching.is_some())
        || (w_normal > 0.0 && t.n.is_some())
        || cfg.depth_ssi > 0.0
}

/// Both views' encoder tokens `(B, N, D)` with each channel's mean and spread over the tokens
/// moved, the same way in both views of a sample (one scene, one look): `e + a ((e - mu) eps_s
/// + sigma eps_m)`, `eps` standard normal per channel drawn from the sample's seed (none: left
/// as it is): the spread scaled by `1 + a eps_s`, the mean shifted by `a eps_m` spreads.
pub fn style_jitter(views: [Tensor<3>; 2], a: f32, seeds: &[Option<u64>]) -> [Tensor<3>; 2] {
    let [b, _, d] = views[0].dims();
    let device = views[0].device();
    let (mut es, mut em) = (vec![0.0f32; b * d], vec![0.0f32; b * d]);
    for (k, seed) in seeds.iter().enumerate().take(b) {
        let Some(seed) = seed else { continue };
        let mut rng = ChaCha8Rng::seed_from_u64(*seed);
        // Box-Muller: a standard normal from two uniforms.
        let mut normal = || {
            let (u, t): (f32, f32) = (rng.gen_range(f32::EPSILON..1.0), rng.gen_range(0.0..1.0));
            a * (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * t).cos()
        };
        es[k * d..(k + 1) * d].iter_mut().for_each(|e| *e = normal());
        em[k * d..(k + 1) * d].iter_mut().for_each(|e| *e = normal());
    }
    let t = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [b, 1, d]), &device);
    let (eps_s, eps_m) = (t(es), t(em));
    views.map(|e| {
        let mu = e.clone().mean_dim(1);
        let centred = e.clone() - mu;
        let sigma = (centred.clone() * centred.clone()).mean_dim(1).add_scalar(1e-6).sqrt();
        e + centred * eps_s.clone() + sigma * eps_m.clone()
    })
}

/// The weighted loss of a batch under `stage` (and each term), from the network's outputs.
pub fn batch_loss(model: &Dens3r, batch: &Batch, cfg: &TrainConfig) -> Result<(Tensor<1>, LossTerms), TrainError> {
    shard_loss(model, batch, cfg, &BatchCounts::of(&batch.targets, cfg))
}

/// The weighted loss of `batch` as a shard of a larger batch with counts `whole`: its share of
/// that batch's loss and terms (the whole batch's loss when it is that batch).
pub fn shard_loss(
    model: &Dens3r,
    batch: &Batch,
    cfg: &TrainConfig,
    whole: &BatchCounts,
) -> Result<(Tensor<1>, LossTerms), TrainError> {
    let device = model.device().clone();
    let [img1, img2] = batch.images.clone();
    let [w_glb, w_n, w_match, w_normal] = cfg.weights();
    // Only the outputs the stage's losses read (stage 1 skips the normal head's DPT).
    let want = HeadOutputs { normal: w_normal > 0.0, desc: w_match > 0.0 };
    let features = if cfg.style_jitter > 0.0 && batch.style.iter().any(Option::is_some) {
        let [(e1, g1), (e2, g2)] = model.encode_images(img1, img2);
        let [e1, e2] = style_jitter([e1, e2], cfg.style_jitter, &batch.style);
        model.decode(e1, g1, e2, g2)
    } else {
        model.encode(img1, img2)
    };
    let pred = model.heads_with(&features, want);
    let [p1, p2] = &pred.views;
    let t = &batch.targets;
    let size = t[0].size;
    // View 2's target: in view 1's frame, or in its own (`PointsFrame::Own`).
    let own2 = cfg.frame == PointsFrame::Own;
    let view = |k: usize| {
        let pts: Vec<&[Vec3]> =
            t.iter().map(|s| if k == 1 && own2 { s.pts_own[1].as_slice() } else { s.pts[k].as_slice() }).collect();
        let valid: Vec<&[bool]> = t.iter().map(|s| s.valid[k].as_slice()).collect();
        (vec3_tensor(&pts, size, &device), mask_tensor(&valid, size, &device))
    };
    let ((g1, m1), (g2, m2)) = (view(0), view(1));
    let no_conf = || TrainError::invalid("the network has no confidence channel; train a Dens3R with conf");
    let regr = |p: &dens3r_backbone::ViewPrediction, gt: Tensor<4>, valid: Tensor<3>, k: usize| {
        let conf = p.conf.clone().ok_or_else(no_conf)?;
        Ok::<_, TrainError>(RegrView { pred: p.pts3d.clone(), conf, gt, valid, count: Some(whole.valid[k]) })
    };
    let pts_glb = conf_regr3d(regr(p1, g1.clone(), m1.clone(), 0)?, regr(p2, g2, m2.clone(), 1)?, cfg.alpha);
    let n_in1 = |k: usize| {
        let n: Vec<&[Vec3]> = t
            .iter()
            .map(|s| if k == 1 && own2 { s.normals[1].as_slice() } else { s.normals_in1[k].as_slice() })
            .collect();
        vec3_tensor(&n, size, &device)
    };
    let pts_n = pointmap_normal_loss(
        [p1.pts3d.clone(), p2.pts3d.clone()],
        [n_in1(0), n_in1(1)],
        [m1.clone(), m2.clone()],
        whole.pts_n.map(Some),
    );
    // Terms weighted 0 stay out of the total (and of the gradient), so a NaN in a term that
    // is not trained cannot poison the step.
    let mut total = Tensor::<1>::zeros([1], &device);
    for (x, w) in [(&pts_glb, w_glb), (&pts_n, w_n)] {
        if w > 0.0 {
            total = total + x.clone().mul_scalar(w);
        }
    }
    let value = |x: &Tensor<1>| x.clone().into_data().try_to_vec::<f32>().map(|v| v[0]).unwrap_or(f32::NAN);
    let mut terms = LossTerms { pts_glb: value(&pts_glb), pts_n: value(&pts_n), ..Default::default() };
    if cfg.depth_ssi > 0.0 {
        let z = |p: Tensor<4>| {
            let [b, h, w, _] = p.dims();
            p.narrow(3, 2, 1).reshape([b, h, w])
        };
        let ssi = ssi_depth_l1(z(p1.pts3d.clone()), z(g1.clone()), m1.clone(), Some(whole.pairs));
        terms.ssi = Some(value(&ssi));
        total = total + ssi.mul_scalar(cfg.depth_ssi);
    }
    if w_match > 0.0 {
        let (d1, d2) = (p1.desc.clone(), p2.desc.clone());
        let (c1, c2) = (p1.desc_conf.clone(), p2.desc_conf.clone());
        let (Some(d1), Some(d2), Some(c1), Some(c2)) = (d1, d2, c1, c2) else {
            return Err(TrainError::invalid("stage 1 trains matching: the network needs descriptors"));
        };
        let matches: Vec<Matches> = t.iter().map(|s| s.matches.clone()).collect();
        let (tau, alpha, block) = (cfg.match_temperature, cfg.match_alpha, cfg.match_block);
        if let Some(m) = matching_loss([d1, d2], [c1, c2], &matches, tau, alpha, block, Some(whole.matches)) {
            terms.matching = Some(value(&m));
            total = total + m.mul_scalar(w_match);
        }
    }
    if w_normal > 0.0 {
        let (Some(n1), Some(n2)) = (p1.normal.clone(), p2.normal.clone()) else {
            return Err(TrainError::invalid("stage 2 trains the normal head: the network needs one"));
        };
        let own = |k: usize| {
            let n: Vec<&[Vec3]> = t.iter().map(|s| s.normals[k].as_slice()).collect();
            vec3_tensor(&n, size, &device)
        };
        let [c1, c2] = whole.normals.map(Some);
        let n = normal_l1(n1, own(0), m1, c1) + normal_l1(n2, own(1), m2, c2);
        terms.n = Some(value(&n));
        total = total + n.mul_scalar(w_normal);
    }
    terms.loss = value(&total);
    Ok((total, terms))
}

/// Training pairs: scene folders (frames read from disk when a batch needs them, so a large
/// dataset is not held in memory) and the ordered frame pairs whose co-visibility falls in the
/// configured range: read from the scene's `pairs.json` (written by `dens3r synth`) or
/// measured on the frames at network size.
pub struct Dataset {
    /// The scenes.
    pub scenes: Vec<Scene>,
    /// `(scene, frame 1, frame 2)`.
    pub pairs: Vec<(usize, usize, usize)>,
}

/// Scene folders under `dirs`: each one that holds `cameras.json`, else its sub-folders that
/// do (sorted by name; e.g. a `dens3r synth` output).
pub fn scene_dirs(dirs: &[PathBuf]) -> Result<Vec<PathBuf>, TrainError> {
    let mut out = Vec::new();
    for d in dirs {
        if d.join("cameras.json").is_file() {
            out.push(d.clone());
            continue;
        }
        if !d.is_dir() {
            return Err(TrainError::file(d, "no such scene folder; give scene folders or a `dens3r synth` output"));
        }
        let mut subs: Vec<PathBuf> = std::fs::read_dir(d)
            .map_err(|e| TrainError::file(d, format!("cannot list ({e})")))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.join("cameras.json").is_file() && !p.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.'))
            })
            .collect();
        if subs.is_empty() {
            return Err(TrainError::file(d, "neither a scene folder (no cameras.json) nor a folder of scene folders"));
        }
        subs.sort();
        out.extend(subs);
    }
    Ok(out)
}

impl Dataset {
    /// Opens scene folders (or folders of them, see [`scene_dirs`]; each frame with depth
    /// and a pose) and lists their pairs; co-visibility without `pairs.json` is measured at
    /// `size`.
    pub fn load(dirs: &[PathBuf], size: (usize, usize), covis: (f64, f64)) -> Result<Self, TrainError> {
        let mut scenes = Vec::new();
        let mut pairs = Vec::new();
        for (s, d) in scene_dirs(dirs)?.iter().enumerate() {
            let scene = Scene::open(d)?;
            for f in scene.frames() {
                if !scene.has(f, Layer::Depth) {
                    return Err(missing_depth(&scene, f));
                }
            }
            let n = scene.frames().len();
            let listed = crate::synth::read_pairs(&scene)?;
            let measured;
            let table: &[f64] = match &listed {
                Some(t) => t,
                None => {
                    let views =
                        scene.frames().iter().map(|f| View::load(&scene, f, size)).collect::<Result<Vec<_>, _>>()?;
                    measured = (0..n * n)
                        .map(|k| if k / n == k % n { 0.0 } else { covisibility(&views[k / n], &views[k % n]) })
                        .collect::<Vec<_>>();
                    &measured
                }
            };
            for i in 0..n {
                for j in 0..n {
                    let c = table[i * n + j];
                    if i != j && c >= covis.0 && c <= covis.1 {
                        pairs.push((s, i, j));
                    }
                }
            }
            scenes.push(scene);
        }
        if pairs.is_empty() {
            return Err(TrainError::invalid(format!(
                "no training pair: no two frames of {} see each other with co-visibility in [{}, {}]",
                dirs.iter().map(|d| d.display().to_string()).collect::<Vec<_>>().join(", "),
                covis.0,
                covis.1
            )));
        }
        Ok(Self { scenes, pairs })
    }

    /// Checks that every frame has normals (stage 2 supervises the normal head with them).
    pub fn require_normals(&self) -> Result<(), TrainError> {
        for scene in &self.scenes {
            if let Some(f) = scene.frames().iter().find(|f| !scene.has(f, Layer::Normals)) {
                return Err(TrainError::file(scene.root(), format!("frame '{}' has no normals/{}.npy; stage 2 supervises the normal head (render or synthesise the scene, or train stage 1)", f.name, f.name)));
            }
        }
        Ok(())
    }

    /// The network size of step `step` (see [`TrainConfig::aspects`]) for a first frame of
    /// `(fw, fh)` pixels.
    pub fn step_size(
        cfg: &TrainConfig,
        patch: usize,
        (fw, fh): (usize, usize),
        rng: &mut ChaCha8Rng,
    ) -> (usize, usize) {
        if !cfg.aspects {
            return cfg.size;
        }
        let long = cfg.size.0.max(cfg.size.1);
        let lo = (long / 2).div_ceil(patch).max(1);
        let short = rng.gen_range(lo..=long / patch) * patch;
        if fh > fw {
            (short, long)
        } else {
            (long, short)
        }
    }

    /// The batch of step `step`: pairs drawn, windows cropped and images jittered by
    /// `(seed, step)`, `n_corres` correspondences sampled per pair; `patch` is the network's
    /// patch size.
    pub fn batch(&self, cfg: &TrainConfig, patch: usize, step: usize, device: &Device) -> Result<Batch, TrainError> {
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed ^ (step as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        // The degradations draw from a stream of their own, so turning them on changes the
        // images only: the pairs, crops, jitter and correspondences stay as drawn without them.
        let mut degrade_rng = rng.clone();
        degrade_rng.set_stream(1);
        let mut style_rng = rng.clone();
        style_rng.set_stream(2);
        let mut grey_rng = rng.clone();
        grey_rng.set_stream(3);
        let mut style = Vec::new();
        let picks: Vec<(usize, usize, usize)> =
            (0..cfg.batch).map(|_| self.pairs[rng.gen_range(0..self.pairs.len())]).collect();
        let first = &self.scenes[picks[0].0].frames()[picks[0].1];
        let (w, h) = Self::step_size(cfg, patch, (first.width, first.height), &mut rng);
        let mut imgs = [Vec::new(), Vec::new()];
        let mut targets = Vec::with_capacity(cfg.batch);
        for (s, i, j) in picks {
            let scene = &self.scenes[s];
            // A self pair reuses view 1 (the draw is skipped at 0: older runs resume exactly).
            let own = cfg.self_pairs > 0.0 && rng.gen_range(0.0f32..1.0) < cfg.self_pairs;
            let mut load = |k: usize| {
                let f = &scene.frames()[k];
                let scale = if cfg.crop < 1.0 { rng.gen_range(cfg.crop as f64..=1.0) } else { 1.0 };
                let at = if cfg.crop < 1.0 { (rng.gen_range(0.0..=1.0), rng.gen_range(0.0..=1.0)) } else { (0.5, 0.5) };
                View::load_window(scene, f, crop_window((f.width, f.height), (w, h), scale, at), (w, h))
            };
            let mut v1 = load(i)?;
            let mut v2 = if own { v1.clone() } else { load(j)? };
            // The draw is skipped at 0, so older runs resume exactly.
            if cfg.roll_top_down > 0.0 && v1.looks_down(TOP_DOWN_DEG) && rng.gen_range(0.0f32..1.0) < cfg.roll_top_down
            {
                (v1, v2) = (v1.rotated_180(), v2.rotated_180());
            }
            let mut t = pair_target(&v1, &v2);
            t.matches = sample_matches(&t.matches, cfg.n_corres, &mut rng);
            let grey = cfg.grey > 0.0 && grey_rng.gen_range(0.0f32..1.0) < cfg.grey;
            for (k, v) in [&v1, &v2].into_iter().enumerate() {
                let mut img = jitter(normalise(&v.image), cfg.jitter, &mut rng);
                if cfg.degrade > 0.0 && degrade_rng.gen_range(0.0f32..1.0) < cfg.degrade {
                    Degradation::draw(&mut degrade_rng).apply(&mut img, (w, h), &mut degrade_rng);
                }
                if grey {
                    to_grey(&mut img);
                }
                imgs[k].extend(img);
            }
            targets.push(t);
            if cfg.style_jitter > 0.0 {
                style.push((style_rng.gen_range(0.0f32..1.0) < 0.5).then(|| style_rng.gen::<u64>()));
            }
        }
        let b = cfg.batch;
        let images = imgs.map(|v| Tensor::<4>::from_data(TensorData::new(v, [b, 3, h, w]), device));
        Ok(Batch { images, targets, style })
    }
}

/// Up to `n` correspondences drawn without replacement.
fn sample_matches(m: &Matches, n: usize, rng: &mut ChaCha8Rng) -> Matches {
    let picked = rand::seq::index::sample(rng, m.idx1.len(), n.min(m.idx1.len()));
    Matches { idx1: picked.iter().map(|i| m.idx1[i]).collect(), idx2: picked.iter().map(|i| m.idx2[i]).collect() }
}

/// A network being trained, with AdamW moments.
pub struct Trainer {
    /// The parameters.
    pub params: Params,
    /// Settings.
    pub config: TrainConfig,
    /// Steps done.
    pub step: usize,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    trains: Vec<bool>,
    device: Device,
}

#[derive(Serialize, Deserialize)]
struct State {
    format: String,
    config: TrainConfig,
    step: usize,
}

const STATE_FORMAT: &str = "dens3r-train/1";

/// One line of the JSONL log.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LogLine {
    /// Step index (0-based).
    pub step: usize,
    /// Learning rate used.
    pub lr: f32,
    /// Loss terms.
    #[serde(flatten)]
    pub terms: LossTerms,
    /// Gradient norm before clipping.
    pub grad_norm: f32,
    /// Mean loss terms on the held-out scenes after this step (when validated).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub val: Option<LossTerms>,
}

/// The mean loss terms of `params` on `batches` fixed batches of held-out `data` (no
/// gradients, the inference device; centre crops at `cfg.size`, no jitter, draws seeded
/// apart from training's so every validation sees the same pairs).
pub fn validate(params: &Params, data: &Dataset, cfg: &TrainConfig, batches: usize) -> Result<LossTerms, TrainError> {
    let device = Device::flex();
    // Distinct, upright views only, so scores stay comparable between runs with and without
    // self pairs or rolled top-down pairs.
    let vcfg = TrainConfig {
        crop: 1.0,
        aspects: false,
        jitter: 0.0,
        self_pairs: 0.0,
        roll_top_down: 0.0,
        degrade: 0.0,
        grey: 0.0,
        style_jitter: 0.0,
        seed: 0x5eed_0a11_d00d,
        ..cfg.clone()
    };
    let tensors = params.tensors(&device, &vec![false; params.values.len()]);
    let model = params.model(&tensors, &device);
    let n = batches.max(1);
    let mut sum = LossTerms::default();
    for k in 0..n {
        let b = data.batch(&vcfg, params.config.patch, k, &device)?;
        sum.add(&batch_loss(&model, &b, &vcfg)?.1);
    }
    let m = n as f32;
    Ok(LossTerms {
        loss: sum.loss / m,
        pts_glb: sum.pts_glb / m,
        pts_n: sum.pts_n / m,
        matching: sum.matching.map(|v| v / m),
        n: sum.n.map(|v| v / m),
        ssi: sum.ssi.map(|v| v / m),
    })
}

impl Trainer {
    /// A fresh trainer on `device` (an autodiff device, e.g. `Device::autodiff(Device::flex())`).
    pub fn new(params: Params, config: TrainConfig, device: Device) -> Result<Self, TrainError> {
        config.check(params.config.patch)?;
        let zeros: Vec<Vec<f32>> = params.values.iter().map(|v| vec![0.0; v.len()]).collect();
        let trains = params.names.iter().map(|n| config.freeze.trains(n, params.config.enc_depth)).collect();
        Ok(Self { params, config, step: 0, m: zeros.clone(), v: zeros, trains, device })
    }

    /// Learning rate at `step`: linear warm-up, then cosine decay to zero.
    pub fn lr_at(&self, step: usize) -> f32 {
        WarmupCosine { lr: self.config.lr, warmup: self.config.warmup, total: self.config.steps }.at(step)
    }

    /// One optimiser step on `batch`.
    ///
    /// On the CPU each pair of the batch is a shard with a graph and parameter leaves of its
    /// own, and as many shards as there are threads run side by side: much of a step is burn's
    /// autodiff and element-wise work on one core, so one pair at a time left the other core
    /// idle (dens3r-s continuing at 224x160, batch 2: 12 steps 14.8 s as one graph, 9.6 s as
    /// two shards). The shards' losses are their shares of the batch's means
    /// ([`BatchCounts`]), so their gradients, added in order, are the batch's (to rounding),
    /// whatever the thread count. On a GPU the batch stays one graph.
    pub fn train_step(&mut self, batch: &Batch) -> Result<LogLine, TrainError> {
        let whole = BatchCounts::of(&batch.targets, &self.config);
        let split;
        let shards: &[Batch] = if dens3r_backbone::device::is_gpu(&self.device) {
            std::slice::from_ref(batch)
        } else {
            split = batch.pairs();
            &split
        };
        let mut terms = LossTerms::default();
        let mut g: Vec<Option<Vec<f32>>> = vec![None; self.trains.len()];
        dens3r_optim::side_by_side(
            shards,
            |s| self.shard_gradients(s, &whole),
            |r| {
                let (t, gs) = r?;
                terms.add(&t);
                gs.into_iter().for_each(|gs| dens3r_optim::add_gradients(&mut g, gs));
                Ok::<(), TrainError>(())
            },
        )?;
        let lr = self.lr_at(self.step);
        // A batch none of whose weighted terms applies (e.g. only matching trains and no pair
        // has a correspondence) moves nothing.
        if !trained_term(&self.config, &terms) {
            let line = LogLine { step: self.step, lr, terms, grad_norm: 0.0, val: None };
            self.step += 1;
            return Ok(line);
        }
        let norm = dens3r_optim::global_norm(&g) as f32;
        let scale = dens3r_optim::clip_scale(norm.into(), (self.config.clip > 0.0).then_some(self.config.clip));
        let opt = AdamW { weight_decay: self.config.weight_decay, ..Default::default() };
        let step = self.step;
        let taps_lr = lr * self.config.taps_lr_mult;
        let names = &self.params.names;
        (&mut self.params.values, &mut self.m, &mut self.v, &g, &self.params.shapes, names).into_par_iter().for_each(
            |(vals, m, v, gi, shape, name)| {
                // Weight matrices decay; biases and norms do not.
                if let Some(gi) = gi {
                    let lr = if dens3r_backbone::config::is_encoder_tap(name) { taps_lr } else { lr };
                    opt.update(At::new(step, lr).scaled(scale), vals, m, v, gi, shape.len() >= 2);
                }
            },
        );
        let line = LogLine { step: self.step, lr, terms, grad_norm: norm, val: None };
        self.step += 1;
        Ok(line)
    }

    /// One shard's loss terms and, where a weighted term applies to it, the trained
    /// parameters' gradients of its share of the batch's loss.
    #[allow(clippy::type_complexity)]
    fn shard_gradients(
        &self,
        shard: &Batch,
        whole: &BatchCounts,
    ) -> Result<(LossTerms, Option<Vec<Option<Vec<f32>>>>), TrainError> {
        let tensors = self.params.tensors(&self.device, &self.trains);
        let model = self.params.model(&tensors, &self.device);
        let (loss, terms) = shard_loss(&model, shard, &self.config, whole)?;
        if !terms.loss.is_finite() {
            return Err(TrainError::invalid(format!(
                "step {}: the loss is not finite ({:?}); lower --lr",
                self.step, terms
            )));
        }
        if !trained_term(&self.config, &terms) {
            return Ok((terms, None));
        }
        let grads = loss.backward();
        let g = tensors
            .iter()
            .zip(&self.trains)
            .map(|(t, &tr)| if tr { t.grad(&grads).and_then(|g| g.into_data().try_to_vec::<f32>().ok()) } else { None })
            .collect();
        Ok((terms, Some(g)))
    }

    /// Writes the checkpoint into `dir` (parameters with official names, moments, then the
    /// state last; each file atomic).
    pub fn save(&self, dir: &Path) -> Result<(), TrainError> {
        std::fs::create_dir_all(dir).map_err(|e| TrainError::file(dir, format!("cannot create ({e})")))?;
        self.params.save(&dir.join("params.safetensors"))?;
        let mut moments = self.params.clone();
        moments.names =
            ["m", "v"].iter().flat_map(|k| self.params.names.iter().map(move |n| format!("{k}.{n}"))).collect();
        moments.shapes = [&self.params.shapes, &self.params.shapes].into_iter().flatten().cloned().collect();
        moments.values = self.m.iter().chain(&self.v).cloned().collect();
        moments.save(&dir.join("adam.safetensors"))?;
        let state = State { format: STATE_FORMAT.into(), config: self.config.clone(), step: self.step };
        dens3r_io::tensors::save_json(&dir.join("state.json"), &state)?;
        Ok(())
    }

    /// Resumes from a checkpoint folder written by [`Trainer::save`] for the same network and
    /// settings; `Ok(None)` when the folder holds none.
    pub fn resume(
        dir: &Path,
        fresh: &Params,
        config: &TrainConfig,
        device: Device,
    ) -> Result<Option<Self>, TrainError> {
        let sp = dir.join("state.json");
        if !sp.is_file() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&sp).map_err(|e| TrainError::file(&sp, format!("{e}")))?;
        let state: State = serde_json::from_str(&text)
            .map_err(|e| TrainError::file(&sp, format!("damaged checkpoint ({e}); delete the folder to start over")))?;
        if state.format != STATE_FORMAT || &state.config != config {
            return Err(TrainError::file(&sp, "the checkpoint was made with other settings; rerun with the same options, or delete the folder (or use --restart) to start over"));
        }
        let w = Weights::from_safetensors(&dir.join("params.safetensors"))?;
        let mut params = Params::from_weights(&w, &fresh.config)?;
        params.dinov2 = fresh.dinov2.clone();
        let a = Weights::from_safetensors(&dir.join("adam.safetensors"))?;
        let mut t = Self::new(params, config.clone(), device)?;
        for (i, (n, s)) in fresh.names.iter().zip(&fresh.shapes).enumerate() {
            t.m[i] = a.values(&format!("m.{n}"), s).unwrap_or_default();
            t.v[i] = a.values(&format!("v.{n}"), s).unwrap_or_default();
        }
        a.finish()?;
        t.step = state.step;
        Ok(Some(t))
    }
}
