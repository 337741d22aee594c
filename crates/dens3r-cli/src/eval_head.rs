//! `dens3r eval head`: scores a trained head on folders it never saw (held-out scenes, real
//! images), with the image-blind constant beside depth scores.

use crate::eval::{depth_align, Align};
use crate::train_head::{class_iou_json, features};
use anyhow::{anyhow, Result};
use clap::Args;
use dens3r_geom::metrics::DepthAlign;
use dens3r_heads::cache::Precision;
use dens3r_heads::data::Target;
use dens3r_heads::infer::check_head;
use dens3r_heads::metrics::DepthStats;
use dens3r_heads::plan;
use dens3r_heads::train::evaluate_confusion;
use dens3r_heads::{Head, Task};
use serde_json::json;
use std::path::PathBuf;

#[derive(Args)]
pub struct HeadArgs {
    /// The head (`train-head`'s OUTPUT.json).
    head: PathBuf,
    /// The backbone it was trained on (as `train-head --backbone`).
    #[arg(long)]
    backbone: String,
    /// JSON with the head counts of a `dens3r:` backbone (as `train-head --config`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Folders to score on: `images/` + `labels/` (or `depth/`), or `dens3r synth` sets.
    #[arg(long, num_args = 1.., required = true)]
    data: Vec<PathBuf>,
    /// Depth alignment per image before scoring (depth heads).
    #[arg(long, value_enum, default_value_t = Align::None)]
    align: Align,
    /// Feature cache folder (default: HEAD.features/, as train-head's).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// The cache holds f16 features (as `train-head --f16` stored them).
    #[arg(long)]
    f16: bool,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(a: HeadArgs) -> Result<()> {
    let head = Head::load(&a.head).map_err(|e| anyhow!(e))?;
    let backbone = crate::model_args::open_backbone(&a.backbone, a.config.as_deref())?;
    check_head(&a.head, &head, &backbone.id(), &backbone.dims()).map_err(|e| anyhow!(e))?;
    let classes = match &head.config.task {
        Task::Seg { classes } => Some(classes.as_slice()),
        Task::Depth => None,
    };
    let patch = head.config.patch as u32;
    let (samples, unknown) = plan::load_eval(&a.data, classes, head.config.size, patch).map_err(|e| anyhow!(e))?;
    if !unknown.is_empty() {
        eprintln!("classes the head does not know, left out of the scores: {}", unknown.join(", "));
    }
    let cache_dir = a.cache.clone().unwrap_or_else(|| a.head.with_extension("features"));
    let precision = if a.f16 { Precision::F16 } else { Precision::F32 };
    let examples = features(&cache_dir, precision, backbone.as_ref(), vec![samples])?.remove(0);
    let align = depth_align(a.align);
    let (v, conf) = evaluate_confusion(&head, &examples, align).map_err(|e| anyhow!(e))?;
    let mut out = json!({ "head": a.head, "images": examples.len(), "data": a.data });
    let mut text = vec![format!("{}: {} images", a.head.display(), examples.len())];
    match &head.config.task {
        Task::Seg { classes } => {
            let ious = conf.class_ious(classes);
            out["miou"] = v.miou.into();
            out["pixel_accuracy"] = v.pixel_accuracy.into();
            out["class_iou"] = class_iou_json(&ious);
            text.push(format!("mIoU {:.4}  pixel accuracy {:.4}", v.miou, v.pixel_accuracy));
            let per: Vec<String> = ious.iter().map(|(k, v)| format!("{k} {v:.3}")).collect();
            text.push(format!("class IoU: {}", per.join(", ")));
        }
        Task::Depth => {
            // The image-blind constant: each image's ground-truth median everywhere.
            let mut constant = DepthStats::default();
            for ex in &examples {
                if let Target::Depth(d) = &ex.sample.target {
                    let (w, h) = (ex.sample.image.width() as usize, ex.sample.image.height() as usize);
                    constant.add(vec![1.0; w * h], d, w, h, DepthAlign::MedianScale);
                }
            }
            let (c_abs, c_d1) = (constant.abs_rel(), constant.delta1());
            out["align"] = format!("{align:?}").into();
            out["abs_rel"] = v.abs_rel.into();
            out["delta1"] = v.delta1.into();
            out["constant"] = json!({ "abs_rel": c_abs, "delta1": c_d1 });
            text.push(format!("AbsRel {:.4}  delta1 {:.4}  (alignment {align:?})", v.abs_rel, v.delta1));
            text.push(format!("constant (each image's median depth): AbsRel {c_abs:.4}  delta1 {c_d1:.4}"));
        }
    }
    if a.json {
        println!("{out}");
    } else {
        println!("{}", text.join("\n"));
    }
    Ok(())
}
