//! Parity fixtures dumped from the official PyTorch code (model spec section 9), shared by the
//! crates' test files through `#[path]`.
//!
//! Fixture A (shared decoder) and the RoPE tables live in the repository, under
//! `tests/fixtures/parity/`, so every clone runs the core parity checks. Fixtures B and C and the
//! full-size key listings exist only in the team's `../shared/fixtures/` (or `$DENS3R_SHARED`):
//! the checks on them run when it is present and otherwise say SKIPPED; with
//! `DENS3R_REQUIRE_SHARED=1` an absent one fails the test instead.
#![allow(dead_code)]

use std::path::PathBuf;

/// The repository's root.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Fixture A: shared decoder, desc_conf off, two different 48x64 images.
pub const A: &str = "A_shared_dec_48x64";

/// A parity case bundled in the repository (`A_shared_dec_48x64` or `rope`).
pub fn parity(case: &str) -> PathBuf {
    let p = repo_root().join("tests/fixtures/parity").join(case);
    assert!(p.is_dir(), "{} is missing from the repository", p.display());
    p
}

/// `rel` under the team's shared folder (`$DENS3R_SHARED`, else `../shared` beside the
/// repository), or `None` with a SKIPPED line saying what `check` is skipped.
pub fn shared(rel: &str, check: &str) -> Option<PathBuf> {
    let root = std::env::var_os("DENS3R_SHARED").map(PathBuf::from).unwrap_or_else(|| repo_root().join("../shared"));
    let p = root.join(rel);
    if p.exists() {
        return Some(p);
    }
    let msg = format!(
        "{check}: {} is absent (it ships only beside the team's checkouts; set DENS3R_SHARED to its folder)",
        p.display()
    );
    if std::env::var_os("DENS3R_REQUIRE_SHARED").is_some_and(|v| v != "0") {
        panic!("{msg}");
    }
    eprintln!("SKIPPED: {msg}");
    None
}

/// A parity case that only `../shared/fixtures/parity/` holds (B, C), or `None` with a SKIPPED
/// line.
pub fn shared_parity(case: &str, check: &str) -> Option<PathBuf> {
    shared(&format!("fixtures/parity/{case}"), check)
}
