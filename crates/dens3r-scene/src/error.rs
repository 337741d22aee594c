use std::path::{Path, PathBuf};

/// A scene-folder problem: the file concerned and what to do about it (one line).
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct SceneError {
    /// The file or folder at fault.
    pub path: PathBuf,
    /// What is wrong and how to fix it.
    pub message: String,
}

impl SceneError {
    pub(crate) fn new(path: &Path, message: impl Into<String>) -> Self {
        Self { path: path.to_path_buf(), message: message.into() }
    }
}

impl From<dens3r_mesh::MeshError> for SceneError {
    fn from(e: dens3r_mesh::MeshError) -> Self {
        Self { path: e.path, message: e.message }
    }
}

impl From<dens3r_io::IoError> for SceneError {
    fn from(e: dens3r_io::IoError) -> Self {
        Self { path: e.path, message: e.message }
    }
}
