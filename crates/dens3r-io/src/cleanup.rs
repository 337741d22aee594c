//! Temporary files and folders of unfinished outputs, removed when the process is told to stop.
//!
//! Every writer that stages an output (a temporary file before its rename, a staging folder, a
//! new output folder not yet complete) registers it here for as long as it exists; a binary's
//! SIGINT / SIGTERM handler calls [`remove_all`] before exiting, so an interrupted command
//! leaves nothing half-written behind. What a `kill -9` leaves is swept by the next run
//! ([`sweep_stale`]): temporary names carry the writing process's id, and those of processes
//! that no longer run are removed.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Registered paths, with whether a folder is removed only when empty.
static STAGED: Mutex<Vec<(PathBuf, bool)>> = Mutex::new(Vec::new());
static STOPPING: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
static SWEPT: Mutex<Option<HashSet<PathBuf>>> = Mutex::new(None);

/// A registered path, unregistered when dropped (it is then finished, or removed by its owner).
#[derive(Debug)]
pub struct Staged(PathBuf);

impl Drop for Staged {
    fn drop(&mut self) {
        // While stopping, a writer giving up on its failed write still leaves the path to the
        // handler's removal.
        if stopping() {
            return;
        }
        let mut s = STAGED.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(i) = s.iter().rposition(|p| p.0 == self.0) {
            s.swap_remove(i);
        }
    }
}

/// Registers `path` (a file or folder) to be removed if the process is stopped while the
/// returned guard lives.
pub fn stage(path: &Path) -> Staged {
    STAGED.lock().unwrap_or_else(|e| e.into_inner()).push((path.to_path_buf(), false));
    Staged(path.to_path_buf())
}

/// Registers a folder this process created, removed if the process is stopped while the guard
/// lives and it then holds no file (after the paths registered later are removed; empty
/// folders inside it go too).
pub fn stage_if_empty(dir: &Path) -> Staged {
    STAGED.lock().unwrap_or_else(|e| e.into_inner()).push((dir.to_path_buf(), true));
    Staged(dir.to_path_buf())
}

/// Whether the process is stopping ([`stop`]): writers start nothing new.
pub fn stopping() -> bool {
    STOPPING.load(std::sync::atomic::Ordering::SeqCst)
}

/// The signal handler's work: marks the process as stopping (so [`crate::io::write_atomic`]
/// starts and finishes no file), lets writes in flight end, then removes every registered
/// path. Returns how many were removed.
pub fn stop() -> usize {
    STOPPING.store(true, std::sync::atomic::Ordering::SeqCst);
    std::thread::sleep(std::time::Duration::from_millis(100));
    remove_all()
}

/// Removes every registered path. Returns how many were removed.
pub fn remove_all() -> usize {
    let paths = std::mem::take(&mut *STAGED.lock().unwrap_or_else(|e| e.into_inner()));
    let mut n = 0;
    for (p, if_empty) in paths.iter().rev() {
        let r = match (p.is_dir(), if_empty) {
            (true, true) => remove_empty_tree(p),
            (true, false) => std::fs::remove_dir_all(p),
            (false, _) => std::fs::remove_file(p),
        };
        n += r.is_ok() as usize;
    }
    n
}

/// Removes the folders under `dir` that hold no file (deepest first), then `dir` if it is
/// then empty: a folder this process created, with nothing kept in it.
pub fn remove_empty_tree(dir: &Path) -> std::io::Result<()> {
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                let _ = remove_empty_tree(&e.path());
            }
        }
    }
    std::fs::remove_dir(dir)
}

/// The marker temporary names carry: `.dens3r-tmp-PID-` (see [`sweep_stale`]).
pub fn temp_prefix() -> String {
    format!(".dens3r-tmp-{}-", std::process::id())
}

/// Whether process `pid` still runs (Linux: `/proc/PID`; elsewhere assumed to, so nothing of
/// a live writer is ever removed).
pub(crate) fn alive(pid: u32) -> bool {
    if cfg!(target_os = "linux") {
        Path::new(&format!("/proc/{pid}")).exists()
    } else {
        true
    }
}

/// The writer's pid when `name` is exactly a name dens3r gives its temporary files
/// (`.dens3r-tmp-PID-XXXXXX`, six letters or digits) or staging folders (`.dens3r-stage-PID`);
/// None for every other name, however much of one it contains.
pub fn leftover_pid(name: &str) -> Option<u32> {
    let digits = |s: &str| !s.is_empty() && s.len() <= 10 && s.bytes().all(|b| b.is_ascii_digit());
    if let Some(rest) = name.strip_prefix(".dens3r-stage-") {
        return digits(rest).then(|| rest.parse().ok()).flatten();
    }
    let rest = name.strip_prefix(".dens3r-tmp-")?;
    let (pid, tail) = rest.split_once('-')?;
    (digits(pid) && tail.len() == 6 && tail.bytes().all(|b| b.is_ascii_alphanumeric())).then(|| pid.parse().ok())?
}

/// Removes temporary files and staging folders in `dir` ([`leftover_pid`]'s exact names) left
/// by processes that no longer run; each folder is swept once per process. A temporary name
/// is a file and a staging name a folder: anything else under those names is left.
pub fn sweep_stale(dir: &Path) {
    {
        let mut swept = SWEPT.lock().unwrap_or_else(|e| e.into_inner());
        if !swept.get_or_insert_with(HashSet::new).insert(dir.to_path_buf()) {
            return;
        }
    }
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = leftover_pid(&name) else { continue };
        if pid == std::process::id() || alive(pid) {
            continue;
        }
        let Ok(kind) = e.file_type() else { continue };
        let p = e.path();
        let _ = match (name.starts_with(".dens3r-stage-"), kind.is_dir(), kind.is_file()) {
            (true, true, _) => std::fs::remove_dir_all(&p),
            (false, _, true) => std::fs::remove_file(&p),
            _ => Ok(()),
        };
    }
}
