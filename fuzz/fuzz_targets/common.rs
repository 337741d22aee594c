//! The case folder of each reader, set up once per process; every input replaces the
//! reader's file in it and is read (refusals are fine, a panic or an abort is the finding).

#[path = "../../crates/dens3r-cli/tests/readers/mod.rs"]
mod readers;

use std::path::PathBuf;
use std::sync::OnceLock;

pub fn run(name: &str, data: &[u8]) {
    static CASE: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let targets = readers::targets();
    let t = targets.iter().find(|t| t.name == name).expect("a reader of readers::targets()");
    let (_, dir) = CASE.get_or_init(|| {
        let tmp = tempfile::tempdir().expect("a temporary folder");
        let dir = tmp.path().join("case");
        readers::prepare(t, &dir);
        (tmp, dir)
    });
    let _ = readers::run(t, dir, data);
}
