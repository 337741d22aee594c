//! The frozen Dens3R / DUSt3R / MASt3R backbone on burn: a siamese ViT encoder, a
//! cross-attention decoder (shared or two), DPT heads for pointmap + confidence, a descriptor
//! MLP and a normal head; numerics as in the official PyTorch code (model spec sections 1.2 to
//! 1.7). Configuration is read from the weight shapes, never hard-coded.
//!
//! [`Dens3r::encode`] gives [`Features`] (encoder tokens and every decoder layer per view) that
//! other heads reuse without re-running the backbone; [`Dens3r::heads`] turns them into
//! [`Predictions`].

pub mod autodiff_cpu;
pub mod config;
pub mod convert;
pub mod cpu;
pub mod default_model;
pub mod device;
pub mod dinov2;
mod error;
pub mod model;
pub mod onnx;
pub mod ops;
pub mod params;
pub mod predict;
pub mod preprocess;
pub mod pth;
pub mod verify;
pub mod weights;

pub use config::ModelConfig;
pub use error::BackboneError;
pub use model::{Dens3r, Features, HeadOutputs, Predictions, ViewFeatures, ViewPrediction};
pub use params::{Freeze, Params, Precision};
pub use weights::{Weights, WeightsError};

/// The tensor types of the seam (burn, device-dispatched).
pub use burn::tensor::{Device, Tensor, TensorData};
