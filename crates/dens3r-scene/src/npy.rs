//! NumPy `.npy` arrays (float32, C order) through the `npyz` crate, so numpy users read our
//! files as they are (`np.load`).

use crate::error::SceneError;
use npyz::WriterBuilder;
use std::path::Path;

/// Largest array we read, in elements (guards against corrupt headers).
const MAX_ELEMENTS: u64 = 1 << 31;

/// Reads a float array (`<f4`, or `<f8` converted) and its shape.
pub fn read_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>), SceneError> {
    let bytes = std::fs::read(path).map_err(|e| SceneError::new(path, format!("cannot read: {e}")))?;
    let bad = |m: String| SceneError::new(path, m);
    if header_len(&bytes).is_some_and(|(at, len)| at.saturating_add(len) > bytes.len()) {
        return Err(bad("not a valid .npy file: its header is longer than the file (truncated or damaged)".into()));
    }
    if header_shape_overflows(&bytes) {
        return Err(bad("array shape is too large (its element count overflows)".into()));
    }
    let npy = npyz::NpyFile::new(&bytes[..])
        .map_err(|e| bad(format!("not a valid .npy file ({e}); save it with numpy.save")))?;
    if npy.order() == npyz::Order::Fortran {
        return Err(bad("array is in Fortran order; save it with numpy.save(np.ascontiguousarray(a))".into()));
    }
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let elements = npy.shape().iter().try_fold(1u64, |n, &d| n.checked_mul(d)).filter(|&n| n <= MAX_ELEMENTS);
    let Some(elements) = elements else {
        return Err(bad(format!("array shape {shape:?} is too large")));
    };
    // The header's shape must fit in the bytes that follow it (no allocation for data the
    // file does not hold).
    let item = npy.dtype().num_bytes().unwrap_or(1) as u64;
    if elements.saturating_mul(item) > bytes.len() as u64 {
        return Err(bad(format!("array data is truncated: shape {shape:?} needs more bytes than the file holds")));
    }
    let truncated = |e: std::io::Error| bad(format!("array data is truncated or unreadable ({e})"));
    let data = match npy.try_data::<f32>() {
        Ok(r) => r.collect::<std::io::Result<Vec<f32>>>().map_err(truncated)?,
        Err(npy) => match npy.try_data::<f64>() {
            Ok(r) => {
                r.collect::<std::io::Result<Vec<f64>>>().map_err(truncated)?.into_iter().map(|v| v as f32).collect()
            }
            Err(npy) => return Err(bad(format!("dtype {} is not supported; save as float32", npy.dtype().descr()))),
        },
    };
    Ok((shape, data))
}

/// Where the header text starts and its declared length (format versions 1 to 3).
fn header_len(bytes: &[u8]) -> Option<(usize, usize)> {
    match bytes.get(6) {
        Some(1) => bytes.get(8..10).map(|l| (10, u16::from_le_bytes([l[0], l[1]]) as usize)),
        Some(2 | 3) => bytes.get(8..12).map(|l| (12, u32::from_le_bytes([l[0], l[1], l[2], l[3]]) as usize)),
        _ => None,
    }
}

/// Whether the header's `'shape': (...)` multiplies out past `u64` (npyz's own products of
/// it would overflow). Unparsable headers are left to npyz, which refuses them.
fn header_shape_overflows(bytes: &[u8]) -> bool {
    let text = header_len(bytes).and_then(|(at, len)| bytes.get(at..at.saturating_add(len).min(bytes.len())));
    let Some(text) = text.map(String::from_utf8_lossy) else { return false };
    let Some(tuple) = text.split("'shape'").nth(1).and_then(|t| t.split(')').next()) else { return false };
    let mut n = 1u64;
    for d in tuple.split(|c: char| !c.is_ascii_digit()).filter(|d| !d.is_empty()) {
        // Zero dimensions count as one: npyz also multiplies the strides, which skip none.
        match d.parse::<u64>().ok().and_then(|d| n.checked_mul(d.max(1))) {
            Some(m) => n = m,
            None => return true,
        }
    }
    false
}

/// Writes a float32 array of the given shape atomically.
pub fn write_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<(), SceneError> {
    assert_eq!(shape.iter().product::<usize>(), data.len(), "shape does not match data length");
    let mut buf = Vec::with_capacity(data.len() * 4 + 128);
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let io = |e: std::io::Error| SceneError::new(path, format!("cannot encode: {e}"));
    let mut w = npyz::WriteOptions::new().default_dtype().shape(&shape).writer(&mut buf).begin_nd().map_err(io)?;
    w.extend(data.iter().copied()).map_err(io)?;
    w.finish().map_err(io)?;
    dens3r_io::write_atomic(path, |f| std::io::Write::write_all(f, &buf))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Damaged headers found by the mutation test (`dens3r-cli/tests/fuzz_readers.rs`): each
    /// panicked (overflow) or allocated hundreds of MB before.
    #[test]
    fn damaged_headers_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.npy");
        let header = |shape: &str| {
            let text = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({shape}), }}");
            let mut b = b"\x93NUMPY\x01\x00".to_vec();
            b.extend((text.len() as u16).to_le_bytes());
            b.extend(text.as_bytes());
            b.extend([0u8; 16]);
            b
        };
        for shape in ["4294967296, 4294967296, 2", "0, 18446744073709551615, 2", "100000, 100000"] {
            std::fs::write(&p, header(shape)).unwrap();
            let e = read_f32(&p).unwrap_err().to_string();
            assert!(e.contains("a.npy") && (e.contains("too large") || e.contains("truncated")), "{shape}: {e}");
        }
        // A version-2 header whose declared length runs past the file.
        let mut b = b"\x93NUMPY\x02\x00".to_vec();
        b.extend(0x2000_0000u32.to_le_bytes());
        b.extend(b"{'descr': '<f4'");
        std::fs::write(&p, b).unwrap();
        assert!(read_f32(&p).unwrap_err().to_string().contains("longer than the file"));
    }

    #[test]
    fn round_trip_and_header_is_numpy_compatible() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5).collect();
        write_f32(&p, &[2, 4, 3], &data).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..6], b"\x93NUMPY");
        let header = String::from_utf8_lossy(&bytes[10..80]);
        assert!(header.contains("'descr': '<f4'") && header.contains("'shape': (2, 4, 3"), "{header}");
        assert_eq!(read_f32(&p).unwrap(), (vec![2, 4, 3], data));
    }

    #[test]
    fn hand_made_float64_file_is_converted() {
        // A version-1.0 header written by hand the way numpy does: magic, version, length.
        let mut header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (2,), }".to_vec();
        while !(10 + header.len() + 1).is_multiple_of(64) {
            header.push(b' ');
        }
        header.push(b'\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend((header.len() as u16).to_le_bytes());
        bytes.extend(header);
        bytes.extend(1.5f64.to_le_bytes());
        bytes.extend((-2.0f64).to_le_bytes());
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.npy");
        std::fs::write(&p, bytes).unwrap();
        assert_eq!(read_f32(&p).unwrap(), (vec![2], vec![1.5, -2.0]));
        std::fs::write(&p, b"garbage").unwrap();
        assert!(read_f32(&p).unwrap_err().to_string().contains("not a valid .npy"));
    }
}
