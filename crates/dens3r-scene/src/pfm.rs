//! Portable float maps (`.pfm`), the format of Middlebury 2014's and Scene Flow's disparity:
//! a text header (`Pf` grey or `PF` colour, width and height, a scale whose sign gives the byte
//! order: negative little-endian) and rows of f32 from the bottom one up. Unknown disparity is
//! stored as infinity.

use crate::error::SceneError;
use std::path::Path;

/// Largest side accepted (guards against damaged headers).
const MAX_SIDE: usize = 1 << 16;

/// Reads a grey `.pfm` as `(width, height, values)`, rows top to bottom.
pub fn read_pfm(path: &Path) -> Result<(usize, usize, Vec<f32>), SceneError> {
    let bytes = std::fs::read(path).map_err(|e| SceneError::new(path, format!("cannot read: {e}")))?;
    let bad = |m: &str| SceneError::new(path, format!("not a valid .pfm file: {m}"));
    // Three whitespace-separated header fields after the magic, then one whitespace byte.
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while at < bytes.len() && bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        let start = at;
        while at < bytes.len() && !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        if start == at || at - start > 32 {
            return Err(bad("its header is cut short or damaged"));
        }
        fields.push(std::str::from_utf8(&bytes[start..at]).map_err(|_| bad("its header is not text"))?);
    }
    at += 1;
    match fields[0] {
        "Pf" => {}
        "PF" => return Err(SceneError::new(path, "is a colour .pfm (PF); give a grey one (Pf)")),
        _ => return Err(bad("it does not start with Pf")),
    }
    let side = |s: &str| s.parse::<usize>().ok().filter(|v| (1..=MAX_SIDE).contains(v));
    let (Some(w), Some(h)) = (side(fields[1]), side(fields[2])) else {
        return Err(bad(&format!("its size {}x{} is not 1 to {MAX_SIDE} a side", fields[1], fields[2])));
    };
    let scale: f32 = fields[3]
        .parse()
        .ok()
        .filter(|s: &f32| s.is_finite() && *s != 0.0)
        .ok_or_else(|| bad("its scale is not a non-zero number"))?;
    let body = bytes.get(at..).unwrap_or(&[]);
    if body.len() != w * h * 4 {
        return Err(bad(&format!(
            "{w}x{h} needs {} bytes of data, the file has {} (truncated or damaged)",
            w * h * 4,
            body.len()
        )));
    }
    let word = |c: &[u8]| {
        let b = [c[0], c[1], c[2], c[3]];
        if scale < 0.0 {
            f32::from_le_bytes(b)
        } else {
            f32::from_be_bytes(b)
        }
    };
    let rows: Vec<&[u8]> = body.chunks_exact(w * 4).collect();
    let values = rows.iter().rev().flat_map(|r| r.chunks_exact(4).map(word)).collect();
    Ok((w, h, values))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pfm(header: &str, rows_bottom_up: &[[f32; 3]], little: bool) -> Vec<u8> {
        let mut b = header.as_bytes().to_vec();
        for r in rows_bottom_up {
            for v in r {
                b.extend(if little { v.to_le_bytes() } else { v.to_be_bytes() });
            }
        }
        b
    }

    #[test]
    fn reads_both_byte_orders_top_row_first() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.pfm");
        // Stored bottom row first: the top row (10, 11, inf) comes out first.
        let rows = [[1.0, 2.0, 3.0], [10.0, 11.0, f32::INFINITY]];
        for (header, little) in [("Pf\n3 2\n-1.0\n", true), ("Pf\n3 2\n1.0\n", false)] {
            std::fs::write(&p, pfm(header, &rows, little)).unwrap();
            let (w, h, v) = read_pfm(&p).unwrap();
            assert_eq!((w, h), (3, 2));
            assert_eq!(v, [10.0, 11.0, f32::INFINITY, 1.0, 2.0, 3.0]);
        }
    }

    #[test]
    fn damaged_files_are_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.pfm");
        let rows = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
        let cases: [(Vec<u8>, &str); 5] = [
            (pfm("Pf\n3 2\n-1.0\n", &rows, true)[..30].to_vec(), "truncated"),
            (pfm("PF\n3 2\n-1.0\n", &rows, true), "colour"),
            (pfm("P6\n3 2\n-1.0\n", &rows, true), "Pf"),
            (pfm("Pf\n3 99999999\n-1.0\n", &rows, true), "a side"),
            (b"Pf\n3".to_vec(), "cut short"),
        ];
        for (bytes, why) in cases {
            std::fs::write(&p, bytes).unwrap();
            let e = read_pfm(&p).unwrap_err().to_string();
            assert!(e.contains("d.pfm") && e.contains(why), "{why}: {e}");
        }
    }
}
