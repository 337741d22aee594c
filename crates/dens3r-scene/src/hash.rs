//! A stable content hash for cache keys (std's hasher may change between Rust versions).

/// FNV-1a, 64 bit, with `seed` xor-ed into the offset basis.
pub fn fnv1a(bytes: &[u8], seed: u64) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64 ^ seed;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}
