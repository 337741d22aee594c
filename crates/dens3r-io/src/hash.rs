//! A stable content hash for cache keys (std's hasher may change between Rust versions).

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
