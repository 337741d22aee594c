//! Named f32 tensors as safetensors, with JSON beside them: the one checkpoint format of
//! dens3r's trainers (heads, neural SDF fields, training state). Written atomically; read back
//! with every tensor checked (present, f32, finite, and the shape asked for), so a damaged or
//! foreign file is refused with its name, never trusted.

use crate::{write_atomic, IoError};
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;
use std::io::Write;
use std::path::Path;

/// A tensor to write: name, shape, row-major values.
pub type Named<'a> = (String, Vec<usize>, &'a [f32]);

/// The safetensors bytes of `tensors`, stored as `dtype` (F32, F16 or BF16, rounded to
/// nearest; any other dtype stores F32).
pub fn serialize(tensors: &[Named], dtype: Dtype) -> Result<Vec<u8>, safetensors::SafeTensorError> {
    let dtype = if matches!(dtype, Dtype::F16 | Dtype::BF16) { dtype } else { Dtype::F32 };
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|(_, _, v)| match dtype {
            Dtype::F16 => v.iter().flat_map(|x| half::f16::from_f32(*x).to_le_bytes()).collect(),
            Dtype::BF16 => v.iter().flat_map(|x| half::bf16::from_f32(*x).to_le_bytes()).collect(),
            _ => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        })
        .collect();
    let views = tensors
        .iter()
        .zip(&bytes)
        .map(|((n, s, _), b)| Ok((n.clone(), TensorView::new(dtype, s.clone(), b)?)))
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
    safetensors::serialize(views, None)
}

/// Writes `tensors` to `path` as f32 safetensors (atomically); returns the file's size.
pub fn save(path: &Path, tensors: &[Named]) -> Result<u64, IoError> {
    let data = serialize(tensors, Dtype::F32).map_err(|e| IoError::new(path, e.to_string()))?;
    write_atomic(path, |w| w.write_all(&data))?;
    Ok(data.len() as u64)
}

/// Writes `value` to `path` as pretty JSON (atomically).
pub fn save_json(path: &Path, value: &impl serde::Serialize) -> Result<(), IoError> {
    let text = serde_json::to_vec_pretty(value).map_err(|e| IoError::new(path, e.to_string()))?;
    write_atomic(path, |w| w.write_all(&text))
}

/// A safetensors file read whole, its header parsed once, its tensors handed out checked.
pub struct TensorFile {
    path: std::path::PathBuf,
    bytes: Vec<u8>,
    /// Name -> (dtype, shape, byte range in `bytes`), in the file's order.
    index: Vec<(String, Dtype, Vec<usize>, std::ops::Range<usize>)>,
}

impl TensorFile {
    /// Reads `path`, refusing a file that is not safetensors (`fix` says what to do then,
    /// e.g. "delete it and retrain").
    pub fn open(path: &Path, fix: &str) -> Result<Self, IoError> {
        let bytes = std::fs::read(path).map_err(|e| IoError::new(path, format!("cannot read ({e})")))?;
        let st = SafeTensors::deserialize(&bytes)
            .map_err(|e| IoError::new(path, format!("not a valid safetensors file ({e}); {fix}")))?;
        let base = bytes.as_ptr() as usize;
        let index = st
            .tensors()
            .into_iter()
            .map(|(name, t)| {
                let start = t.data().as_ptr() as usize - base;
                (name, t.dtype(), t.shape().to_vec(), start..start + t.data().len())
            })
            .collect();
        Ok(Self { path: path.to_path_buf(), bytes, index })
    }

    /// The names of its tensors.
    pub fn names(&self) -> Vec<String> {
        self.index.iter().map(|t| t.0.clone()).collect()
    }

    /// The file's size in bytes.
    pub fn len_bytes(&self) -> u64 {
        self.bytes.len() as u64
    }

    /// Tensor `name`: its shape and values; an error naming the file when it is missing, not
    /// f32, or holds NaN or infinity.
    pub fn get(&self, name: &str) -> Result<(Vec<usize>, Vec<f32>), IoError> {
        let err = |m: String| IoError::new(&self.path, m);
        let (_, dtype, shape, range) =
            self.index.iter().find(|t| t.0 == name).ok_or_else(|| err(format!("tensor {name} is missing")))?;
        if *dtype != Dtype::F32 {
            return Err(err(format!("tensor {name} is {dtype:?} {shape:?}, expected F32")));
        }
        let v: Vec<f32> =
            self.bytes[range.clone()].chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(err(format!("tensor {name} holds NaN or infinity")));
        }
        Ok((shape.clone(), v))
    }

    /// Tensor `name`, which must have `shape`.
    pub fn get_shaped(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, IoError> {
        let (s, v) = self.get(name)?;
        if s != shape {
            return Err(IoError::new(&self.path, format!("tensor {name} is F32 {s:?}, expected F32 {shape:?}")));
        }
        Ok(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What is saved reads back bit for bit; a missing name, a wrong shape, NaN and a damaged
    /// file are refused naming the file.
    #[test]
    fn round_trip_and_refusals() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.safetensors");
        let a = [1.0f32, -2.5, 3.25, 1e-30, 7.0, 0.0];
        let n = save(&p, &[("a".into(), vec![2, 3], &a), ("nan".into(), vec![1], &[f32::NAN])]).unwrap();
        let f = TensorFile::open(&p, "delete it").unwrap();
        assert_eq!(f.len_bytes(), n);
        assert_eq!(f.get("a").unwrap(), (vec![2, 3], a.to_vec()));
        assert_eq!(f.get_shaped("a", &[2, 3]).unwrap(), a.to_vec());
        for e in [f.get("b").unwrap_err(), f.get_shaped("a", &[3, 2]).unwrap_err(), f.get("nan").unwrap_err()] {
            assert!(e.path == p && !e.message.is_empty(), "{e}");
        }
        std::fs::write(&p, b"garbage").unwrap();
        let e = TensorFile::open(&p, "delete it").err().unwrap().to_string();
        assert!(e.contains("t.safetensors") && e.contains("delete it"), "{e}");
    }

    /// F16 storage rounds to the nearest half (1/3 -> 0.333251953125).
    #[test]
    fn half_precision_rounds_to_nearest() {
        let bytes = serialize(&[("x".into(), vec![1], &[1.0 / 3.0])], Dtype::F16).unwrap();
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let t = st.tensor("x").unwrap();
        assert_eq!(t.dtype(), Dtype::F16);
        assert_eq!(half::f16::from_le_bytes([t.data()[0], t.data()[1]]).to_f32(), 0.333_251_95);
    }
}
