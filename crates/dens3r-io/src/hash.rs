//! A stable content hash for cache keys (std's hasher may change between Rust versions).

use std::path::Path;

/// FNV-1a, 64 bit, with `seed` xor-ed into the offset basis.
pub fn fnv1a(bytes: &[u8], seed: u64) -> u64 {
    fnv1a_update(0xcbf2_9ce4_8422_2325u64 ^ seed, bytes)
}

/// Continues an FNV-1a hash whose state is `h` with more bytes: hashing in chunks gives
/// [`fnv1a`] of the whole.
pub fn fnv1a_update(mut h: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// The content hash of a file (FNV-1a of its bytes), remembered in the JSON file `memo` under
/// the file's path, size, modification and change times and inode, so an unchanged file is
/// read once. Any write to a file moves its change time, which no tool can set back (`cp -p`,
/// `rsync -t` and `touch` set only the modification time), so an edited file is read again.
/// A damaged or unwritable memo only costs the reading.
pub fn file_hash(path: &Path, memo: Option<&Path>) -> std::io::Result<u64> {
    let meta = std::fs::metadata(path)?;
    let stamp = |t: std::io::Result<std::time::SystemTime>| {
        t.ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map_or(0, |d| d.as_nanos())
    };
    #[cfg(unix)]
    let (ctime, ino) = {
        use std::os::unix::fs::MetadataExt;
        (meta.ctime() as i128 * 1_000_000_000 + meta.ctime_nsec() as i128, meta.ino())
    };
    #[cfg(not(unix))]
    let (ctime, ino) = (0i128, 0u64);
    let canon = path.canonicalize().unwrap_or_else(|_| path.to_path_buf());
    let key = format!("{} {} {} {ctime} {ino}", canon.display(), meta.len(), stamp(meta.modified()));
    let mut known: std::collections::BTreeMap<String, String> = memo
        .and_then(|m| std::fs::read_to_string(m).ok())
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default();
    if let Some(h) = known.get(&key).and_then(|h| u64::from_str_radix(h, 16).ok()) {
        return Ok(h);
    }
    let h = content_hash(path)?;
    if let Some(m) = memo {
        // Entries of the same path under older stamps are dropped.
        let prefix = format!("{} ", canon.display());
        known.retain(|k, _| !k.starts_with(&prefix));
        known.insert(key, format!("{h:016x}"));
        if let Ok(text) = serde_json::to_string_pretty(&known) {
            let _ = crate::write_atomic(m, |w| std::io::Write::write_all(w, text.as_bytes()));
        }
    }
    Ok(h)
}

/// FNV-1a of a file's bytes, read in 1 MB pieces (no memo).
pub fn content_hash(path: &Path) -> std::io::Result<u64> {
    let mut f = std::fs::File::open(path)?;
    let mut buf = vec![0u8; 1 << 20];
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    loop {
        let n = std::io::Read::read(&mut f, &mut buf)?;
        if n == 0 {
            return Ok(h);
        }
        h = fnv1a_update(h, &buf[..n]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The published FNV-1a 64-bit test vectors, whole and in chunks.
    #[test]
    fn fnv1a_matches_the_reference_vectors() {
        assert_eq!(fnv1a(b"", 0), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a(b"a", 0), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(fnv1a(b"foobar", 0), 0x8594_4171_f739_67e8);
        assert_eq!(fnv1a_update(fnv1a(b"foo", 0), b"bar"), 0x8594_4171_f739_67e8);
    }
}
