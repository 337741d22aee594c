//! Trains segmentation heads on frozen features of the bundled rendered scenes and prints the
//! held-out mIoU of each: a DPT head and a linear probe on DINOv2 ViT-S/14 (when
//! `scripts/fetch-data.sh` has fetched it) and a DPT head on raw pixels.
//!
//!     cargo run --release -p dens3r-heads --example train_segmentation
//!
//! Every 4th view of `data-samples/orbit` and `data-samples/room` is held out.

use dens3r_heads::cache::{FeatureCache, Precision};
use dens3r_heads::data::{self, Want};
use dens3r_heads::{Backbone, Dinov2Backbone, Example, Head, HeadConfig, PixelBackbone, Task, TrainOptions, Trainer};
use std::path::Path;

fn main() -> Result<(), dens3r_heads::HeadsError> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut backbones: Vec<(&str, Box<dyn Backbone>)> = vec![("raw pixels", Box::new(PixelBackbone { patch: 14 }))];
    let onnx = root.join(".cache/data/dinov2/vit_s_focus.onnx");
    if onnx.is_file() {
        backbones.insert(0, ("DINOv2-S", Box::new(Dinov2Backbone::load(&onnx, None)?)));
    } else {
        println!("{} is absent (run scripts/fetch-data.sh): raw pixels only", onnx.display());
    }
    let cache_dir = std::env::temp_dir().join("dens3r-example-features");
    for (name, bb) in &backbones {
        let mut cache = FeatureCache::new(&cache_dir, Precision::F16);
        let (mut train, mut val) = (Vec::new(), Vec::new());
        for scene in ["orbit", "room"] {
            let samples = data::load_folder(&root.join("data-samples").join(scene), Want::Labels, 224, 14)?;
            for (i, s) in samples.into_iter().enumerate() {
                // A cache entry, read at each use: the features are not held in memory.
                let features = cache.store(bb.as_ref(), &s.image)?.into();
                let ex = Example { sample: s, features };
                if i % 4 == 3 {
                    val.push(ex)
                } else {
                    train.push(ex)
                }
            }
        }
        let classes = data::class_names(&root.join("data-samples/room"))?.unwrap_or_default();
        let dims = bb.dims();
        let kinds: &[&str] = if dims.len() > 1 { &["dpt", "linear"] } else { &["dpt"] };
        for kind in kinds {
            let layers = dens3r_heads::plan::default_layers(kind, dims.len());
            let config = HeadConfig {
                kind: kind.to_string(),
                task: Task::Seg { classes: classes.clone() },
                backbone: bb.id(),
                patch: 14,
                in_dims: layers.iter().map(|&l| dims[l]).collect(),
                layers,
                width: 32,
                widths: Vec::new(),
                size: 224,
            };
            let options = TrainOptions { epochs: 15, batch: 4, ..TrainOptions::default() };
            let mut t = Trainer::new(
                Head::new(config, 0)?,
                options,
                burn::tensor::Device::autodiff(burn::tensor::Device::flex()),
            )?;
            t.fit(&train, &val, None, None, None, &mut |_| {})?;
            let v = t.history.last().copied().unwrap_or_default();
            println!("{name:>10} {kind:>6}: held-out mIoU {:.3}, pixel accuracy {:.3}", v.miou, v.pixel_accuracy);
        }
    }
    Ok(())
}
