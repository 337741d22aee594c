//! An output folder written as one transaction.
//!
//! A command's outputs are written into a staging folder inside the destination
//! (`DEST/.dens3r-stage-PID`) and moved into place only by [`OutputDir::finish`], so a failure,
//! SIGINT or SIGTERM leaves the destination as it was (a destination this run created is
//! removed again once empty). The destination keeps a manifest, `DEST/.dens3r-outputs.json`,
//! of the files dens3r wrote there: a later run replaces exactly those (its own earlier
//! outputs) and refuses, before touching anything, to replace a file it did not write. Files
//! of the user's beside the outputs (photos, notes) are never moved, changed or removed.
//! One run at a time writes a destination: a lock file, `DEST/.dens3r-lock`, holds the
//! writer's process id, and a second run is refused while that process lives.

use crate::cleanup::Staged;
use crate::IoError;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// The manifest's file name: the files (and folders) dens3r wrote in a destination.
pub const MANIFEST: &str = ".dens3r-outputs.json";
/// The lock file's name: the process id of the run writing the destination.
pub const LOCK: &str = ".dens3r-lock";

/// What dens3r wrote in a folder: files and the folders it created for them, relative paths
/// with `/` separators.
#[derive(Debug, Default, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// Files written.
    pub files: BTreeSet<String>,
    /// Folders created for them.
    #[serde(default)]
    pub dirs: BTreeSet<String>,
}

impl Manifest {
    /// The manifest of `dest` (`None` when it has none; an unreadable one is an error).
    pub fn read(dest: &Path) -> Result<Option<Manifest>, IoError> {
        let path = dest.join(MANIFEST);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(IoError::new(&path, format!("cannot read dens3r's list of its outputs: {e}"))),
        };
        serde_json::from_str(&text).map(Some).map_err(|e| {
            IoError::new(&path, format!("damaged list of dens3r's outputs ({e}); remove it to write here again"))
        })
    }

    /// Whether it lists no file.
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }
}

/// Whether `dest` holds outputs of an earlier dens3r run (by its manifest).
pub fn holds_outputs(dest: &Path) -> bool {
    match Manifest::read(dest) {
        Ok(m) => m.is_some_and(|m| !m.is_empty()),
        Err(_) => true,
    }
}

/// Removes the folder `dir` when every file in it is one dens3r wrote (listed in its
/// manifest); otherwise refuses, naming a file that is not, and removes nothing.
pub fn remove_own(dir: &Path) -> Result<(), IoError> {
    let m = Manifest::read(dir)?.ok_or_else(|| {
        IoError::new(dir, "was not written by dens3r (no list of its outputs), so it is not replaced; move it")
    })?;
    let mut files = Vec::new();
    walk(dir, Path::new(""), &mut files).map_err(|e| IoError::new(dir, format!("cannot list it: {e}")))?;
    if let Some(f) = files.iter().find(|f| rel_string(f) != MANIFEST && !m.files.contains(&rel_string(f))) {
        return Err(in_the_way(&dir.join(f)));
    }
    std::fs::remove_dir_all(dir).map_err(|e| IoError::new(dir, format!("cannot remove this earlier output: {e}")))
}

/// The lock a run holds on a destination while it writes there.
#[derive(Debug)]
struct Lock {
    path: PathBuf,
    _staged: Staged,
}

impl Lock {
    fn take(dest: &Path) -> Result<Lock, IoError> {
        let path = dest.join(LOCK);
        for _ in 0..3 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut f) => {
                    let staged = crate::cleanup::stage(&path);
                    std::io::Write::write_all(&mut f, std::process::id().to_string().as_bytes())
                        .map_err(|e| IoError::new(&path, format!("cannot write the lock file: {e}")))?;
                    return Ok(Lock { path, _staged: staged });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let holder = std::fs::read_to_string(&path).ok().and_then(|s| s.trim().parse::<u32>().ok());
                    match holder {
                        Some(pid) if pid != std::process::id() && crate::cleanup::alive(pid) => {
                            return Err(IoError::new(
                                dest,
                                format!(
                                    "another dens3r run (process {pid}) is writing this folder; wait for it to finish, or write to another folder"
                                ),
                            ));
                        }
                        // A dead run's lock (or one being written this instant): taken over.
                        _ => {
                            if holder.is_none() {
                                std::thread::sleep(std::time::Duration::from_millis(50));
                                let again = std::fs::read_to_string(&path).ok();
                                if again.as_deref().and_then(|s| s.trim().parse::<u32>().ok()).is_some() {
                                    continue;
                                }
                            }
                            let _ = std::fs::remove_file(&path);
                        }
                    }
                }
                Err(e) => return Err(IoError::new(&path, format!("cannot create the lock file: {e}"))),
            }
        }
        Err(IoError::new(dest, "cannot take the folder's lock; another dens3r run may be starting there"))
    }
}

impl Drop for Lock {
    fn drop(&mut self) {
        if !crate::cleanup::stopping() {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// An output folder being written; see the module documentation.
#[derive(Debug)]
pub struct OutputDir {
    dest: PathBuf,
    stage: PathBuf,
    /// Files counted as dens3r's where the destination has no manifest (outputs of versions
    /// before it).
    legacy: Vec<String>,
    /// Folders this run created (the destination, its missing parents), outermost first.
    created: Vec<PathBuf>,
    _created_guards: Vec<Staged>,
    _stage_guard: Staged,
    lock: Option<Lock>,
}

/// A relative path with `/` separators.
fn rel_string(p: &Path) -> String {
    p.components().map(|c| c.as_os_str().to_string_lossy()).collect::<Vec<_>>().join("/")
}

impl OutputDir {
    /// Starts writing `dest` (created with its missing parents): takes its lock and makes the
    /// staging folder. Fails, naming `dest`, when another run holds it or it cannot be made.
    pub fn begin(dest: &Path) -> Result<OutputDir, IoError> {
        if crate::cleanup::stopping() {
            return Err(IoError::new(dest, "not written: the process is stopping"));
        }
        if dest.exists() && !dest.is_dir() {
            return Err(IoError::new(dest, "is a file, not a folder; give a folder to write the outputs in"));
        }
        // The folders this run creates, outermost first (removed again if the run fails).
        let mut missing = Vec::new();
        let mut p = Some(dest);
        while let Some(d) = p.filter(|d| !d.as_os_str().is_empty() && !d.exists()) {
            missing.push(d.to_path_buf());
            p = d.parent();
        }
        missing.reverse();
        let undo = |e: IoError| {
            for c in missing.iter().rev() {
                let _ = std::fs::remove_dir(c);
            }
            e
        };
        let mut created_guards = Vec::new();
        for d in &missing {
            match std::fs::create_dir(d) {
                Ok(()) => created_guards.push(crate::cleanup::stage_if_empty(d)),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && d.is_dir() => {}
                Err(e) => return Err(undo(IoError::new(dest, format!("cannot create the output folder: {e}")))),
            }
        }
        crate::cleanup::sweep_stale(dest);
        let lock = Lock::take(dest).map_err(undo)?;
        let stage = dest.join(format!(".dens3r-stage-{}", std::process::id()));
        if stage.exists() {
            let _ = std::fs::remove_dir_all(&stage);
        }
        let stage_guard = crate::cleanup::stage(&stage);
        if let Err(e) = std::fs::create_dir(&stage) {
            drop(lock);
            return Err(undo(IoError::new(dest, format!("cannot create a staging folder in it: {e}"))));
        }
        Ok(OutputDir {
            dest: dest.to_path_buf(),
            stage,
            legacy: Vec::new(),
            created: missing,
            _created_guards: created_guards,
            _stage_guard: stage_guard,
            lock: Some(lock),
        })
    }

    /// The folder to write every output in (moved into the destination by `finish`).
    pub fn root(&self) -> &Path {
        &self.stage
    }

    /// The destination.
    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// Files (relative to the destination) counted as written by dens3r when the destination
    /// has no manifest: what an earlier version wrote, recognised by the caller.
    pub fn set_legacy(&mut self, files: Vec<String>) {
        self.legacy = files;
    }

    /// Whether the destination already held it before this run (it was not created now).
    pub fn existed(&self) -> bool {
        self.created.is_empty()
    }

    /// Refuses, before anything is computed, outputs (relative paths) whose place in the
    /// destination holds a file dens3r did not write: `finish` would refuse them at the end.
    pub fn check_free(&self, files: &[String]) -> Result<(), IoError> {
        let old = self.earlier()?;
        for rel in files {
            let target = self.dest.join(rel);
            if target.symlink_metadata().is_ok() && !old.files.contains(rel) {
                return Err(in_the_way(&target));
            }
        }
        Ok(())
    }

    /// What earlier dens3r runs wrote in the destination: its manifest, else the files
    /// recognised as an earlier version's.
    fn earlier(&self) -> Result<Manifest, IoError> {
        Ok(match Manifest::read(&self.dest)? {
            Some(m) => m,
            None => {
                let files: BTreeSet<String> = self.legacy.iter().cloned().collect();
                let dirs = files
                    .iter()
                    .flat_map(|f| Path::new(f).ancestors().skip(1).map(rel_string).collect::<Vec<_>>())
                    .filter(|d| !d.is_empty())
                    .collect();
                Manifest { files, dirs }
            }
        })
    }

    /// Moves the staged outputs into the destination: files of an earlier dens3r run there
    /// are replaced, those the new run does not write removed, every other file left alone. A
    /// staged file whose place holds a file dens3r did not write is refused before anything
    /// moves. Files named `cameras.json` move last, so a scene is complete when it appears.
    pub fn finish(mut self) -> Result<PathBuf, IoError> {
        let old = self.earlier()?;
        let mut new = Vec::new();
        walk(&self.stage, Path::new(""), &mut new)
            .map_err(|e| IoError::new(&self.stage, format!("cannot list the staged outputs: {e}")))?;
        // Refuse before anything moves.
        for f in &new {
            let rel = rel_string(f);
            let target = self.dest.join(f);
            for anc in f.ancestors().skip(1).filter(|a| !a.as_os_str().is_empty()) {
                let d = self.dest.join(anc);
                if d.symlink_metadata().is_ok_and(|m| !m.is_dir()) {
                    return Err(IoError::new(
                        &d,
                        "is in the way of an output folder and was not written by dens3r; move it, or write to another folder",
                    ));
                }
            }
            match target.symlink_metadata() {
                Ok(m) if m.is_dir() => {
                    return Err(IoError::new(
                        &target,
                        "is a folder where dens3r writes a file; move it, or write to another folder",
                    ))
                }
                Ok(_) if !old.files.contains(&rel) => return Err(in_the_way(&target)),
                _ => {}
            }
        }
        let new_rel: BTreeSet<String> = new.iter().map(|f| rel_string(f)).collect();
        // The earlier run's files the new one does not write: removed (a scene's cameras.json
        // first, so no scene lists files that are gone).
        let mut stale: Vec<&String> = old.files.iter().filter(|f| !new_rel.contains(*f)).collect();
        stale.sort_by_key(|f| !f.ends_with("cameras.json"));
        for f in stale {
            let p = self.dest.join(f);
            if p.symlink_metadata().is_ok_and(|m| !m.is_dir()) {
                std::fs::remove_file(&p)
                    .map_err(|e| IoError::new(&p, format!("cannot remove this earlier output of dens3r's: {e}")))?;
            }
        }
        // The new files, cameras.json last.
        new.sort_by_key(|f| (f.file_name().is_some_and(|n| n == "cameras.json"), f.components().count()));
        let mut dirs = old.dirs.clone();
        for f in &new {
            let target = self.dest.join(f);
            for anc in f.ancestors().skip(1).filter(|a| !a.as_os_str().is_empty()).collect::<Vec<_>>().into_iter().rev()
            {
                let d = self.dest.join(anc);
                if !d.exists() {
                    std::fs::create_dir(&d)
                        .map_err(|e| IoError::new(&d, format!("cannot create the output folder: {e}")))?;
                    dirs.insert(rel_string(anc));
                }
            }
            std::fs::rename(self.stage.join(f), &target)
                .map_err(|e| IoError::new(&target, format!("cannot move the finished output into place: {e}")))?;
        }
        // Folders of earlier outputs now empty.
        let mut by_depth: Vec<&String> = dirs.iter().collect();
        by_depth.sort_by_key(|d| std::cmp::Reverse(d.matches('/').count()));
        for d in by_depth {
            let _ = std::fs::remove_dir(self.dest.join(d));
        }
        dirs.retain(|d| self.dest.join(d).is_dir());
        let manifest = Manifest { files: new_rel, dirs };
        let text = serde_json::to_string_pretty(&manifest).expect("manifest serialises");
        crate::write_atomic(&self.dest.join(MANIFEST), |w| std::io::Write::write_all(w, text.as_bytes()))?;
        let _ = std::fs::remove_dir_all(&self.stage);
        self.created.clear();
        self._created_guards.clear();
        self.lock.take();
        Ok(self.dest.clone())
    }
}

/// A run that did not finish: the staging folder and the lock go, and the folders it created
/// go again where they hold no file (a pair cache written meanwhile keeps its entries).
impl Drop for OutputDir {
    fn drop(&mut self) {
        if crate::cleanup::stopping() {
            return;
        }
        let _ = std::fs::remove_dir_all(&self.stage);
        self.lock.take();
        for d in self.created.iter().rev() {
            let _ = crate::cleanup::remove_empty_tree(d);
        }
    }
}

/// The refusal of an output whose place holds a file dens3r did not write.
fn in_the_way(target: &Path) -> IoError {
    IoError::new(
        target,
        "exists and was not written by dens3r, so it is not replaced; move it, or write to another folder",
    )
}

/// The regular files under `dir` (relative to the staging root), recursively.
fn walk(root: &Path, rel: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    for e in std::fs::read_dir(root.join(rel))? {
        let e = e?;
        let r = rel.join(e.file_name());
        if e.file_type()?.is_dir() {
            walk(root, &r, out)?;
        } else {
            out.push(r);
        }
    }
    Ok(())
}
