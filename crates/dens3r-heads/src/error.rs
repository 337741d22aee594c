//! Why a head could not be trained, loaded or run: one line naming the file or the setting and
//! what to do.

use std::path::{Path, PathBuf};

/// A dens3r-heads failure.
#[derive(Debug, thiserror::Error)]
pub enum HeadsError {
    /// A file or folder could not be used (read, decoded, written, or it does not fit).
    #[error("{}: {message}", path.display())]
    File {
        /// The file or folder at fault.
        path: PathBuf,
        /// What is wrong with it and how to fix it.
        message: String,
    },
    /// A setting, head configuration or data set that cannot work, and the fix.
    #[error("{0}")]
    Invalid(String),
}

impl HeadsError {
    /// A problem with the file or folder `path`.
    pub fn file(path: &Path, message: impl Into<String>) -> Self {
        Self::File { path: path.to_path_buf(), message: message.into() }
    }

    /// A setting or data set that cannot work.
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::Invalid(message.into())
    }
}

macro_rules! from_file_error {
    ($($t:ty),*) => {$(
        impl From<$t> for HeadsError {
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
    dens3r_backbone::onnx::OnnxError,
    dens3r_io::IoError
);
