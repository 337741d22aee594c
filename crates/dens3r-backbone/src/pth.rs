//! PyTorch `.pth` checkpoints (both formats of `torch.save`: the zip archive of torch >= 1.6
//! and the legacy pickle stream) read natively and safely: `data.pkl` is interpreted by a small pickle machine that builds plain data only
//! (dicts, lists, tuples, strings, numbers and tensor references) and accepts only the globals
//! a checkpoint legitimately names (tensor and parameter rebuilders, typed storages,
//! `OrderedDict`, `argparse.Namespace` as a dict, `torch.device`); any other global
//! (`os.system`, `builtins.eval`, `subprocess.Popen`, ...) is refused by name. Nothing in the
//! file is executed. Tensor bytes are not read here: each tensor becomes a byte range of its
//! storage (zip entries are stored uncompressed; legacy storages follow the pickles), read
//! lazily like safetensors.

use crate::WeightsError;
use safetensors::Dtype;
use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

/// One tensor of a checkpoint: shape, dtype and absolute byte range in the `.pth` file.
#[derive(Debug, Clone, PartialEq)]
pub struct PthTensor {
    /// Shape.
    pub shape: Vec<usize>,
    /// Stored dtype (F32, F16, BF16; other dtypes are listed in [`PthIndex::skipped`]).
    pub dtype: Dtype,
    /// Byte range in the file.
    pub start: u64,
    /// See `start`.
    pub end: u64,
}

/// What a `.pth` holds: its floating-point tensors by name (from `model`, `state_dict` or the
/// top level), the names of tensors that cannot be used (integer dtypes, non-contiguous
/// views), and `args.model` (the official constructor string) when present.
#[derive(Debug, Clone, Default)]
pub struct PthIndex {
    /// Float tensors by state-dict key.
    pub tensors: BTreeMap<String, PthTensor>,
    /// Keys not readable as float tensors, with why.
    pub skipped: Vec<(String, String)>,
    /// `args.model` of the official training scripts.
    pub args_model: Option<String>,
}

/// A pickled value, as plain data (floats and bytes are kept though no checkpoint field read
/// here needs them).
#[derive(Debug, Clone)]
#[allow(dead_code)]
enum V {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<V>),
    List(Vec<V>),
    Dict(Vec<(V, V)>),
    /// An allowed global, `module.name`.
    Global(String),
    /// A typed storage: dtype name (e.g. `FloatStorage`) and its key under `data/`.
    Storage(String, String),
    /// `_rebuild_tensor_v2(storage, offset, size, stride, ...)`.
    Tensor {
        storage: (String, String),
        offset: usize,
        size: Vec<usize>,
        stride: Vec<usize>,
    },
    /// An object of an allowed class (`argparse.Namespace`): its state dict.
    Object(String, Box<V>),
    Mark,
}

const ALLOWED: &[&str] = &[
    "collections.OrderedDict",
    "torch._utils._rebuild_tensor_v2",
    "torch._utils._rebuild_parameter",
    "torch._utils._rebuild_parameter_with_state",
    "torch.FloatStorage",
    "torch.HalfStorage",
    "torch.BFloat16Storage",
    "torch.DoubleStorage",
    "torch.LongStorage",
    "torch.IntStorage",
    "torch.ShortStorage",
    "torch.CharStorage",
    "torch.ByteStorage",
    "torch.BoolStorage",
    "argparse.Namespace",
    "torch.device",
    "builtins.set",
    // numpy scalars in training metadata (e.g. a best score): read as opaque data.
    "numpy.core.multiarray.scalar",
    "numpy._core.multiarray.scalar",
    "numpy.dtype",
    "_codecs.encode",
];

fn int(v: &V) -> Option<i64> {
    match v {
        V::Int(i) => Some(*i),
        V::Bool(b) => Some(*b as i64),
        _ => None,
    }
}

fn usizes(v: &V) -> Option<Vec<usize>> {
    match v {
        V::Tuple(t) | V::List(t) => t.iter().map(|x| int(x).and_then(|i| usize::try_from(i).ok())).collect(),
        _ => None,
    }
}

/// The deepest nesting of containers a checkpoint's pickle may build; deeper data is refused
/// (it would overflow the stack when walked or dropped: a hostile file, not a checkpoint).
pub const MAX_PICKLE_DEPTH: u32 = 1000;
/// The most values a checkpoint's pickle may build, counting every copy a memo reference
/// makes (a few per tensor in real checkpoints; shared references nested inside each other
/// double at every level).
pub const MAX_PICKLE_VALUES: u64 = 10_000_000;

/// The unpickler's stack: each value with its nesting depth and how many values it holds.
struct Stack {
    v: Vec<V>,
    meta: Vec<(u32, u64)>,
}

impl Stack {
    fn push(&mut self, v: V) {
        self.push_with(v, (0, 1));
    }

    fn push_with(&mut self, v: V, meta: (u32, u64)) {
        self.v.push(v);
        self.meta.push(meta);
    }

    fn pop(&mut self) -> Result<(V, (u32, u64)), String> {
        let v = self.v.pop().ok_or_else(|| "the pickle pops an empty stack".to_string())?;
        Ok((v, self.meta.pop().expect("meta follows the stack")))
    }

    fn pop_mark(&mut self) -> Result<(Vec<V>, (u32, u64)), String> {
        let k = self.v.iter().rposition(|v| matches!(v, V::Mark)).ok_or("the pickle has no MARK")?;
        let items = self.v.split_off(k + 1);
        let meta = self.meta.split_off(k + 1);
        self.v.pop();
        self.meta.pop();
        Ok((items, combined(&meta)?))
    }

    fn pop_n(&mut self, n: usize) -> Result<(Vec<V>, (u32, u64)), String> {
        if self.v.len() < n {
            return Err("the pickle pops an empty stack".into());
        }
        let items = self.v.split_off(self.v.len() - n);
        let meta = self.meta.split_off(self.meta.len() - n);
        Ok((items, combined(&meta)?))
    }

    fn last(&self) -> Option<(V, (u32, u64))> {
        Some((self.v.last()?.clone(), *self.meta.last()?))
    }

    /// The top value to add items into (of these greatest depth and total size), its depth
    /// and size updated.
    fn last_mut_adding(&mut self, items: (u32, u64)) -> Result<Option<&mut V>, String> {
        let Some(m) = self.meta.last_mut() else { return Ok(None) };
        *m = bounded(m.0.max(items.0 + 1), m.1.saturating_add(items.1))?;
        Ok(self.v.last_mut())
    }
}

/// The depth and size of a container holding values of these depths and sizes; an error
/// past [`MAX_PICKLE_DEPTH`] or [`MAX_PICKLE_VALUES`].
fn combined(items: &[(u32, u64)]) -> Result<(u32, u64), String> {
    let depth = items.iter().map(|m| m.0).max().unwrap_or(0) + 1;
    let size = items.iter().fold(1u64, |a, m| a.saturating_add(m.1));
    bounded(depth, size)
}

/// `(depth, size)`, or the refusal past [`MAX_PICKLE_DEPTH`] or [`MAX_PICKLE_VALUES`].
fn bounded(depth: u32, size: u64) -> Result<(u32, u64), String> {
    if depth > MAX_PICKLE_DEPTH {
        return Err(format!("the pickle nests its data over {MAX_PICKLE_DEPTH} levels deep: not a checkpoint"));
    }
    if size > MAX_PICKLE_VALUES {
        return Err(format!("the pickle builds over {MAX_PICKLE_VALUES} values: not a checkpoint"));
    }
    Ok((depth, size))
}

/// Runs the pickle program at the start of `data` into plain data; returns it and the bytes
/// it took. Data nested deeper than [`MAX_PICKLE_DEPTH`] or larger than
/// [`MAX_PICKLE_VALUES`] is refused.
fn unpickle(data: &[u8]) -> Result<(V, usize), String> {
    let mut stack = Stack { v: Vec::new(), meta: Vec::new() };
    let mut memo: BTreeMap<u64, (V, (u32, u64))> = BTreeMap::new();
    let mut pos = 0usize;
    let take = |pos: &mut usize, n: usize| -> Result<&[u8], String> {
        let end = pos.checked_add(n).filter(|&e| e <= data.len()).ok_or("the pickle is truncated")?;
        let s = &data[*pos..end];
        *pos = end;
        Ok(s)
    };
    let u32le = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize;
    let text = |b: &[u8]| String::from_utf8(b.to_vec()).map_err(|_| "the pickle holds invalid UTF-8".to_string());
    loop {
        let op = *take(&mut pos, 1)?.first().ok_or("the pickle is truncated")?;
        match op {
            0x80 => {
                take(&mut pos, 1)?;
            }
            0x95 => {
                take(&mut pos, 8)?;
            }
            b'.' => return Ok((stack.pop()?.0, pos)),
            b'}' => stack.push_with(V::Dict(Vec::new()), (1, 1)),
            b']' => stack.push_with(V::List(Vec::new()), (1, 1)),
            b')' => stack.push_with(V::Tuple(Vec::new()), (1, 1)),
            b'(' => stack.push(V::Mark),
            b'N' => stack.push(V::None),
            0x88 => stack.push(V::Bool(true)),
            0x89 => stack.push(V::Bool(false)),
            b'K' => stack.push(V::Int(take(&mut pos, 1)?[0] as i64)),
            b'M' => {
                let b = take(&mut pos, 2)?;
                stack.push(V::Int(u16::from_le_bytes([b[0], b[1]]) as i64));
            }
            b'J' => {
                let b = take(&mut pos, 4)?;
                stack.push(V::Int(i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as i64));
            }
            0x8a => {
                let n = take(&mut pos, 1)?[0] as usize;
                let b = take(&mut pos, n)?;
                if n > 8 {
                    // Wider than 64 bits (the legacy format's magic number): kept as bytes.
                    stack.push(V::Bytes(b.to_vec()));
                    continue;
                }
                let mut v: i64 = 0;
                for (i, byte) in b.iter().enumerate() {
                    v |= (*byte as i64) << (8 * i);
                }
                if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                    v -= 1i64 << (8 * n);
                }
                stack.push(V::Int(v));
            }
            b'G' => {
                let b = take(&mut pos, 8)?;
                stack.push(V::Float(f64::from_be_bytes(b.try_into().map_err(|_| "float")?)));
            }
            b'X' => {
                let n = u32le(take(&mut pos, 4)?);
                stack.push(V::Str(text(take(&mut pos, n)?)?));
            }
            0x8c => {
                let n = take(&mut pos, 1)?[0] as usize;
                stack.push(V::Str(text(take(&mut pos, n)?)?));
            }
            b'B' => {
                let n = u32le(take(&mut pos, 4)?);
                stack.push(V::Bytes(take(&mut pos, n)?.to_vec()));
            }
            b'C' => {
                let n = take(&mut pos, 1)?[0] as usize;
                stack.push(V::Bytes(take(&mut pos, n)?.to_vec()));
            }
            b'q' => {
                let k = take(&mut pos, 1)?[0] as u64;
                memo.insert(k, stack.last().ok_or("BINPUT on an empty stack")?);
            }
            b'r' => {
                let k = u32le(take(&mut pos, 4)?) as u64;
                memo.insert(k, stack.last().ok_or("LONG_BINPUT on an empty stack")?);
            }
            0x94 => {
                let k = memo.len() as u64;
                memo.insert(k, stack.last().ok_or("MEMOIZE on an empty stack")?);
            }
            b'h' => {
                let k = take(&mut pos, 1)?[0] as u64;
                let (v, m) = memo.get(&k).cloned().ok_or("BINGET of an unknown memo entry")?;
                stack.push_with(v, m);
            }
            b'j' => {
                let k = u32le(take(&mut pos, 4)?) as u64;
                let (v, m) = memo.get(&k).cloned().ok_or("LONG_BINGET of an unknown memo entry")?;
                stack.push_with(v, m);
            }
            b'c' => {
                let line = |pos: &mut usize| -> Result<String, String> {
                    let rest = &data[*pos..];
                    let n = rest.iter().position(|&c| c == b'\n').ok_or("the pickle is truncated")?;
                    let s = text(&rest[..n])?;
                    *pos += n + 1;
                    Ok(s)
                };
                let (module, name) = (line(&mut pos)?, line(&mut pos)?);
                stack.push(global(&module, &name)?);
            }
            0x93 => {
                let (name, _) = stack.pop()?;
                let (module, _) = stack.pop()?;
                let (V::Str(m), V::Str(n)) = (module, name) else { return Err("STACK_GLOBAL without names".into()) };
                stack.push(global(&m, &n)?);
            }
            b't' => {
                let (items, m) = stack.pop_mark()?;
                stack.push_with(V::Tuple(items), m);
            }
            0x85..=0x87 => {
                let (items, m) = stack.pop_n((op - 0x84) as usize)?;
                stack.push_with(V::Tuple(items), m);
            }
            b'l' => {
                let (items, m) = stack.pop_mark()?;
                stack.push_with(V::List(items), m);
            }
            b'd' => {
                let (items, m) = stack.pop_mark()?;
                stack.push_with(V::Dict(pairs(items)?), m);
            }
            b'a' => {
                let (x, m) = stack.pop()?;
                match stack.last_mut_adding(m)? {
                    Some(V::List(l)) => l.push(x),
                    _ => return Err("APPEND to a non-list".into()),
                }
            }
            b'e' => {
                let (items, m) = stack.pop_mark()?;
                match stack.last_mut_adding(m)? {
                    Some(V::List(l)) => l.extend(items),
                    _ => return Err("APPENDS to a non-list".into()),
                }
            }
            b's' => {
                let (v, mv) = stack.pop()?;
                let (k, mk) = stack.pop()?;
                match stack.last_mut_adding((mv.0.max(mk.0), mv.1.saturating_add(mk.1)))? {
                    Some(V::Dict(d)) => d.push((k, v)),
                    _ => return Err("SETITEM on a non-dict".into()),
                }
            }
            b'u' => {
                let (items, m) = stack.pop_mark()?;
                let items = pairs(items)?;
                match stack.last_mut_adding(m)? {
                    Some(V::Dict(d)) => d.extend(items),
                    _ => return Err("SETITEMS on a non-dict".into()),
                }
            }
            b'Q' => {
                let (pid, m) = stack.pop()?;
                stack.push_with(persistent(pid)?, m);
            }
            b'R' | 0x81 => {
                let (args, ma) = stack.pop()?;
                let (f, mf) = stack.pop()?;
                stack.push_with(call(f, args)?, combined(&[ma, mf])?);
            }
            b'b' => {
                let (state, ms) = stack.pop()?;
                let (obj, mo) = stack.pop()?;
                stack.push_with(
                    match obj {
                        V::Object(c, _) => V::Object(c, Box::new(state)),
                        // Parameters and tensors may carry (empty) state: the data is what counts.
                        other => other,
                    },
                    combined(&[ms, mo])?,
                );
            }
            other => return Err(format!("the pickle uses opcode 0x{other:02x}, which checkpoints do not need")),
        }
    }
}

fn pairs(items: Vec<V>) -> Result<Vec<(V, V)>, String> {
    if !items.len().is_multiple_of(2) {
        return Err("a dict with an odd number of items".into());
    }
    let mut it = items.into_iter();
    let mut out = Vec::new();
    while let (Some(k), Some(v)) = (it.next(), it.next()) {
        out.push((k, v));
    }
    Ok(out)
}

fn global(module: &str, name: &str) -> Result<V, String> {
    let full = format!("{module}.{name}");
    if ALLOWED.contains(&full.as_str()) {
        Ok(V::Global(full))
    } else {
        Err(format!(
            "refuses the global {full}: a checkpoint holds data, and this one asks to run code (nothing was executed)"
        ))
    }
}

fn persistent(pid: V) -> Result<V, String> {
    let V::Tuple(t) = pid else { return Err("a persistent id that is not a tuple".into()) };
    match t.as_slice() {
        [V::Str(kind), V::Global(ty), V::Str(key), ..] if kind == "storage" => {
            Ok(V::Storage(ty.trim_start_matches("torch.").to_string(), key.clone()))
        }
        _ => Err("a persistent id that is not a torch storage".into()),
    }
}

fn call(f: V, args: V) -> Result<V, String> {
    let V::Global(name) = f else { return Err("the pickle calls something that is not an allowed global".into()) };
    let args = match args {
        V::Tuple(a) => a,
        _ => return Err(format!("{name} called without an argument tuple")),
    };
    match name.as_str() {
        "collections.OrderedDict" => Ok(V::Dict(Vec::new())),
        "argparse.Namespace" => Ok(V::Object(name, Box::new(V::Dict(Vec::new())))),
        "torch.device" => Ok(args.into_iter().next().unwrap_or(V::None)),
        // Opaque: the values of numpy scalars are not needed to load weights.
        "numpy.core.multiarray.scalar" | "numpy._core.multiarray.scalar" => Ok(V::None),
        "numpy.dtype" => Ok(V::Object(name, Box::new(V::None))),
        "_codecs.encode" => Ok(V::Bytes(match args.into_iter().next() {
            Some(V::Str(s)) => s.into_bytes(),
            _ => Vec::new(),
        })),
        "builtins.set" => Ok(V::List(match args.into_iter().next() {
            Some(V::List(l)) | Some(V::Tuple(l)) => l,
            _ => Vec::new(),
        })),
        "torch._utils._rebuild_tensor_v2" => {
            let bad = || "a tensor rebuilt from malformed arguments".to_string();
            let storage = match args.first() {
                Some(V::Storage(t, k)) => (t.clone(), k.clone()),
                _ => return Err(bad()),
            };
            let offset = args.get(1).and_then(int).and_then(|i| usize::try_from(i).ok()).ok_or_else(bad)?;
            let size = args.get(2).and_then(usizes).ok_or_else(bad)?;
            let stride = args.get(3).and_then(usizes).ok_or_else(bad)?;
            Ok(V::Tensor { storage, offset, size, stride })
        }
        "torch._utils._rebuild_parameter" | "torch._utils._rebuild_parameter_with_state" => {
            args.into_iter().next().ok_or_else(|| "a parameter without data".to_string())
        }
        other => Err(format!("{other} cannot be called")),
    }
}

fn dtype_of(storage: &str) -> Option<(Dtype, u64)> {
    match storage {
        "FloatStorage" => Some((Dtype::F32, 4)),
        "HalfStorage" => Some((Dtype::F16, 2)),
        "BFloat16Storage" => Some((Dtype::BF16, 2)),
        _ => None,
    }
}

/// Where a storage's bytes are: absolute file offset and length.
type StorageAt = (u64, u64);

/// Reads the index of a `.pth`: its float tensors as byte ranges of the file. Both formats of
/// `torch.save`: the zip archive (torch >= 1.6) and the legacy stream of pickles followed by
/// the raw storages.
pub fn read_index(path: &Path) -> Result<PthIndex, WeightsError> {
    read_index_at(path).map_err(|m| WeightsError::new(path, m))
}

fn read_index_at(path: &Path) -> Result<PthIndex, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("cannot read the checkpoint: {e}"))?;
    let mut magic = [0u8; 2];
    (&file).read_exact(&mut magic).map_err(|_| "the file is empty".to_string())?;
    if magic == *b"PK" {
        read_zip(file)
    } else if magic == [0x80, 0x02] {
        read_legacy(file)
    } else {
        Err("neither a zip-format nor a legacy torch checkpoint".into())
    }
}

fn read_legacy(mut file: std::fs::File) -> Result<PthIndex, String> {
    use std::io::{Seek, SeekFrom};
    let len = file.metadata().map_err(|e| e.to_string())?.len();
    // The pickles come first and are small; read up to 256 MB of them.
    let head_len = len.min(256 << 20) as usize;
    let mut head = vec![0u8; head_len];
    file.seek(SeekFrom::Start(0)).map_err(|e| e.to_string())?;
    file.read_exact(&mut head).map_err(|e| format!("cannot read ({e})"))?;
    let mut pos = 0usize;
    let next = |pos: &mut usize| -> Result<V, String> {
        let (v, n) = unpickle(&head[*pos..]).map_err(|e| format!("legacy checkpoint: {e}"))?;
        *pos += n;
        Ok(v)
    };
    let _magic = next(&mut pos)?;
    let protocol = next(&mut pos)?;
    if int(&protocol) != Some(1001) {
        return Err("a legacy torch checkpoint of an unknown protocol (not 1001)".into());
    }
    let _sys_info = next(&mut pos)?;
    let root = next(&mut pos)?;
    let V::List(keys) = next(&mut pos)? else { return Err("legacy checkpoint: no storage key list".into()) };
    // Each storage: its element count (little-endian u64), then its bytes; their order is
    // the key list's. Element sizes come from the tensors' storage types.
    let mut elsize: BTreeMap<String, u64> = BTreeMap::new();
    collect_storages(&root, &mut elsize);
    let mut at: BTreeMap<String, StorageAt> = BTreeMap::new();
    let mut off = pos as u64;
    for k in keys {
        let V::Str(k) = k else { return Err("legacy checkpoint: a storage key is not a string".into()) };
        let mut n = [0u8; 8];
        file.seek(SeekFrom::Start(off)).map_err(|e| e.to_string())?;
        file.read_exact(&mut n).map_err(|_| format!("legacy checkpoint: storage {k} is cut short"))?;
        let bytes = u64::from_le_bytes(n).checked_mul(*elsize.get(&k).unwrap_or(&1)).ok_or("a huge storage")?;
        if (off + 8).checked_add(bytes).is_none_or(|end| end > len) {
            return Err(format!("legacy checkpoint: storage {k} runs past the end of the file"));
        }
        at.insert(k, (off + 8, bytes));
        off += 8 + bytes;
    }
    index_of(root, |key| at.get(key).copied().ok_or_else(|| format!("storage {key} is missing")))
}

/// Element sizes of every storage the tensors under `v` name.
fn collect_storages(v: &V, out: &mut BTreeMap<String, u64>) {
    match v {
        V::Tensor { storage: (ty, key), .. } => {
            out.insert(key.clone(), storage_elsize(ty));
        }
        V::Dict(d) => d.iter().for_each(|(_, x)| collect_storages(x, out)),
        V::List(l) | V::Tuple(l) => l.iter().for_each(|x| collect_storages(x, out)),
        V::Object(_, s) => collect_storages(s, out),
        _ => {}
    }
}

fn storage_elsize(ty: &str) -> u64 {
    match ty {
        "DoubleStorage" | "LongStorage" => 8,
        "FloatStorage" | "IntStorage" => 4,
        "HalfStorage" | "BFloat16Storage" | "ShortStorage" => 2,
        _ => 1,
    }
}

fn read_zip(file: std::fs::File) -> Result<PthIndex, String> {
    let mut zip = zip::ZipArchive::new(file).map_err(|e| format!("not a valid torch zip checkpoint ({e})"))?;
    let pkl = (0..zip.len())
        .filter_map(|i| zip.by_index(i).ok().map(|f| f.name().to_string()))
        .find(|n| n.ends_with("/data.pkl") && n.matches('/').count() == 1)
        .ok_or("no data.pkl in the archive: not a torch checkpoint")?;
    let prefix = pkl.trim_end_matches("data.pkl").to_string();
    let mut data = Vec::new();
    {
        let mut f = zip.by_name(&pkl).map_err(|e| e.to_string())?;
        if f.size() > 1 << 30 {
            return Err("data.pkl is over 1 GB: not a checkpoint".into());
        }
        f.read_to_end(&mut data).map_err(|e| format!("cannot read data.pkl ({e})"))?;
    }
    let (root, _) = unpickle(&data)?;
    index_of(root, |key| {
        let entry = format!("{prefix}data/{key}");
        let f = zip.by_name(&entry).map_err(|_| format!("its storage {entry} is missing"))?;
        if f.compression() != zip::CompressionMethod::Stored {
            return Err(format!("storage {entry} is compressed; torch stores them plain"));
        }
        Ok((f.data_start(), f.size()))
    })
}

/// The index of an unpickled checkpoint whose storages are located by `storage(key)`.
fn index_of(root: V, mut storage: impl FnMut(&str) -> Result<StorageAt, String>) -> Result<PthIndex, String> {
    let mut index = PthIndex::default();
    let entries = match &root {
        V::Dict(d) => d.clone(),
        _ => return Err("the checkpoint is not a dict".into()),
    };
    let get = |k: &str| entries.iter().find(|(key, _)| matches!(key, V::Str(s) if s == k)).map(|(_, v)| v.clone());
    if let Some(V::Object(_, state)) = get("args") {
        if let V::Dict(d) = *state {
            index.args_model =
                d.iter().find(|(k, _)| matches!(k, V::Str(s) if s == "model")).and_then(|(_, v)| match v {
                    V::Str(s) => Some(s.clone()),
                    _ => None,
                });
        }
    }
    let state = match (get("model"), get("state_dict")) {
        (Some(V::Dict(d)), _) | (None, Some(V::Dict(d))) => d,
        _ => entries,
    };
    for (k, v) in state {
        let V::Str(name) = k else { continue };
        let V::Tensor { storage: (ty, key), offset, size, stride } = v else { continue };
        let Some((dtype, elsize)) = dtype_of(&ty) else {
            index.skipped.push((name, format!("{ty} is not a float storage")));
            continue;
        };
        // Row-major strides of `size` (dims of size 1 may have any stride).
        let mut want = 1usize;
        let contiguous = size.iter().zip(&stride).rev().all(|(&n, &s)| {
            let ok = n == 1 || s == want;
            want = want.saturating_mul(n);
            ok
        });
        if !contiguous || stride.len() != size.len() {
            index.skipped.push((name, "a non-contiguous view".into()));
            continue;
        }
        let (data_start, data_len) = storage(&key).map_err(|e| format!("tensor '{name}': {e}"))?;
        let numel = size.iter().try_fold(1u64, |a, &d| a.checked_mul(d as u64)).ok_or("a huge shape")?;
        let span = (offset as u64)
            .checked_mul(elsize)
            .and_then(|o| data_start.checked_add(o))
            .and_then(|start| Some((start, start.checked_add(numel.checked_mul(elsize)?)?)));
        let storage_end = data_start.checked_add(data_len);
        let Some(((start, end), storage_end)) = span.zip(storage_end) else {
            return Err(format!("tensor '{name}': {size:?} at offset {offset} lies outside any file"));
        };
        if end > storage_end {
            return Err(format!("tensor '{name}': {size:?} at offset {offset} overruns its storage {key}"));
        }
        index.tensors.insert(name, PthTensor { shape: size, dtype, start, end });
    }
    Ok(index)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 66, 4: lists nested 10^6 deep and dicts 10^5 deep (a stack overflow, exit 134,
    /// before) are refused in one line; data just under the bound still reads.
    #[test]
    fn deep_nesting_is_refused_not_a_crash() {
        let lists = |n: usize| {
            let mut p = vec![0x80, 2];
            p.extend(std::iter::repeat_n(b']', n));
            p.extend(std::iter::repeat_n(b'a', n - 1));
            p.push(b'.');
            p
        };
        let e = unpickle(&lists(1_000_000)).unwrap_err();
        assert!(e.contains("levels deep") && !e.contains('\n'), "{e}");
        let mut dicts = vec![0x80, 2, b'}'];
        for _ in 0..100_000 {
            dicts.extend([b'K', 1, b'}']);
        }
        dicts.extend(std::iter::repeat_n(b's', 100_000));
        dicts.push(b'.');
        let e = unpickle(&dicts).unwrap_err();
        assert!(e.contains("levels deep"), "{e}");
        let (v, _) = unpickle(&lists(MAX_PICKLE_DEPTH as usize)).unwrap();
        assert!(matches!(v, V::List(_)));
        // A long flat list appended item by item is shallow, however long.
        let mut flat = vec![0x80, 2, b']'];
        for _ in 0..5000 {
            flat.extend([b'K', 7, b'a']);
        }
        flat.push(b'.');
        let (v, _) = unpickle(&flat).unwrap();
        assert!(matches!(v, V::List(l) if l.len() == 5000));
        // Shared references nested in each other double at every level: refused, not built.
        let mut bomb = vec![0x80, 2, b']', b'q', 0];
        for _ in 0..60 {
            bomb.extend([b'h', 0, b'h', 0, 0x86, b'q', 0]);
        }
        bomb.push(b'.');
        let e = unpickle(&bomb).unwrap_err();
        assert!(e.contains("values"), "{e}");
    }

    /// Issue 66, 6: a storage offset of 2^62 elements of 4 bytes (wrapping to 0 in u64) is
    /// refused, as is one past the storage.
    #[test]
    fn wrapping_storage_offsets_are_refused() {
        let tensor = |offset: usize| V::Tensor {
            storage: ("FloatStorage".into(), "0".into()),
            offset,
            size: vec![4],
            stride: vec![1],
        };
        let root = |offset| V::Dict(vec![(V::Str("w".into()), tensor(offset))]);
        let at = |_: &str| Ok((100u64, 16u64));
        let e = index_of(root(1 << 62), at).unwrap_err();
        assert!(e.contains("'w'"), "{e}");
        assert!(index_of(root(1), at).unwrap_err().contains("overruns"));
        let ok = index_of(root(0), at).unwrap();
        assert_eq!((ok.tensors["w"].start, ok.tensors["w"].end), (100, 116));
    }
}
