//! Photos to a reconstructed scene (`dens3r reconstruct`), as a library:
//!
//! 1. [`input`]: decode (EXIF orientation), preprocess (portrait -> landscape, resize, crop).
//! 2. [`pipeline`]: run every pair of the pair graph through a [`PairPredictor`] (the network,
//!    or anything that yields pointmaps), each ordered pair once and cached on disk
//!    ([`cache`]); match descriptors into tracks; align globally (`dens3r-align`).
//! 3. [`output`]: the scene folder (aligned depth, normals, confidence, cameras), COLMAP text
//!    model and nerfstudio `transforms.json`, match pictures ([`viz`]), and the TSDF mesh.
//!
//! [`mono`] writes one image's self-pair prediction as a scene frame (`dens3r predict`);
//! [`model`] resolves which network runs (a file, a folder, a known name, the bundled default).

pub mod cache;
pub mod graph;
pub mod input;
pub mod masks;
pub mod model;
pub mod mono;
pub mod oracle;
pub mod output;
pub mod pipeline;
pub mod predictor;
pub mod sfm;
pub mod shard;
pub mod tracks;
pub mod viz;

pub use cache::PairCache;
pub use input::{list_images, load_images, InputImage};
pub use masks::attach_masks;
pub use output::{begin_outputs, write_outputs, write_outputs_into, OutputOptions, OutputSummary};
pub use pipeline::{reconstruct, reconstruct_dense, Cameras, KeypointOptions, ReconOptions, Reconstruction, Stage};
pub use predictor::{NetworkPredictor, PairPredictor, ViewOutput, Wanted};
pub use sfm::SfmSettings;
pub use shard::{compute_shard, Shard, ShardStats};
pub use tracks::TrackOptions;

use std::path::Path;

/// Why a reconstruction stopped; every message names the file or step and what to do.
#[derive(Debug, thiserror::Error)]
pub enum ReconError {
    /// A photo or folder could not be used.
    #[error("{path}: {msg}")]
    Input {
        /// The file or folder.
        path: String,
        /// What is wrong with it.
        msg: String,
    },
    /// The predictor failed on a pair or returned malformed maps.
    #[error("pair ({a}, {b}): {msg}")]
    Predict {
        /// First image name.
        a: String,
        /// Second image name.
        b: String,
        /// What went wrong.
        msg: String,
    },
    /// Global alignment could not run.
    #[error(transparent)]
    Align(#[from] dens3r_align::GlobalAlignError),
    /// Writing an output failed.
    #[error(transparent)]
    Scene(#[from] dens3r_scene::SceneError),
    /// Anything else, described.
    #[error("{0}")]
    Other(String),
}

impl From<dens3r_io::IoError> for ReconError {
    fn from(e: dens3r_io::IoError) -> Self {
        Self::Input { path: e.path.display().to_string(), msg: e.message }
    }
}

impl From<dens3r_backbone::BackboneError> for ReconError {
    fn from(e: dens3r_backbone::BackboneError) -> Self {
        match e {
            dens3r_backbone::BackboneError::File { path, message } => {
                Self::Input { path: path.display().to_string(), msg: message }
            }
            dens3r_backbone::BackboneError::Invalid(m) => Self::Other(m),
        }
    }
}

impl ReconError {
    pub(crate) fn input(path: &Path, msg: impl Into<String>) -> Self {
        Self::Input { path: path.display().to_string(), msg: msg.into() }
    }
}
