//! The official checkpoints by name, and their download into a local cache.
//!
//! * [`catalogue`]: what dens3r knows (name, family, what it predicts, size, licence, page,
//!   where its files come from);
//! * [`download`]: one file over HTTP(S), resumed after a cut and checked against its SHA-256;
//! * [`fetch_model`]: a known checkpoint's folder in the cache (`$DENS3R_HOME/models/NAME`,
//!   default `~/.cache/dens3r`), downloaded from the hub (`$DENS3R_HUB_ENDPOINT`, default
//!   `https://huggingface.co`) when missing; the folder is what `--weights` takes.

pub mod catalogue;
pub mod download;

pub use catalogue::{find, Known, Source, KNOWN};
pub use download::{download, Fetched, Progress};

use std::path::{Path, PathBuf};

dens3r_io::file_or_setting_error! {
    /// Why a checkpoint could not be found or fetched: one line naming the file or address and
    /// what to do.
    HubError;
    files: [dens3r_io::IoError];
    plain: [];
}

/// The environment variable naming the cache folder.
pub const HOME_ENV: &str = "DENS3R_HOME";
/// The environment variable naming the hub's address (for mirrors and tests).
pub const ENDPOINT_ENV: &str = "DENS3R_HUB_ENDPOINT";
/// The hub used when no endpoint is set.
pub const DEFAULT_ENDPOINT: &str = "https://huggingface.co";

/// The cache folder: `$DENS3R_HOME`, else `$XDG_CACHE_HOME/dens3r`, else `~/.cache/dens3r`.
pub fn home() -> PathBuf {
    let var = |n: &str| std::env::var_os(n).filter(|v| !v.is_empty()).map(PathBuf::from);
    var(HOME_ENV)
        .or_else(|| var("XDG_CACHE_HOME").map(|d| d.join("dens3r")))
        .or_else(|| var("HOME").map(|d| d.join(".cache").join("dens3r")))
        .unwrap_or_else(|| PathBuf::from(".cache").join("dens3r"))
}

/// The hub's address: `$DENS3R_HUB_ENDPOINT`, else Hugging Face's `$HF_ENDPOINT`, else
/// [`DEFAULT_ENDPOINT`]; without a trailing slash.
pub fn endpoint() -> String {
    [ENDPOINT_ENV, "HF_ENDPOINT"]
        .iter()
        .find_map(|n| std::env::var(n).ok().filter(|v| !v.trim().is_empty()))
        .unwrap_or_else(|| DEFAULT_ENDPOINT.to_string())
        .trim()
        .trim_end_matches('/')
        .to_string()
}

/// The cache folder of a known checkpoint.
pub fn model_dir(k: &Known) -> PathBuf {
    home().join("models").join(k.name)
}

/// Whether every file of a hub checkpoint is in the cache and has its format (a damaged or
/// wrong file is not "cached").
pub fn is_cached(k: &Known) -> bool {
    matches!(k.source, Source::Hub { .. })
        && catalogue::HUB_FILES.iter().all(|f| download::check_hub_file(f, &model_dir(k).join(f)).is_ok())
}

/// The most bytes a hub file of `k` may have: its catalogue size with a quarter and 64 MB
/// to spare for the weights, 1 MB for the config.
pub fn max_bytes(k: &Known, file: &str) -> u64 {
    match file {
        "model.safetensors" => (k.size_mb as u64 * 5 / 4 + 64) << 20,
        _ => 1 << 20,
    }
}

/// The state of a cached checkpoint file, checked in full: its format, and its SHA-256
/// against the record its download left beside it.
pub fn verify_cached(k: &Known, file: &str) -> Result<String, HubError> {
    let path = model_dir(k).join(file);
    download::check_hub_file(file, &path).map_err(|why| HubError::file(&path, format!("the cached file is {why}")))?;
    let side = model_dir(k).join(format!("{file}.sha256"));
    let record = std::fs::read_to_string(&side).ok();
    let sha = download::sha256_file(&path)?;
    match record.as_deref().and_then(|r| r.split_whitespace().next()) {
        Some(want) if want == sha => Ok(format!("SHA-256 {sha} matches its download record")),
        Some(want) => Err(HubError::file(
            &path,
            format!("the cached file's SHA-256 is {sha}, its download record says {want}: changed since"),
        )),
        None => Ok(format!("SHA-256 {sha} (no download record: not placed by dens3r)")),
    }
}

/// The cache folder of the hub checkpoint `k`, its missing files downloaded first (each
/// resumed after a cut and checked against the SHA-256 the hub publishes); `progress` gets the
/// file name and how far it is. A bundled or manual entry is an error saying where it is.
pub fn fetch_model(k: &Known, progress: &mut dyn FnMut(&str, Progress)) -> Result<PathBuf, HubError> {
    let repo = match k.source {
        Source::Hub { repo } => repo,
        Source::Manual { how } => return Err(HubError::invalid(format!("{}: no download address; {how}", k.name))),
        Source::Bundled => {
            return Err(HubError::invalid(format!("{} is bundled with dens3r; it needs no download", k.name)))
        }
    };
    let dir = model_dir(k);
    // The folders created here go again if nothing is downloaded into them (a refused or cut
    // download leaves no empty model folder that looks like a cached model).
    let created: Vec<PathBuf> = dir.ancestors().take_while(|d| !d.exists()).map(Path::to_path_buf).collect();
    std::fs::create_dir_all(&dir)
        .map_err(|e| HubError::file(&dir, format!("cannot create the cache folder ({e}); set ${HOME_ENV}")))?;
    let result = fetch_files(k, repo, &dir, progress);
    if result.is_err() {
        for d in &created {
            if std::fs::remove_dir(d).is_err() {
                break;
            }
        }
    }
    result
}

/// The hub files of `k` into `dir` ([`fetch_model`]).
fn fetch_files(
    k: &Known,
    repo: &str,
    dir: &Path,
    progress: &mut dyn FnMut(&str, Progress),
) -> Result<PathBuf, HubError> {
    let base = endpoint();
    for file in catalogue::HUB_FILES {
        let dest = dir.join(file);
        if dest.is_file() {
            match download::check_hub_file(file, &dest) {
                Ok(()) => continue,
                // A file an earlier download of dens3r's placed (its record beside it) is
                // fetched again; one placed by hand is the user's: named, not touched.
                Err(_) if dir.join(format!("{file}.sha256")).is_file() => {
                    std::fs::remove_file(&dest)
                        .map_err(|e| HubError::file(&dest, format!("damaged, and cannot be removed ({e})")))?;
                }
                Err(why) => {
                    return Err(HubError::file(
                        &dest,
                        format!(
                        "the cached file is {why}; remove it (dens3r did not place it) and run again to download it"
                    ),
                    ))
                }
            }
        }
        let url = format!("{base}/{repo}/resolve/main/{file}");
        let check = |p: &std::path::Path| download::check_hub_file(file, p);
        let expect = download::Expect { sha256: None, max_bytes: Some(max_bytes(k, file)), check: Some(&check) };
        let got = download::download_checked(&url, &dest, &expect, &mut |p| progress(file, p))?;
        let record = format!("{}  {}  {}\n", got.sha256, got.checked_against, url);
        let side = dir.join(format!("{file}.sha256"));
        dens3r_io::write_atomic(&side, |w| std::io::Write::write_all(w, record.as_bytes()))?;
    }
    Ok(dir.to_path_buf())
}
