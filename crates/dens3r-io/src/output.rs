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
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Component, Path, PathBuf};

/// The manifest's file name: the files (and folders) dens3r wrote in a destination.
pub const MANIFEST: &str = ".dens3r-outputs.json";
/// The lock file's name: the process id of the run writing the destination.
pub const LOCK: &str = ".dens3r-lock";

/// A file as dens3r wrote it: its size and content hash (FNV-1a, hex). A file counts as
/// dens3r's only while it still matches.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Stamp {
    /// Bytes.
    pub size: u64,
    /// [`crate::hash::content_hash`], 16 hex digits.
    pub hash: String,
}

impl Stamp {
    /// The stamp of the regular file at `path` (None: absent, not a regular file, unreadable).
    pub fn of(path: &Path) -> Option<Stamp> {
        let m = path.symlink_metadata().ok().filter(|m| m.file_type().is_file())?;
        let hash = crate::hash::content_hash(path).ok()?;
        Some(Stamp { size: m.len(), hash: format!("{hash:016x}") })
    }
}

/// What dens3r wrote in a folder: files and the folders it created for them, relative paths
/// with `/` separators.
///
/// A manifest is read as untrusted input (an output folder may come from anyone): only plain
/// relative paths below the folder are kept, and a file is dens3r's only where its recorded
/// [`Stamp`] still matches ([`Manifest::owns`]).
#[derive(Debug, Default, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// Files written.
    pub files: BTreeSet<String>,
    /// Folders created for them.
    #[serde(default)]
    pub dirs: BTreeSet<String>,
    /// Each file's size and content hash when it was written.
    #[serde(default)]
    pub stamps: BTreeMap<String, Stamp>,
    /// While a run moves its files in: the stamps of the earlier files it replaces (either
    /// version is dens3r's until the move ends).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub replacing: BTreeMap<String, Stamp>,
    /// Entries of the file on disk that are not plain relative paths below the folder: never
    /// used, named in a warning.
    #[serde(skip)]
    pub refused: Vec<String>,
}

/// Whether `rel` is a plain relative path below a folder: no root, no `..` or `.`, no empty
/// part, no backslash (a Windows separator).
pub fn plain_relative(rel: &str) -> bool {
    !rel.is_empty()
        && !rel.contains('\\')
        && !rel.contains('\0')
        && rel.split('/').all(|c| !c.is_empty() && c != "." && c != "..")
        && Path::new(rel).components().all(|c| matches!(c, Component::Normal(_)))
}

impl Manifest {
    /// The manifest of `dest` (`None` when it has none; an unreadable one is an error). Entries
    /// that are not plain relative paths are set apart in `refused`.
    pub fn read(dest: &Path) -> Result<Option<Manifest>, IoError> {
        let path = dest.join(MANIFEST);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(IoError::new(&path, format!("cannot read dens3r's list of its outputs: {e}"))),
        };
        let mut m: Manifest = serde_json::from_str(&text).map_err(|e| {
            IoError::new(&path, format!("damaged list of dens3r's outputs ({e}); remove it to write here again"))
        })?;
        let mut refused = Vec::new();
        for set in [&mut m.files, &mut m.dirs] {
            refused.extend(set.iter().filter(|f| !plain_relative(f)).cloned());
            set.retain(|f| plain_relative(f));
        }
        m.stamps.retain(|f, _| plain_relative(f));
        m.replacing.retain(|f, _| plain_relative(f));
        m.refused = refused;
        Ok(Some(m))
    }

    /// Writes it as `dest`'s manifest (atomically).
    fn write(&self, dest: &Path) -> Result<(), IoError> {
        let text = serde_json::to_string_pretty(self).expect("manifest serialises");
        crate::write_atomic(&dest.join(MANIFEST), |w| std::io::Write::write_all(w, text.as_bytes()))
    }

    /// Whether it lists no file.
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// Whether `rel` in `dest` is still the file dens3r wrote: listed with a stamp, reached
    /// through real folders (no symbolic link on the way), a regular file of the recorded size
    /// and content.
    pub fn owns(&self, dest: &Path, rel: &str) -> bool {
        let known: Vec<&Stamp> = [self.stamps.get(rel), self.replacing.get(rel)].into_iter().flatten().collect();
        if known.is_empty() || !self.files.contains(rel) || !plain_relative(rel) || !real_folders(dest, Path::new(rel))
        {
            return false;
        }
        let path = dest.join(rel);
        path.symlink_metadata().is_ok_and(|m| m.file_type().is_file() && known.iter().any(|s| s.size == m.len()))
            && Stamp::of(&path).is_some_and(|s| known.contains(&&s))
    }

    /// The refusal of an output whose place holds `rel`, a file this manifest does not own.
    fn refusal(&self, target: &Path, rel: &str) -> IoError {
        if self.files.contains(rel) && !self.stamps.contains_key(rel) && !self.replacing.contains_key(rel) {
            return IoError::new(
                target,
                "was written by a dens3r version that kept no record of its content, so it is not replaced; move it (or the folder's older outputs), or write to another folder",
            );
        }
        in_the_way(target)
    }
}

/// Whether every folder between `dest` and `dest/rel` is a real folder (not a symbolic link,
/// not a file); folders that do not exist yet pass.
fn real_folders(dest: &Path, rel: &Path) -> bool {
    rel.ancestors()
        .skip(1)
        .filter(|a| !a.as_os_str().is_empty())
        .all(|a| dest.join(a).symlink_metadata().map_or(true, |m| m.file_type().is_dir()))
}

/// Rewrites `rel`, a file dens3r wrote in `dest` and still listed there unchanged, with
/// `bytes` (atomically), and records its new stamp in the manifest; returns false, writing
/// nothing, when the file is not dens3r's.
pub fn rewrite_own(dest: &Path, rel: &str, bytes: &[u8]) -> Result<bool, IoError> {
    let Some(mut m) = Manifest::read(dest)? else { return Ok(false) };
    if !m.owns(dest, rel) {
        return Ok(false);
    }
    let path = dest.join(rel);
    crate::write_atomic(&path, |w| std::io::Write::write_all(w, bytes))?;
    let stamp = Stamp::of(&path).ok_or_else(|| IoError::new(&path, "cannot read this output back"))?;
    m.stamps.insert(rel.to_string(), stamp);
    m.replacing.remove(rel);
    m.write(dest)?;
    Ok(true)
}

/// Whether `dest` holds outputs of an earlier dens3r run (by its manifest).
pub fn holds_outputs(dest: &Path) -> bool {
    match Manifest::read(dest) {
        Ok(m) => m.is_some_and(|m| !m.is_empty()),
        Err(_) => true,
    }
}

/// Removes the folder `dir` when every file in it is one dens3r wrote (listed in its
/// manifest, unchanged since); otherwise refuses, naming a file that is not, and removes
/// nothing.
pub fn remove_own(dir: &Path) -> Result<(), IoError> {
    let m = Manifest::read(dir)?.ok_or_else(|| {
        IoError::new(dir, "was not written by dens3r (no list of its outputs), so it is not replaced; move it")
    })?;
    let mut files = Vec::new();
    walk(dir, Path::new(""), &mut files).map_err(|e| IoError::new(dir, format!("cannot list it: {e}")))?;
    if let Some(f) = files.iter().find(|f| rel_string(f) != MANIFEST && !m.owns(dir, &rel_string(f))) {
        return Err(in_the_way(&dir.join(f)));
    }
    std::fs::remove_dir_all(dir).map_err(|e| IoError::new(dir, format!("cannot remove this earlier output: {e}")))
}

/// The start time of process `pid` (clock ticks since boot, `/proc/PID/stat`'s 22nd field):
/// with the pid, it tells a live writer from a new process that reuses a dead writer's pid.
fn start_time(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    stat[stat.rfind(')')? + 1..].split_whitespace().nth(19)?.parse().ok()
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
        let me = std::process::id();
        for _ in 0..3 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut f) => {
                    let staged = crate::cleanup::stage(&path);
                    let text = match start_time(me) {
                        Some(t) => format!("{me} {t}"),
                        None => me.to_string(),
                    };
                    std::io::Write::write_all(&mut f, text.as_bytes())
                        .map_err(|e| IoError::new(&path, format!("cannot write the lock file: {e}")))?;
                    return Ok(Lock { path, _staged: staged });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    // "PID" or "PID START": a holder whose pid now names a process started at
                    // another time is gone (its pid reused).
                    let text = std::fs::read_to_string(&path).ok();
                    let mut parts = text.as_deref().unwrap_or("").split_whitespace();
                    let holder = parts.next().and_then(|p| p.parse::<u32>().ok());
                    let started = parts.next().and_then(|p| p.parse::<u64>().ok());
                    match holder {
                        Some(pid)
                            if pid != me
                                && crate::cleanup::alive(pid)
                                && started.is_none_or(|t| start_time(pid).is_none_or(|now| now == t)) =>
                        {
                            return Err(IoError::new(
                                dest,
                                format!(
                                    "another dens3r run (process {pid}) is writing this folder; wait for it to finish, or write to another folder (if no dens3r run is writing it, remove {})",
                                    path.display()
                                ),
                            ));
                        }
                        // A dead run's lock (or one being written this instant): taken over.
                        _ => {
                            if holder.is_none() {
                                std::thread::sleep(std::time::Duration::from_millis(50));
                                let again = std::fs::read_to_string(&path).ok();
                                let first = again.as_deref().and_then(|s| s.split_whitespace().next());
                                if first.and_then(|s| s.parse::<u32>().ok()).is_some() {
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
            if !real_folders(&self.dest, Path::new(rel)) {
                return Err(in_the_way_folder(&self.dest, Path::new(rel)));
            }
            if target.symlink_metadata().is_ok() && !old.owns(&self.dest, rel) {
                return Err(old.refusal(&target, rel));
            }
        }
        Ok(())
    }

    /// What earlier dens3r runs wrote in the destination: its manifest (none: nothing there is
    /// dens3r's).
    fn earlier(&self) -> Result<Manifest, IoError> {
        Ok(Manifest::read(&self.dest)?.unwrap_or_default())
    }

    /// [`OutputDir::finish_with_warnings`], its warnings printed on stderr.
    pub fn finish(self) -> Result<PathBuf, IoError> {
        let (dest, warnings) = self.finish_with_warnings()?;
        for w in warnings {
            eprintln!("warning: {w}");
        }
        Ok(dest)
    }

    /// Moves the staged outputs into the destination: files of an earlier dens3r run there
    /// are replaced, those the new run does not write removed, every other file left alone.
    /// A file counts as an earlier run's only while the manifest lists it by a plain relative
    /// path and it still has the size and content recorded there; anything else the manifest
    /// lists is left where it is and named in the returned warnings. A staged file whose place
    /// holds a file dens3r did not write is refused before anything moves. The earlier scene
    /// index (`cameras.json`) goes before anything moves and the new one moves last, so a stop
    /// in between leaves no scene that mixes two runs; the manifest written before the moves
    /// lists both runs' files, so the next run still knows them.
    pub fn finish_with_warnings(mut self) -> Result<(PathBuf, Vec<String>), IoError> {
        let old = self.earlier()?;
        let mut warnings: Vec<String> = old
            .refused
            .iter()
            .map(|f| {
                format!(
                    "{}: lists {f:?}, which is not a path inside the folder; ignored",
                    self.dest.join(MANIFEST).display()
                )
            })
            .collect();
        let mut new = Vec::new();
        walk(&self.stage, Path::new(""), &mut new)
            .map_err(|e| IoError::new(&self.stage, format!("cannot list the staged outputs: {e}")))?;
        // Which earlier files are still dens3r's: each hashed once.
        let owned: BTreeSet<String> = old.files.iter().filter(|f| old.owns(&self.dest, f)).cloned().collect();
        // Refuse before anything moves.
        for f in &new {
            let rel = rel_string(f);
            let target = self.dest.join(f);
            if !real_folders(&self.dest, f) {
                return Err(in_the_way_folder(&self.dest, f));
            }
            match target.symlink_metadata() {
                Ok(m) if m.is_dir() => {
                    return Err(IoError::new(
                        &target,
                        "is a folder where dens3r writes a file; move it, or write to another folder",
                    ))
                }
                Ok(_) if !owned.contains(&rel) => return Err(old.refusal(&target, &rel)),
                _ => {}
            }
        }
        let mut stamps = BTreeMap::new();
        for f in &new {
            let staged = self.stage.join(f);
            let stamp =
                Stamp::of(&staged).ok_or_else(|| IoError::new(&staged, "cannot read this staged output back"))?;
            stamps.insert(rel_string(f), stamp);
        }
        let new_rel: BTreeSet<String> = stamps.keys().cloned().collect();
        // The earlier run's files the new one does not write, and those it replaces.
        let stale: Vec<&String> = old.files.iter().filter(|f| !new_rel.contains(*f)).collect();
        let owned_stale: Vec<&String> = stale.iter().copied().filter(|f| owned.contains(*f)).collect();
        for f in stale.iter().filter(|f| !owned.contains(**f)) {
            if self.dest.join(f).symlink_metadata().is_ok() {
                warnings.push(format!(
                    "{}: listed as an earlier output of dens3r's but changed since (or not a file dens3r wrote); left as it is",
                    self.dest.join(f).display()
                ));
            }
        }
        // The journal: both runs' files, so a stop during the moves leaves them known.
        let mut journal = Manifest { files: old.files.clone(), dirs: old.dirs.clone(), ..Default::default() };
        journal.files.extend(new_rel.iter().cloned());
        journal.stamps =
            old.stamps.iter().filter(|(f, _)| !new_rel.contains(*f)).map(|(f, s)| (f.clone(), s.clone())).collect();
        journal.stamps.extend(stamps.iter().map(|(f, s)| (f.clone(), s.clone())));
        journal.replacing =
            old.stamps.iter().filter(|(f, _)| new_rel.contains(*f)).map(|(f, s)| (f.clone(), s.clone())).collect();
        journal.write(&self.dest)?;
        // Scene indexes first (stale ones and those replaced), then the other stale files.
        let replaced_index: Vec<&String> =
            new_rel.iter().filter(|f| f.ends_with("cameras.json") && owned.contains(*f)).collect();
        let mut removed = Vec::new();
        let mut remove = |f: &String| -> Result<(), IoError> {
            let p = self.dest.join(f);
            std::fs::remove_file(&p)
                .map_err(|e| IoError::new(&p, format!("cannot remove this earlier output of dens3r's: {e}")))?;
            removed.push(f.clone());
            Ok(())
        };
        for f in replaced_index.iter().chain(owned_stale.iter().filter(|f| f.ends_with("cameras.json"))) {
            remove(f)?;
        }
        for f in owned_stale.iter().filter(|f| !f.ends_with("cameras.json")) {
            remove(f)?;
        }
        // The new files, cameras.json last.
        new.sort_by_key(|f| (f.file_name().is_some_and(|n| n == "cameras.json"), f.components().count()));
        let mut dirs = old.dirs.clone();
        for f in &new {
            let target = self.dest.join(f);
            for anc in f.ancestors().skip(1).filter(|a| !a.as_os_str().is_empty()).collect::<Vec<_>>().into_iter().rev()
            {
                let d = self.dest.join(anc);
                if d.symlink_metadata().is_err() {
                    std::fs::create_dir(&d)
                        .map_err(|e| IoError::new(&d, format!("cannot create the output folder: {e}")))?;
                    dirs.insert(rel_string(anc));
                }
            }
            std::fs::rename(self.stage.join(f), &target)
                .map_err(|e| IoError::new(&target, format!("cannot move the finished output into place: {e}")))?;
        }
        // Folders dens3r created that held a file removed now, once empty (deepest first).
        let mut emptied: Vec<String> = removed
            .iter()
            .flat_map(|f| Path::new(f).ancestors().skip(1).map(rel_string).collect::<Vec<_>>())
            .filter(|d| !d.is_empty() && dirs.contains(d))
            .collect();
        emptied.sort_by_key(|d| std::cmp::Reverse(d.matches('/').count()));
        emptied.dedup();
        for d in emptied {
            if real_folders(&self.dest, Path::new(&format!("{d}/x"))) {
                let _ = std::fs::remove_dir(self.dest.join(&d));
            }
        }
        dirs.retain(|d| self.dest.join(d).symlink_metadata().is_ok_and(|m| m.is_dir()));
        Manifest { files: new_rel, dirs, stamps, ..Default::default() }.write(&self.dest)?;
        let _ = std::fs::remove_dir_all(&self.stage);
        self.created.clear();
        self._created_guards.clear();
        self.lock.take();
        Ok((self.dest.clone(), warnings))
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

/// The refusal of an output whose folder's place holds a file or a symbolic link.
fn in_the_way_folder(dest: &Path, rel: &Path) -> IoError {
    let bad = rel
        .ancestors()
        .skip(1)
        .filter(|a| !a.as_os_str().is_empty())
        .map(|a| dest.join(a))
        .find(|d| d.symlink_metadata().is_ok_and(|m| !m.file_type().is_dir()))
        .unwrap_or_else(|| dest.join(rel));
    IoError::new(
        &bad,
        "is in the way of an output folder (a file, or a link to elsewhere) and was not written by dens3r; move it, or write to another folder",
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
