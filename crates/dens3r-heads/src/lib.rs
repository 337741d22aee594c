//! Trainable heads on frozen backbone features (the design card's first use: "train a
//! segmentation head on frozen features").
//!
//! [`features`] is the seam: a [`Backbone`] (Dens3R, DINOv2 or raw pixels) turns an image into
//! [`FeatureMaps`]; [`cache`] stores them on disk once per image; [`head`] holds the head
//! architectures (registry: `linear`, `dpt`, and [`pointmap`], the network's own DPT that can
//! start from a checkpoint's pointmap head) and their safetensors + JSON files; [`loss`] and
//! [`metrics`] the objectives and scores; [`data`] the labelled images; [`train`] AdamW
//! training with validation, checkpoints and resume; [`infer`] runs saved heads (one backbone
//! pass feeds every head) and writes label PNGs. The backbone is never trained: only head
//! parameters are tracked by autodiff.

pub mod arch;
pub mod cache;
pub mod data;
mod error;
pub mod features;
pub mod head;
pub mod infer;
pub mod io;
pub mod loss;
pub mod metrics;
pub mod plan;
pub mod pointmap;
pub mod train;

pub use error::HeadsError;
pub use features::{Backbone, Dens3rBackbone, Dinov2Backbone, FeatureMaps, PixelBackbone};
pub use head::{Head, HeadConfig, Task};
pub use train::{Example, Features, TrainOptions, Trainer};
