//! Where the bundled default model (dens3r-s, trained here by `scripts/train-default.sh`) lives.
//!
//! It is a Hugging Face style folder (`model.safetensors` + `config.json` + `MODEL_CARD.md`)
//! under `data-samples/models/dens3r-s/` in the repository. The commands that run the network
//! use it when no `--weights` is given.

use crate::BackboneError;
use std::path::{Path, PathBuf};

/// The default model's name.
pub const NAME: &str = "dens3r-s";

/// The folder inside the repository.
pub const REPO_DIR: &str = "data-samples/models/dens3r-s";

/// Environment variable that points at another default model folder (or checkpoint file).
pub const ENV: &str = "DENS3R_DEFAULT_MODEL";

/// The one line the commands print when they fall back to the default model.
pub fn notice(dir: &Path) -> String {
    format!(
        "using the bundled {NAME} ({}): a small model trained here on synthetic scenes; for better quality \
         give --weights with an official Dens3R / DUSt3R / MASt3R checkpoint (.pth, .safetensors or a Hugging Face folder)",
        dir.display()
    )
}

/// The default model: `$DENS3R_DEFAULT_MODEL` when set, else `data-samples/models/dens3r-s`
/// of the repository that holds the running executable (`target/release/dens3r`), else that
/// of the source tree this was built from.
pub fn locate() -> Result<PathBuf, BackboneError> {
    if let Some(p) = std::env::var_os(ENV) {
        let p = PathBuf::from(p);
        return if p.exists() {
            Ok(p)
        } else {
            Err(BackboneError::file(
                &p,
                format!("${ENV} names no file or folder; unset it or point it at a model folder"),
            ))
        };
    }
    let mut candidates = Vec::new();
    if let Ok(exe) = std::env::current_exe() {
        candidates.extend(exe.ancestors().skip(1).map(|d| d.join(REPO_DIR)));
    }
    candidates.push(Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").join(REPO_DIR));
    candidates
        .into_iter()
        .find(|d| d.join("model.safetensors").is_file())
        .map(|d| d.canonicalize().unwrap_or(d))
        .ok_or_else(|| {
            BackboneError::invalid(format!(
                "the bundled {NAME} model was not found ({REPO_DIR}/model.safetensors next to the repository's \
                 target/ folder); give --weights, set ${ENV}, or rebuild it with scripts/train-default.sh"
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn notice_names_the_folder_and_the_way_to_better_weights() {
        let line = notice(Path::new("/x/dens3r-s"));
        assert!(line.contains("/x/dens3r-s") && line.contains("--weights") && !line.contains('\n'));
    }
}
