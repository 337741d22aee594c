//! `file_hash` in a process of its own (the cleanup tests remove every registered temporary
//! file of their process, the memo's among them).

use dens3r_io::hash::{file_hash, fnv1a};

/// An edit that keeps the size and the modification time (as `cp -p` / `rsync -t` do) is
/// read again: the memo is keyed by the change time too.
#[test]
fn file_hash_sees_edits_that_keep_size_and_mtime() {
    let dir = tempfile::tempdir().unwrap();
    let (f, memo) = (dir.path().join("w.bin"), dir.path().join("memo.json"));
    std::fs::write(&f, b"weights one").unwrap();
    let t = std::fs::metadata(&f).unwrap().modified().unwrap();
    let a = file_hash(&f, Some(&memo)).unwrap();
    assert_eq!(a, fnv1a(b"weights one", 0));
    assert!(memo.is_file());
    // Remembered: the same answer without reading (shown by a poisoned memo entry).
    let text = std::fs::read_to_string(&memo).unwrap().replace(&format!("{a:016x}"), "00000000000000aa");
    std::fs::write(&memo, text).unwrap();
    assert_eq!(file_hash(&f, Some(&memo)).unwrap(), 0xaa);
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::write(&f, b"weights two").unwrap();
    std::fs::File::options().write(true).open(&f).unwrap().set_modified(t).unwrap();
    assert_eq!(std::fs::metadata(&f).unwrap().modified().unwrap(), t);
    assert_eq!(file_hash(&f, Some(&memo)).unwrap(), fnv1a(b"weights two", 0));
    assert_eq!(file_hash(&f, None).unwrap(), fnv1a(b"weights two", 0));
}
