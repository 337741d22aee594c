//! Checkpoint tensors by name (safetensors; f32, f16 or bf16 stored, f32 in memory), with
//! shape checks, PyTorch's aliased DPT keys, and a record of which keys were used so that a
//! wrong or partial checkpoint is reported with its missing, unexpected and mis-shaped keys.

use burn::tensor::{Device, Tensor, TensorData};
use std::cell::RefCell;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

dens3r_io::file_error! {
    /// A checkpoint problem, naming the file and the keys at fault.
    WeightsError;
    from: [dens3r_io::IoError];
}

/// A tensor's shape and row-major f32 values.
type Stored = (Vec<usize>, Vec<f32>);

/// Where a checkpoint tensor's bytes are in the file.
#[derive(Debug, Clone, Copy)]
struct Extent {
    dtype: safetensors::Dtype,
    /// Absolute byte range in the file.
    start: u64,
    end: u64,
}

/// Named f32 tensors of a checkpoint. Only the header is read up front; each tensor is read
/// and converted when the model asks for it, so loading never holds the file and the model
/// in memory at once (peak = model + one tensor).
pub struct Weights {
    path: PathBuf,
    file: Option<RefCell<std::fs::File>>,
    tensors: BTreeMap<String, (Vec<usize>, Extent)>,
    unreadable: RefCell<Vec<String>>,
    used: RefCell<BTreeSet<String>>,
    missing: RefCell<Vec<String>>,
    misshaped: RefCell<Vec<String>>,
    /// Tensors holding NaN or Inf values.
    nonfinite: RefCell<Vec<String>>,
    /// Synthetic mode: `(rng state, std)`; missing keys are generated and recorded.
    synthetic: Option<RefCell<(u64, f32)>>,
    generated: RefCell<Vec<(String, Stored)>>,
    /// `args.model` of an official `.pth` (the constructor call it was trained with).
    args_model: Option<String>,
    /// Tensors in the file that are not read (integer, bool, non-contiguous), and why.
    skipped: BTreeMap<String, String>,
    /// Keys the model asked for that are among `skipped`.
    unusable: RefCell<Vec<String>>,
}

impl Weights {
    /// Opens a `.safetensors` file and reads its header (tensor names, dtypes, shapes,
    /// offsets), checking that every tensor lies inside the file.
    pub fn from_safetensors(path: &Path) -> Result<Self, WeightsError> {
        use std::io::Read;
        let err = |m: String| WeightsError { path: path.to_path_buf(), message: m };
        if path.extension().is_some_and(|e| e == "pth" || e == "pt") {
            return Self::from_pth(path);
        }
        let corrupt = |m: &str| err(format!("not a valid safetensors file ({m}); re-export the checkpoint"));
        let mut file = std::fs::File::open(path).map_err(|e| err(format!("cannot read the checkpoint: {e}")))?;
        let file_len = file.metadata().map_err(|e| err(format!("cannot read the checkpoint: {e}")))?.len();
        let mut n = [0u8; 8];
        file.read_exact(&mut n).map_err(|_| corrupt("shorter than its 8-byte header length"))?;
        let n = u64::from_le_bytes(n);
        if n > 100_000_000 || 8 + n > file_len {
            return Err(corrupt(&format!("header length {n} does not fit a {file_len}-byte file")));
        }
        let mut header = vec![0u8; n as usize];
        file.read_exact(&mut header).map_err(|_| corrupt("truncated header"))?;
        let header: BTreeMap<String, serde_json::Value> =
            serde_json::from_slice(&header).map_err(|e| corrupt(&format!("header is not JSON: {e}")))?;
        let mut tensors = BTreeMap::new();
        let mut skipped = BTreeMap::new();
        // Every tensor's bytes, to refuse two tensors sharing bytes.
        let mut spans: Vec<(u64, u64, String)> = Vec::new();
        for (name, info) in header {
            if name == "__metadata__" {
                continue;
            }
            let bad = |m: &str| corrupt(&format!("tensor '{name}': {m}"));
            let dtype = info["dtype"].as_str().ok_or_else(|| bad("no dtype"))?;
            let shape: Vec<usize> = serde_json::from_value(info["shape"].clone()).map_err(|_| bad("bad shape"))?;
            let offs: [u64; 2] =
                serde_json::from_value(info["data_offsets"].clone()).map_err(|_| bad("bad offsets"))?;
            let (float, size) = match dtype {
                "F32" => (Some(safetensors::Dtype::F32), 4),
                "F16" => (Some(safetensors::Dtype::F16), 2),
                "BF16" => (Some(safetensors::Dtype::BF16), 2),
                "I64" | "U64" | "F64" => (None, 8),
                "I32" | "U32" => (None, 4),
                "I16" | "U16" => (None, 2),
                "BOOL" | "U8" | "I8" => (None, 1),
                other => return Err(err(format!("tensor '{name}' has dtype {other}; store f32, f16 or bf16"))),
            };
            let count =
                shape.iter().try_fold(1u64, |a, &d| a.checked_mul(d as u64)).ok_or_else(|| bad("huge shape"))?;
            let at = |o: u64| (8 + n).checked_add(o);
            let fits = match (at(offs[0]), at(offs[1]), count.checked_mul(size)) {
                (Some(start), Some(end), Some(bytes))
                    if offs[0] <= offs[1] && end <= file_len && end - start == bytes =>
                {
                    Some((start, end))
                }
                _ => None,
            };
            let Some((start, end)) = fits else {
                return Err(bad(&format!(
                    "bytes {}..{} do not hold {shape:?} {dtype} in a {file_len}-byte file",
                    offs[0], offs[1]
                )));
            };
            spans.push((start, end, name.clone()));
            match float {
                Some(dtype) => {
                    tensors.insert(name, (shape, Extent { dtype, start, end }));
                }
                // Integer and bool tensors are left out; a model that needs one names its dtype.
                None => {
                    skipped.insert(name, format!("stored as {dtype}"));
                }
            }
        }
        spans.sort();
        for w in spans.windows(2) {
            if w[1].0 < w[0].1 && w[1].0 < w[1].1 {
                return Err(corrupt(&format!("tensors '{}' and '{}' share bytes", w[0].2, w[1].2)));
            }
        }
        let mut w = Self::with(path.to_path_buf(), Some(file), tensors, None, None);
        w.skipped = skipped;
        Ok(w)
    }

    /// A store over `tensors` of `file` (none when synthetic), nothing used yet.
    fn with(
        path: PathBuf,
        file: Option<std::fs::File>,
        tensors: BTreeMap<String, (Vec<usize>, Extent)>,
        synthetic: Option<(u64, f32)>,
        args_model: Option<String>,
    ) -> Self {
        Self {
            path,
            file: file.map(RefCell::new),
            tensors,
            unreadable: Default::default(),
            used: Default::default(),
            missing: Default::default(),
            misshaped: Default::default(),
            nonfinite: Default::default(),
            synthetic: synthetic.map(RefCell::new),
            generated: Default::default(),
            args_model,
            skipped: Default::default(),
            unusable: Default::default(),
        }
    }

    /// Opens a PyTorch `.pth` (zip format) through [`crate::pth`]: the state dict under
    /// `model` (or `state_dict`, or the top level), its tensors read lazily from their
    /// storages; nothing in the file is executed.
    pub fn from_pth(path: &Path) -> Result<Self, WeightsError> {
        let err = |m: String| WeightsError { path: path.to_path_buf(), message: m };
        let index = crate::pth::read_index(path)?;
        let file = std::fs::File::open(path).map_err(|e| err(format!("cannot read the checkpoint: {e}")))?;
        let tensors = index
            .tensors
            .into_iter()
            .map(|(n, t)| (n, (t.shape, Extent { dtype: t.dtype, start: t.start, end: t.end })))
            .collect();
        // Integer tensors and views are left out, as integer safetensors entries are: a model
        // that needs one names why.
        let mut w = Self::with(path.to_path_buf(), Some(file), tensors, None, index.args_model);
        w.skipped = index.skipped.into_iter().collect();
        Ok(w)
    }

    /// The constructor call an official `.pth` records under `args.model` (e.g.
    /// `AsymmetricCroCo3DStereo(..., enc_num_heads=16, ...)`), if any.
    pub fn args_model(&self) -> Option<&str> {
        self.args_model.as_deref()
    }

    /// Reads and converts one stored tensor to f32.
    fn read(&self, e: &Extent) -> std::io::Result<Vec<f32>> {
        use std::io::{Read, Seek, SeekFrom};
        let file = self.file.as_ref().ok_or_else(|| std::io::Error::other("no checkpoint file"))?;
        let mut f = file.borrow_mut();
        f.seek(SeekFrom::Start(e.start))?;
        let mut data = vec![0u8; (e.end - e.start) as usize];
        f.read_exact(&mut data)?;
        Ok(match e.dtype {
            safetensors::Dtype::F16 => {
                data.chunks_exact(2).map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32()).collect()
            }
            safetensors::Dtype::BF16 => {
                data.chunks_exact(2).map(|c| half::bf16::from_le_bytes([c[0], c[1]]).to_f32()).collect()
            }
            _ => data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
        })
    }

    /// A store that invents every tensor it is asked for: LayerNorm weights 1 and biases 0,
    /// everything else seeded N(0, std^2). Generated tensors are kept, so
    /// [`Weights::save_safetensors`] exports exactly the model that was built (benchmarks,
    /// tests of other implementations).
    pub fn synthetic(seed: u64, std: f32) -> Self {
        let state = (seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1, std);
        Self::with(PathBuf::from("<synthetic>"), None, BTreeMap::new(), Some(state), None)
    }

    /// Writes every tensor (f32) to a safetensors file, atomically.
    pub fn save_safetensors(&self, path: &Path) -> Result<(), WeightsError> {
        let err = |m: String| WeightsError { path: path.to_path_buf(), message: m };
        let generated = self.generated.borrow();
        let mut all: Vec<(String, Stored)> = Vec::new();
        for (k, (shape, e)) in &self.tensors {
            all.push((k.clone(), (shape.clone(), self.read(e).map_err(|e| err(format!("reading '{k}': {e}")))?)));
        }
        all.extend(generated.iter().cloned());
        let named: Vec<(String, Vec<usize>, &[f32])> =
            all.iter().map(|(k, (s, v))| (k.clone(), s.clone(), v.as_slice())).collect();
        dens3r_io::tensors::save(path, &named).map_err(|e| err(e.message))?;
        Ok(())
    }

    fn generate(&self, name: &str, shape: &[usize]) -> Option<Vec<f32>> {
        let cell = self.synthetic.as_ref()?;
        let mut st = cell.borrow_mut();
        let n: usize = shape.iter().product();
        if is_layer_norm(name) {
            return Some(vec![if name.ends_with(".weight") { 1.0 } else { 0.0 }; n]);
        }
        let std = st.1 as f64;
        let mut v = Vec::with_capacity(n + 1);
        while v.len() < n {
            // xorshift64* -> two uniforms -> Box-Muller
            let mut next = || {
                st.0 ^= st.0 >> 12;
                st.0 ^= st.0 << 25;
                st.0 ^= st.0 >> 27;
                ((st.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (u1, u2) = (next(), next());
            let r = (-2.0 * u1.ln()).sqrt() * std;
            v.push((r * (std::f64::consts::TAU * u2).cos()) as f32);
            v.push((r * (std::f64::consts::TAU * u2).sin()) as f32);
        }
        v.truncate(n);
        Some(v)
    }

    /// The checkpoint path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// True when a tensor (or its alias) exists.
    pub fn contains(&self, name: &str) -> bool {
        self.resolve(name).is_some()
    }

    /// Shape of a tensor (or its alias), if present.
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.resolve(name).map(|k| self.tensors[k].0.as_slice())
    }

    /// All key names.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.tensors.keys().map(String::as_str)
    }

    /// Loads `name` as a rank-`D` tensor of shape `expect`; a missing or mis-shaped key is
    /// recorded (see [`Weights::finish`]) and a zero tensor of the expected shape returned, so
    /// every problem is reported at once.
    pub fn get<const D: usize>(&self, name: &str, expect: [usize; D], device: &Device) -> Tensor<D> {
        match self.values(name, &expect) {
            Some(values) => Tensor::from_data(TensorData::new(values, expect), device),
            None => Tensor::zeros(expect, device),
        }
    }

    /// The values of `name` (f32, row-major) when it has shape `expect`; a missing, mis-shaped
    /// or unreadable key is recorded as by [`Weights::get`] and gives `None`.
    pub fn values(&self, name: &str, expect: &[usize]) -> Option<Vec<f32>> {
        if self.resolve(name).is_none() {
            if let Some(values) = self.generate(name, expect) {
                self.generated.borrow_mut().push((name.to_string(), (expect.to_vec(), values.clone())));
                self.used.borrow_mut().insert(name.to_string());
                return Some(values);
            }
        }
        match self.resolve(name) {
            None => match self.skipped.get(name) {
                Some(why) => self.unusable.borrow_mut().push(format!("{name} ({why})")),
                None => self.missing.borrow_mut().push(format!("{name} {expect:?}")),
            },
            Some(key) => {
                let (shape, extent) = &self.tensors[key];
                self.mark_used(name, key);
                if shape.as_slice() == expect {
                    match self.read(extent) {
                        Ok(values) if values.iter().all(|v| v.is_finite()) => return Some(values),
                        Ok(values) => {
                            let bad = values.iter().filter(|v| !v.is_finite()).count();
                            self.nonfinite.borrow_mut().push(format!("{name} ({bad} of {})", values.len()));
                        }
                        Err(e) => self.unreadable.borrow_mut().push(format!("{name}: {e}")),
                    }
                } else {
                    self.misshaped.borrow_mut().push(format!("{name}: {shape:?}, expected {expect:?}"));
                }
            }
        }
        None
    }

    /// Errors out listing missing and mis-shaped keys; returns the unexpected (unused) keys,
    /// ignoring the ones known to be unused at inference (`mask_token`, `atm_block.*`,
    /// `enc_pos_embed`, `dec_pos_embed`, and each DPT's `refinenet4.resConfUnit1`, which the
    /// official forward never applies: refinenet4 has no skip input).
    pub fn finish(&self) -> Result<Vec<String>, WeightsError> {
        let (missing, misshaped) = (self.missing.borrow(), self.misshaped.borrow());
        let unreadable = self.unreadable.borrow();
        if !unreadable.is_empty() {
            let m = format!(
                "cannot read {} tensors ({}); check the file and re-copy it",
                unreadable.len(),
                preview(&unreadable)
            );
            return Err(WeightsError { path: self.path.clone(), message: m });
        }
        let nonfinite = self.nonfinite.borrow();
        if !nonfinite.is_empty() {
            let m = format!(
                "{} tensors hold NaN or Inf values ({}): a damaged or diverged checkpoint; re-download or re-export it (a training run: resume from an earlier checkpoint with a lower --lr)",
                nonfinite.len(),
                preview(&nonfinite)
            );
            return Err(WeightsError { path: self.path.clone(), message: m });
        }
        let unusable = self.unusable.borrow();
        if !unusable.is_empty() {
            let m = format!(
                "{} tensors the network needs are not stored as floating point ({}); store them as f32, f16 or bf16",
                unusable.len(),
                preview(&unusable)
            );
            return Err(WeightsError { path: self.path.clone(), message: m });
        }
        if !missing.is_empty() || !misshaped.is_empty() {
            let mut m = String::from("checkpoint does not fit the model");
            if !missing.is_empty() {
                m += &format!("; missing {} keys: {}", missing.len(), preview(&missing));
            }
            if !misshaped.is_empty() {
                m += &format!("; mis-shaped {} keys: {}", misshaped.len(), preview(&misshaped));
            }
            return Err(WeightsError { path: self.path.clone(), message: m });
        }
        let used = self.used.borrow();
        Ok(self
            .tensors
            .keys()
            .filter(|k| !used.contains(*k))
            .filter(|k| {
                !(k.as_str() == "mask_token"
                    || k.starts_with("atm_block.")
                    || k.ends_with("pos_embed")
                    || k.contains(".scratch.refinenet4.resConfUnit1."))
            })
            .cloned()
            .collect())
    }

    /// The stored key for `name`, trying the DPT alias `scratch.layer_rn.{i}` <->
    /// `scratch.layer{i+1}_rn`.
    fn resolve(&self, name: &str) -> Option<&str> {
        if let Some((k, _)) = self.tensors.get_key_value(name) {
            return Some(k);
        }
        let alias = alias_of(name)?;
        self.tensors.get_key_value(&alias).map(|(k, _)| k.as_str())
    }

    fn mark_used(&self, name: &str, key: &str) {
        let mut used = self.used.borrow_mut();
        used.insert(key.to_string());
        used.insert(name.to_string());
        if let Some(a) = alias_of(name) {
            used.insert(a);
        }
    }
}

/// Whether `name` is a LayerNorm's tensor (`enc_norm`, `dec_norm`, a block's `norm1`..`norm3`
/// or `norm_y`): not a DPT or normal-head convolution, whose names also start with "norm".
pub fn is_layer_norm(name: &str) -> bool {
    name.split('.').any(|p| matches!(p, "enc_norm" | "dec_norm" | "norm1" | "norm2" | "norm3" | "norm_y"))
}

fn alias_of(name: &str) -> Option<String> {
    for i in 0..4 {
        let (a, b) = (format!("scratch.layer{}_rn.", i + 1), format!("scratch.layer_rn.{i}."));
        if name.contains(&a) {
            return Some(name.replace(&a, &b));
        }
        if name.contains(&b) {
            return Some(name.replace(&b, &a));
        }
    }
    None
}

fn preview(v: &[String]) -> String {
    let mut s = v.iter().take(8).cloned().collect::<Vec<_>>().join(", ");
    if v.len() > 8 {
        s += &format!(", ... ({} more)", v.len() - 8);
    }
    s
}
