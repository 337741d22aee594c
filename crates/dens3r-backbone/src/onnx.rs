//! Reads the initializers (weights) of an ONNX model and the graph nodes that consume them.
//!
//! Only the few protobuf fields needed are declared (prost skips the rest): a model's graph,
//! its nodes (name, op type, inputs) and its initializer tensors (name, dims, type, raw or
//! float data). Exporters name some weights `onnx::MatMul_1966`; [`OnnxWeights::consumers`]
//! maps such a name back to the node that reads it, whose name carries the layer path.

use prost::Message;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

#[derive(Clone, PartialEq, Message)]
struct ModelProto {
    #[prost(message, optional, tag = "7")]
    graph: Option<GraphProto>,
}

#[derive(Clone, PartialEq, Message)]
struct GraphProto {
    #[prost(message, repeated, tag = "1")]
    node: Vec<NodeProto>,
    #[prost(message, repeated, tag = "5")]
    initializer: Vec<TensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct NodeProto {
    #[prost(string, repeated, tag = "1")]
    input: Vec<String>,
    #[prost(string, tag = "3")]
    name: String,
    #[prost(string, tag = "4")]
    op_type: String,
}

#[derive(Clone, PartialEq, Message)]
struct TensorProto {
    #[prost(int64, repeated, tag = "1")]
    dims: Vec<i64>,
    #[prost(int32, tag = "2")]
    data_type: i32,
    #[prost(float, repeated, tag = "4")]
    float_data: Vec<f32>,
    #[prost(string, tag = "8")]
    name: String,
    #[prost(bytes = "vec", tag = "9")]
    raw_data: Vec<u8>,
    #[prost(int32, tag = "14")]
    data_location: i32,
}

/// ONNX `TensorProto.DataType.FLOAT`.
const FLOAT: i32 = 1;

/// A node that reads an initializer.
#[derive(Debug, Clone)]
pub struct Consumer {
    /// Node name, e.g. `/backbone/encoder/layer.0/attention/attention/key/MatMul`.
    pub node: String,
    /// Op type, e.g. `MatMul`.
    pub op: String,
}

/// An ONNX file's f32 initializers by name, with their consumers.
#[derive(Debug)]
pub struct OnnxWeights {
    path: PathBuf,
    tensors: HashMap<String, (Vec<usize>, Vec<f32>)>,
    consumers: HashMap<String, Vec<Consumer>>,
}

dens3r_io::file_error! {
    /// A problem with an ONNX file, naming it.
    OnnxError;
    from: [];
}

impl OnnxWeights {
    /// Reads and decodes `path`. Only float initializers stored inline are accepted.
    pub fn open(path: &Path) -> Result<Self, OnnxError> {
        let err = |m: String| OnnxError { path: path.to_path_buf(), message: m };
        let bytes = std::fs::read(path).map_err(|e| err(format!("cannot read the ONNX model: {e}")))?;
        let model = ModelProto::decode(bytes.as_slice())
            .map_err(|e| err(format!("not a valid ONNX model ({e}); download it again")))?;
        drop(bytes);
        let graph = model.graph.ok_or_else(|| err("the ONNX model has no graph; download it again".into()))?;
        let mut consumers: HashMap<String, Vec<Consumer>> = HashMap::new();
        for n in &graph.node {
            for i in &n.input {
                consumers.entry(i.clone()).or_default().push(Consumer { node: n.name.clone(), op: n.op_type.clone() });
            }
        }
        let mut tensors = HashMap::new();
        for t in graph.initializer {
            if t.data_location == 1 {
                return Err(err(format!("tensor {} is stored in an external file, which is not supported", t.name)));
            }
            if t.data_type != FLOAT {
                continue;
            }
            let shape: Vec<usize> = t.dims.iter().map(|&d| d.max(0) as usize).collect();
            let n: usize = shape.iter().product();
            let data = if !t.raw_data.is_empty() {
                if t.raw_data.len() != 4 * n {
                    return Err(err(format!(
                        "tensor {} holds {} bytes for shape {shape:?}; the file is damaged, download it again",
                        t.name,
                        t.raw_data.len()
                    )));
                }
                t.raw_data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
            } else {
                t.float_data
            };
            if data.len() != n {
                return Err(err(format!("tensor {} has {} values for shape {shape:?}", t.name, data.len())));
            }
            tensors.insert(t.name, (shape, data));
        }
        Ok(Self { path: path.to_path_buf(), tensors, consumers })
    }

    /// The file this came from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Names of all float initializers.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.tensors.keys().map(String::as_str)
    }

    /// Shape and values of an initializer.
    pub fn get(&self, name: &str) -> Option<&(Vec<usize>, Vec<f32>)> {
        self.tensors.get(name)
    }

    /// Removes and returns an initializer.
    pub fn take(&mut self, name: &str) -> Option<(Vec<usize>, Vec<f32>)> {
        self.tensors.remove(name)
    }

    /// The nodes reading a value.
    pub fn consumers(&self, name: &str) -> &[Consumer] {
        self.consumers.get(name).map_or(&[], Vec::as_slice)
    }

    /// Renames the anonymous initializers (`onnx::...`) after the one node reading each:
    /// `/a/b/key/MatMul` becomes `a.b.key.weight`, any other op `a.b.<Op>_<n>` keeps the
    /// node's last path element. Named ones are left as they are.
    pub fn name_anonymous(&mut self) {
        let anon: Vec<String> = self.tensors.keys().filter(|n| n.starts_with("onnx::")).cloned().collect();
        for old in anon {
            let [c] = self.consumers(&old) else { continue };
            let path = c.node.trim_start_matches('/').replace('/', ".");
            let new = match path.strip_suffix(".MatMul") {
                Some(p) if c.op == "MatMul" => format!("{p}.weight"),
                _ => path,
            };
            if let Some(t) = self.tensors.remove(&old) {
                self.tensors.insert(new, t);
            }
        }
    }
}
