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

use std::path::PathBuf;

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

/// Whether every file of a hub checkpoint is in the cache.
pub fn is_cached(k: &Known) -> bool {
    matches!(k.source, Source::Hub { .. }) && catalogue::HUB_FILES.iter().all(|f| model_dir(k).join(f).is_file())
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
    std::fs::create_dir_all(&dir)
        .map_err(|e| HubError::file(&dir, format!("cannot create the cache folder ({e}); set ${HOME_ENV}")))?;
    let base = endpoint();
    for file in catalogue::HUB_FILES {
        let dest = dir.join(file);
        if dest.is_file() {
            continue;
        }
        let url = format!("{base}/{repo}/resolve/main/{file}");
        let got = download::download(&url, &dest, None, &mut |p| progress(file, p))?;
        let record = format!("{}  {}  {}\n", got.sha256, got.checked_against, url);
        let side = dir.join(format!("{file}.sha256"));
        dens3r_io::write_atomic(&side, |w| std::io::Write::write_all(w, record.as_bytes()))?;
    }
    Ok(dir)
}
