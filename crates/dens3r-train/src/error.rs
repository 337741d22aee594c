//! Why training, its data or its outputs could not go on: one line naming the file or the
//! setting and what to do.

use std::path::{Path, PathBuf};

/// A dens3r-train failure.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// A file or folder could not be used (read, decoded, written, or it does not fit).
    #[error("{}: {message}", path.display())]
    File {
        /// The file or folder at fault.
        path: PathBuf,
        /// What is wrong with it and how to fix it.
        message: String,
    },
    /// A setting, an architecture, a data set or a training state that cannot work, and the fix.
    #[error("{0}")]
    Invalid(String),
}

impl TrainError {
    /// A problem with the file or folder `path`.
    pub fn file(path: &Path, message: impl Into<String>) -> Self {
        Self::File { path: path.to_path_buf(), message: message.into() }
    }

    /// A setting or state that cannot work.
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::Invalid(message.into())
    }
}

macro_rules! from_file_error {
    ($($t:ty),*) => {$(
        impl From<$t> for TrainError {
            fn from(e: $t) -> Self {
                Self::File { path: e.path, message: e.message }
            }
        }
    )*};
}
from_file_error!(
    dens3r_scene::SceneError,
    dens3r_mesh::MeshError,
    dens3r_backbone::weights::WeightsError,
    dens3r_io::IoError
);

/// Errors that carry no file (serialisation, a raster of the wrong size, a failed write to an
/// open log): kept as their message.
macro_rules! from_plain_error {
    ($($t:ty),*) => {$(
        impl From<$t> for TrainError {
            fn from(e: $t) -> Self {
                Self::Invalid(e.to_string())
            }
        }
    )*};
}
from_plain_error!(std::io::Error, serde_json::Error, dens3r_geom::RasterError);
