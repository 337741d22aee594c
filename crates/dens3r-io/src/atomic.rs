//! Atomic file writes.

use crate::IoError;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

/// Writes a file through `f` into a temporary file beside `path`, then renames it into place,
/// so a failure never leaves a partial file, nor does a stop by SIGINT / SIGTERM (the file is
/// staged in [`crate::cleanup`]); leftovers of killed runs in the folder are swept first.
/// Creates the parent folder if needed.
pub fn write_atomic(
    path: &Path,
    f: impl FnOnce(&mut BufWriter<&mut File>) -> std::io::Result<()>,
) -> Result<(), IoError> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let stopped = || IoError::new(path, "not written: the process is stopping");
    if crate::cleanup::stopping() {
        return Err(stopped());
    }
    std::fs::create_dir_all(parent).map_err(|e| IoError::new(path, format!("cannot create the output folder: {e}")))?;
    crate::cleanup::sweep_stale(parent);
    let mut tmp = tempfile::Builder::new()
        .prefix(&crate::cleanup::temp_prefix())
        .rand_bytes(6)
        .tempfile_in(parent)
        .map_err(|e| IoError::new(path, format!("cannot create a temporary file beside it: {e}")))?;
    // Removed if the process is stopped before the rename.
    let _staged = crate::cleanup::stage(tmp.path());
    {
        let mut w = BufWriter::new(tmp.as_file_mut());
        f(&mut w).and_then(|_| w.flush()).map_err(|e| IoError::new(path, format!("write failed: {e}")))?;
    }
    // Temporary files are created owner-only (0600); finished outputs get the usual 0644.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(|e| IoError::new(path, format!("cannot set file permissions: {e}")))?;
    }
    if crate::cleanup::stopping() {
        return Err(stopped());
    }
    tmp.persist(path)
        .map_err(|e| IoError::new(path, format!("cannot move the finished file into place: {}", e.error)))?;
    Ok(())
}
