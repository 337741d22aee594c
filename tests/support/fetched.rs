//! Test data fetched by `scripts/fetch-data.sh` into `.cache/data/` (or `$DENS3R_DATA`),
//! shared by the crates' test files through `#[path]`.

use std::path::PathBuf;

/// `rel` under the data folder, or `None` with a SKIPPED line naming the fetch and `source`;
/// under CI (where the fetch is part of the run) an absent file fails the test instead.
pub fn fetched(rel: &str, source: &str) -> Option<PathBuf> {
    let dir = std::env::var_os("DENS3R_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.cache/data"));
    let p = dir.join(rel);
    if p.exists() {
        return Some(p);
    }
    let msg = format!("{} is absent: run scripts/fetch-data.sh ({source}) to enable this test", p.display());
    if std::env::var_os("CI").is_some() {
        panic!("{msg}");
    }
    eprintln!("SKIPPED: {msg}");
    None
}
