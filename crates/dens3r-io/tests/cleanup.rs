//! The cleanup registry in a process of its own: `remove_all` removes every path its process
//! registered, so beside other tests (an atomic write in flight) it would remove theirs.

use dens3r_io::cleanup::{leftover_pid, remove_all, stage, sweep_stale, temp_prefix};

#[test]
fn staged_paths_are_removed_and_stale_ones_swept() {
    let dir = tempfile::tempdir().unwrap();
    let (f, d) = (dir.path().join("a.tmp"), dir.path().join("b.stage"));
    std::fs::write(&f, b"x").unwrap();
    std::fs::create_dir_all(d.join("inner")).unwrap();
    let (_gf, _gd) = (stage(&f), stage(&d));
    let kept = dir.path().join("kept");
    std::fs::write(&kept, b"y").unwrap();
    drop(stage(&kept)); // finished: no longer removed
    assert!(remove_all() >= 2);
    assert!(!f.exists() && !d.exists() && kept.exists());

    // A dead writer's leftovers go, a live one's (ours) and other files stay.
    let dead = dir.path().join(".dens3r-tmp-4000000000-abc123");
    let ours = dir.path().join(format!("{}xyz789", temp_prefix()));
    let stage_dir = dir.path().join(".dens3r-stage-4000000001");
    std::fs::write(&dead, b"").unwrap();
    std::fs::write(&ours, b"").unwrap();
    std::fs::create_dir(&stage_dir).unwrap();
    // Issue 77, 3: names that only contain a marker are a user's (they used to go).
    let users = [
        "archive-dens3r-old-2024",
        "x.dens3r-stage-4000000001",
        ".dens3r-stage-4000000001-mine",
        ".dens3r-tmp-4000000000-abc",
        "notes-dens3r-tmp-4000000000-abc123",
        ".dens3r-old-4000000002",
    ];
    for u in users {
        std::fs::create_dir(dir.path().join(u)).unwrap();
        std::fs::write(dir.path().join(u).join("keep.txt"), b"mine").unwrap();
    }
    sweep_stale(dir.path());
    if cfg!(target_os = "linux") {
        assert!(!dead.exists() && !stage_dir.exists());
    }
    assert!(ours.exists() && kept.exists());
    for u in users {
        assert!(dir.path().join(u).join("keep.txt").is_file(), "{u} was swept");
    }
    assert_eq!(leftover_pid(".dens3r-stage-12"), Some(12));
    assert_eq!(leftover_pid(&format!("{}aB3dE9", temp_prefix())), Some(std::process::id()));
}
