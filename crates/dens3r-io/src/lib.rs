//! The file plumbing every dens3r crate shares, below the crates that know meshes, scenes or
//! networks:
//!
//! * [`write_atomic`]: a file written to a temporary name beside its place and renamed, so a
//!   failure or a stop never leaves it half-written;
//! * [`cleanup`]: the registry of unfinished outputs that a SIGINT / SIGTERM handler removes,
//!   and the sweep of what killed runs left;
//! * [`hash`]: FNV-1a, a content hash stable across Rust versions, for cache keys;
//! * [`panics`]: a third-party parser's panic on damaged input turned into a refusal;
//! * [`file_or_setting_error!`]: the error type of a crate whose failures name a file or a
//!   setting, defined once;
//! * [`tensors`]: named f32 tensors as safetensors and JSON beside them, written atomically
//!   and read back checked (every checkpoint: heads, neural SDF, training state).

mod atomic;
pub mod cleanup;
mod error_type;
pub mod hash;
pub mod panics;
pub mod tensors;

pub use atomic::write_atomic;

use std::path::{Path, PathBuf};

/// A file that could not be written or read: the file, what is wrong and what to do (one line).
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct IoError {
    /// The file at fault.
    pub path: PathBuf,
    /// What is wrong and how to fix it.
    pub message: String,
}

impl IoError {
    /// A problem with `path`.
    pub fn new(path: &Path, message: impl Into<String>) -> Self {
        Self { path: path.to_path_buf(), message: message.into() }
    }
}
