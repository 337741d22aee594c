//! `OutputDir` in a process of its own (the cleanup tests remove every registered path of
//! their process, a run's lock and staging folder among them).

use dens3r_io::output::{Manifest, OutputDir, LOCK};

/// A run that fails leaves the folders it created only where they hold a file it kept (a
/// pair cache's entries); one that finishes moves its files in and lists them.
#[test]
fn unfinished_runs_leave_only_kept_files() {
    let tmp = tempfile::tempdir().unwrap();
    let dest = tmp.path().join("a/b/out");
    let out = OutputDir::begin(&dest).unwrap();
    std::fs::create_dir_all(dest.join("cache/entry")).unwrap();
    std::fs::write(out.root().join("x.txt"), "x").unwrap();
    drop(out);
    assert!(!tmp.path().join("a").exists());

    let out = OutputDir::begin(&dest).unwrap();
    std::fs::create_dir_all(dest.join("cache")).unwrap();
    std::fs::write(dest.join("cache/kept"), "pair").unwrap();
    drop(out);
    assert!(dest.join("cache/kept").is_file());
    assert_eq!(std::fs::read_dir(&dest).unwrap().count(), 1, "only the cache stays");

    let out = OutputDir::begin(&dest).unwrap();
    std::fs::create_dir_all(out.root().join("sub")).unwrap();
    std::fs::write(out.root().join("sub/y.txt"), "y").unwrap();
    out.finish().unwrap();
    assert_eq!(std::fs::read_to_string(dest.join("sub/y.txt")).unwrap(), "y");
    let m = Manifest::read(&dest).unwrap().unwrap();
    assert_eq!(m.files.iter().collect::<Vec<_>>(), ["sub/y.txt"]);
    assert!(!dest.join(LOCK).exists());
}
