//! `OutputDir` in a process of its own (the cleanup tests remove every registered path of
//! their process, a run's lock and staging folder among them).

use dens3r_io::output::{Manifest, OutputDir, LOCK, MANIFEST};

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

/// Issue 77, 10: a `kill -9` during `finish`'s moves left two runs' files mixed, and the next
/// run could not tell which were dens3r's. The journal written before the moves lists both
/// versions of each replaced file: after a stop at any point, the next run replaces them all
/// (either version is dens3r's), and the finished manifest keeps only its own stamps.
#[test]
fn a_stop_during_the_moves_leaves_files_the_next_run_knows() {
    use dens3r_io::output::{Manifest, Stamp};
    let tmp = tempfile::tempdir().unwrap();
    let dest = tmp.path().join("out");
    let write = |rel: &str, text: &str| {
        let out = OutputDir::begin(&dest).unwrap();
        std::fs::create_dir_all(out.root().join("scene")).unwrap();
        std::fs::write(out.root().join(rel), text).unwrap();
        std::fs::write(out.root().join("scene/cameras.json"), format!("cams of {text}")).unwrap();
        out.finish().unwrap();
    };
    write("a.txt", "first");
    // The state a stop after the first move leaves: the journal, a.txt new, the old index gone.
    let stamp_of = |text: &str| {
        let p = tmp.path().join("probe");
        std::fs::write(&p, text).unwrap();
        Stamp::of(&p).unwrap()
    };
    let mut journal = Manifest::read(&dest).unwrap().unwrap();
    journal.replacing = journal.stamps.clone();
    journal.stamps.insert("a.txt".into(), stamp_of("second"));
    journal.stamps.insert("scene/cameras.json".into(), stamp_of("cams of second"));
    std::fs::write(dest.join(MANIFEST), serde_json::to_string(&journal).unwrap()).unwrap();
    std::fs::write(dest.join("a.txt"), "second").unwrap();
    std::fs::remove_file(dest.join("scene/cameras.json")).unwrap();
    let m = Manifest::read(&dest).unwrap().unwrap();
    assert!(m.owns(&dest, "a.txt"));
    std::fs::write(dest.join("a.txt"), "first").unwrap();
    assert!(m.owns(&dest, "a.txt"), "the version before the move is dens3r's too");
    std::fs::write(dest.join("a.txt"), "a third text, the user's").unwrap();
    assert!(!m.owns(&dest, "a.txt"));
    std::fs::write(dest.join("a.txt"), "second").unwrap();
    write("a.txt", "third");
    assert_eq!(std::fs::read_to_string(dest.join("a.txt")).unwrap(), "third");
    let m = Manifest::read(&dest).unwrap().unwrap();
    assert!(m.replacing.is_empty() && m.owns(&dest, "scene/cameras.json"));
}
