//! Training the Dens3R network (model spec sections 1 and 5): [`arch`] describes a network
//! by the official constructor's keywords; [`pair`] turns two scene-folder frames into a
//! training pair with ground-truth pointmaps, normals and correspondences; [`loss`] holds the
//! losses; [`train`] the two-stage loop (AdamW, warm-up + cosine, clipping, exact resume);
//! [`run`] a whole run into a folder (checkpoints, JSONL log, final weights); [`synth`]
//! writes procedural training scenes with their pairs' co-visibility (`dens3r synth`); [`real`]
//! writes real held-out frames with metric ground truth (`dens3r real-scenes`).

pub mod arch;
pub mod augment;
mod error;
pub mod loss;
pub mod pair;
pub mod real;
pub mod run;
pub mod synth;
pub mod train;

pub use arch::Arch;
pub use error::TrainError;
pub use train::{scene_dirs, Dataset, LossTerms, PointsFrame, Stage, TrainConfig, Trainer};
