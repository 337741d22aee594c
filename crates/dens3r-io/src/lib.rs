//! The file plumbing every dens3r crate shares, below the crates that know meshes, scenes or
//! networks:
//!
//! * [`write_atomic`]: a file written to a temporary name beside its place and renamed, so a
//!   failure or a stop never leaves it half-written;
//! * [`cleanup`]: the registry of unfinished outputs that a SIGINT / SIGTERM handler removes,
//!   and the sweep of what killed runs left;
//! * [`output`]: an output folder written as one transaction: staged, moved into place at
//!   the end, a manifest of what dens3r wrote (only that is ever replaced), one writer at a
//!   time;
//! * [`hash`]: FNV-1a, a content hash stable across Rust versions, for cache keys;
//! * [`panics`]: a third-party parser's panic on damaged input turned into a refusal;
//! * [`file_error!`] and [`file_or_setting_error!`]: the error types of failures that name a
//!   file (or a setting), defined once;
//! * [`tensors`]: named f32 tensors as safetensors and JSON beside them, written atomically
//!   and read back checked (every checkpoint: heads, neural SDF, training state).

mod atomic;
pub mod cleanup;
mod error_type;
pub mod hash;
pub mod output;
pub mod panics;
pub mod tensors;

pub use atomic::write_atomic;

file_error! {
    /// A file that could not be written or read: the file, what is wrong and what to do (one
    /// line).
    IoError;
    from: [];
}
