//! Every reader of outside data, as a target for mutation: a seed file (written by the
//! project's own writers, or taken from the repository's fixtures) and the call that reads
//! it. Shared by the bounded mutation test (`tests/fuzz_readers.rs`) and the cargo-fuzz
//! targets (`fuzz/`).

#![allow(dead_code)]

use dens3r_backbone::{device, Params};
use dens3r_heads::cache::{FeatureCache, Precision};
use dens3r_heads::{Backbone, FeatureMaps, Head, HeadConfig, Task};
use dens3r_mesh::TriMesh;
use dens3r_recon::{PairCache, ViewOutput};
use dens3r_scene::{npy, Scene};
use glam::Vec3;
use image::RgbImage;
use std::path::{Path, PathBuf};

/// A reader and its seed.
pub struct Target {
    /// Short name (`cargo fuzz run NAME`).
    pub name: &'static str,
    /// The file, inside the case folder, that the mutated bytes replace.
    pub file: &'static str,
    /// Writes the companions the reader needs into the folder; returns the seed's bytes.
    pub seed: fn(&Path) -> Vec<u8>,
    /// Reads the folder (an `Err` is a clean refusal; only a panic or a runaway allocation fails).
    pub read: fn(&Path) -> Result<(), String>,
}

/// The repository root: the first folder above this crate's that holds `data-samples/`.
pub fn repo() -> PathBuf {
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    here.ancestors().find(|d| d.join("data-samples").is_dir()).unwrap_or(here).to_path_buf()
}

fn fixture(rel: &str) -> Vec<u8> {
    std::fs::read(repo().join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

fn ok<T, E: std::fmt::Display>(r: Result<T, E>) -> Result<(), String> {
    r.map(|_| ()).map_err(|e| e.to_string())
}

fn png(img: &image::DynamicImage, format: image::ImageFormat) -> Vec<u8> {
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, format).expect("encode the seed image");
    bytes.into_inner()
}

fn gradient(w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 9) as u8, (y * 11) as u8, ((x + y) * 5) as u8]))
}

fn small_mesh() -> TriMesh {
    let p = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]].map(Vec3::from);
    TriMesh::new(p.to_vec(), vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
}

fn mesh_seed(dir: &Path, name: &str) -> Vec<u8> {
    let path = dir.join(name);
    dens3r_mesh::io::write_mesh(&path, &small_mesh()).expect("write the seed mesh");
    std::fs::read(path).unwrap()
}

/// A tiny network: the safetensors checkpoint and its `model.json`.
fn tiny_network(dir: &Path) -> Vec<u8> {
    let toml = "enc_embed_dim = 32\nenc_depth = 2\nenc_num_heads = 2\ndec_embed_dim = 32\ndec_depth = 4\n\
                dec_num_heads = 2\nlayer_dims = [8, 8, 16, 16]\nfeature_dim = 8\nlast_dim = 8\n\
                desc_mlp_ratio = 1\nsymmetrize_dec = true\n";
    std::fs::write(dir.join("arch.toml"), toml).unwrap();
    let arch = dens3r_train::Arch::read(&dir.join("arch.toml")).expect("the tiny arch");
    let params = Params::init(&arch.config(), 3);
    params.save(&dir.join("model.safetensors")).expect("save the tiny network");
    let json = dens3r_train::arch::config_json(&params.config);
    std::fs::write(dir.join("model.json"), serde_json::to_string_pretty(&json).unwrap()).unwrap();
    std::fs::read(dir.join("model.safetensors")).unwrap()
}

fn read_network(dir: &Path) -> Result<(), String> {
    let cpu = device::cpu();
    ok(dens3r_backbone::verify::load_model(&dir.join("model.safetensors"), Some(&dir.join("model.json")), &cpu))
}

/// An ONNX model with two float initializers (one raw, one as float_data) and a node reading
/// them, encoded by hand (protobuf wire format).
fn onnx_seed() -> Vec<u8> {
    fn varint(mut v: u64, out: &mut Vec<u8>) {
        while v >= 0x80 {
            out.push((v as u8) | 0x80);
            v >>= 7;
        }
        out.push(v as u8);
    }
    fn field(tag: u32, bytes: &[u8], out: &mut Vec<u8>) {
        varint(((tag as u64) << 3) | 2, out);
        varint(bytes.len() as u64, out);
        out.extend_from_slice(bytes);
    }
    fn int(tag: u32, v: u64, out: &mut Vec<u8>) {
        varint((tag as u64) << 3, out);
        varint(v, out);
    }
    let mut t1 = Vec::new();
    int(1, 2, &mut t1);
    int(1, 3, &mut t1);
    int(2, 1, &mut t1);
    field(8, b"blocks.0.attn.qkv.weight", &mut t1);
    let raw: Vec<u8> = (0..6).flat_map(|i| (i as f32 * 0.5).to_le_bytes()).collect();
    field(9, &raw, &mut t1);
    let mut t2 = Vec::new();
    int(1, 2, &mut t2);
    int(2, 1, &mut t2);
    let floats: Vec<u8> = [1.5f32, -2.0].iter().flat_map(|x| x.to_le_bytes()).collect();
    field(4, &floats, &mut t2);
    field(8, b"onnx::MatMul_7", &mut t2);
    let mut node = Vec::new();
    field(1, b"x", &mut node);
    field(1, b"onnx::MatMul_7", &mut node);
    field(3, b"/blocks.0/attn/MatMul", &mut node);
    field(4, b"MatMul", &mut node);
    let mut graph = Vec::new();
    field(1, &node, &mut graph);
    field(5, &t1, &mut graph);
    field(5, &t2, &mut graph);
    let mut model = Vec::new();
    int(1, 8, &mut model);
    field(7, &graph, &mut model);
    model
}

fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), to).unwrap();
        }
    }
}

/// The bundled room scene, copied (the mutated file replaces one of its files).
fn scene_seed(dir: &Path, file: &str) -> Vec<u8> {
    copy_dir(&repo().join("data-samples/room"), dir);
    std::fs::read(dir.join(file)).unwrap()
}

/// Opens the scene and reads every layer of its first frame, and its classes.
fn read_scene(dir: &Path) -> Result<(), String> {
    let scene = Scene::open(dir).map_err(|e| e.to_string())?;
    let Some(f) = scene.frames().first().cloned() else { return Ok(()) };
    ok(scene.image(&f))?;
    ok(scene.depth(&f))?;
    ok(scene.normals(&f))?;
    ok(scene.mask(&f))?;
    ok(scene.labels(&f))?;
    ok(scene.instances(&f))?;
    ok(scene.classes())
}

fn view_output(w: usize, h: usize, seed: f32) -> ViewOutput {
    use dens3r_geom::Raster;
    let n = w * h;
    let pts: Vec<Vec3> = (0..n).map(|i| Vec3::new(i as f32 * 0.1, seed, 1.0 + i as f32 * 0.01)).collect();
    ViewOutput {
        points: Raster::from_vec(w, h, pts).unwrap(),
        conf: Raster::from_vec(w, h, vec![2.0; n]).unwrap(),
        normals: Some(Raster::from_vec(w, h, vec![Vec3::new(0.0, 0.0, -1.0); n]).unwrap()),
        desc: Some(dens3r_backbone::predict::DescriptorMap {
            width: w,
            height: h,
            dim: 2,
            data: (0..2 * n).map(|i| i as f32).collect(),
        }),
        desc_conf: Some(Raster::from_vec(w, h, vec![1.5; n]).unwrap()),
    }
}

const PAIR_KEY: &str = "00112233445566778899aabbccddeeff";

fn pair_cache_seed(dir: &Path) -> Vec<u8> {
    let cache = PairCache::new(Some(dir.to_path_buf()));
    cache.store(PAIR_KEY, &[view_output(4, 3, 0.0), view_output(4, 3, 1.0)]).expect("store the seed pair");
    std::fs::read(dir.join(format!("{PAIR_KEY}.d3c"))).unwrap()
}

fn read_pair_cache(dir: &Path) -> Result<(), String> {
    // A damaged entry is a miss (recomputed), never an error.
    let _ = PairCache::new(Some(dir.to_path_buf())).load(PAIR_KEY, [(4, 3), (4, 3)]);
    Ok(())
}

/// A backbone that must not be asked to compute (the test reads the cache only) but is, for a
/// damaged entry: it then returns fixed features.
struct FixedBackbone;

impl Backbone for FixedBackbone {
    fn id(&self) -> String {
        "fuzz-fixed".into()
    }
    fn patch(&self) -> usize {
        8
    }
    fn dims(&self) -> Vec<usize> {
        vec![3, 2]
    }
    fn extract(&self, _: &RgbImage) -> FeatureMaps {
        FeatureMaps {
            grid: (2, 3),
            dims: vec![3, 2],
            layers: vec![vec![0.5; 18], vec![-0.5; 12]],
            ..Default::default()
        }
    }
}

fn feature_cache_seed(dir: &Path) -> Vec<u8> {
    let cache_dir = dir.join("features");
    let mut cache = FeatureCache::new(&cache_dir, Precision::F32);
    let img = gradient(24, 16);
    cache.get(&FixedBackbone, &img).expect("store the seed features");
    let entry = cache.entry(&FixedBackbone, &img);
    std::fs::write(dir.join("entry.name"), entry.file_name().unwrap().to_string_lossy().as_bytes()).unwrap();
    std::fs::read(entry).unwrap()
}

fn read_feature_cache(dir: &Path) -> Result<(), String> {
    // The mutated bytes sit in `entry.feat`; put them where the cache looks.
    let name = std::fs::read_to_string(dir.join("entry.name")).map_err(|e| e.to_string())?;
    std::fs::copy(dir.join("entry.feat"), dir.join("features").join(name.trim())).map_err(|e| e.to_string())?;
    let mut cache = FeatureCache::new(&dir.join("features"), Precision::F32);
    ok(cache.get(&FixedBackbone, &gradient(24, 16)))
}

fn head_seed(dir: &Path) -> Vec<u8> {
    let config = HeadConfig {
        kind: "linear".into(),
        task: Task::Seg { classes: vec!["background".into(), "thing".into()] },
        backbone: "fuzz-fixed".into(),
        patch: 8,
        layers: vec![0],
        in_dims: vec![3],
        width: 8,
        widths: Vec::new(),
        size: 32,
    };
    let head = Head::new(config, 1).expect("the seed head");
    head.save(&dir.join("head.json")).expect("save the seed head");
    std::fs::read(dir.join("head.json")).unwrap()
}

/// Every reader of outside data.
pub fn targets() -> Vec<Target> {
    vec![
        Target {
            name: "npy",
            file: "a.npy",
            seed: |d| {
                let v: Vec<f32> = (0..20).map(|i| i as f32 * 0.25).collect();
                npy::write_f32(&d.join("a.npy"), &[4, 5], &v).unwrap();
                std::fs::read(d.join("a.npy")).unwrap()
            },
            read: |d| ok(npy::read_f32(&d.join("a.npy"))),
        },
        Target { name: "safetensors", file: "model.safetensors", seed: tiny_network, read: read_network },
        Target {
            name: "model-json",
            file: "model.json",
            seed: |d| {
                tiny_network(d);
                std::fs::read(d.join("model.json")).unwrap()
            },
            read: read_network,
        },
        Target {
            name: "pth",
            file: "small.pth",
            seed: |_| fixture("tests/fixtures/pth/small.pth"),
            read: |d| {
                ok(dens3r_backbone::pth::read_index(&d.join("small.pth")))?;
                ok(dens3r_backbone::Weights::from_pth(&d.join("small.pth")))
            },
        },
        Target {
            name: "pth-nesting",
            file: "deep.pth",
            seed: |_| deep_pickle(),
            read: |d| ok(dens3r_backbone::Weights::from_pth(&d.join("deep.pth"))),
        },
        Target {
            name: "safetensors-offsets",
            file: "spans.safetensors",
            seed: |_| spans_safetensors(),
            read: |d| ok(dens3r_backbone::Weights::from_safetensors(&d.join("spans.safetensors"))),
        },
        Target {
            name: "onnx",
            file: "model.onnx",
            seed: |_| onnx_seed(),
            read: |d| ok(dens3r_backbone::onnx::OnnxWeights::open(&d.join("model.onnx"))),
        },
        Target {
            name: "png",
            file: "a.png",
            seed: |_| png(&gradient(20, 12).into(), image::ImageFormat::Png),
            read: |d| ok(dens3r_backbone::preprocess::open_oriented(&d.join("a.png"))),
        },
        Target {
            name: "jpeg",
            file: "a.jpg",
            seed: |_| png(&gradient(20, 12).into(), image::ImageFormat::Jpeg),
            read: |d| ok(dens3r_backbone::preprocess::open_oriented(&d.join("a.jpg"))),
        },
        Target {
            name: "pnm",
            file: "a.pgm",
            seed: |_| {
                png(
                    &image::DynamicImage::ImageLuma8(image::imageops::grayscale(&gradient(20, 12))),
                    image::ImageFormat::Pnm,
                )
            },
            read: |d| ok(dens3r_backbone::preprocess::open_oriented(&d.join("a.pgm"))),
        },
        Target {
            name: "label-png",
            file: "labels.png",
            seed: |_| {
                let img =
                    image::ImageBuffer::<image::Luma<u16>, _>::from_fn(16, 8, |x, y| image::Luma([(x / 4 + y) as u16]));
                png(&image::DynamicImage::ImageLuma16(img), image::ImageFormat::Png)
            },
            read: |d| ok(dens3r_heads::data::read_label_png(&d.join("labels.png"))),
        },
        Target {
            name: "mesh-ply",
            file: "m.ply",
            seed: |d| mesh_seed(d, "m.ply"),
            read: |d| ok(dens3r_mesh::io::read_mesh(&d.join("m.ply"))),
        },
        Target {
            name: "mesh-ply-ascii",
            file: "m.ply",
            seed: |_| {
                b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
                  element face 2\nproperty list uchar int vertex_indices\nend_header\n\
                  0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n4 0 1 3 2\n"
                    .to_vec()
            },
            read: |d| ok(dens3r_mesh::io::read_mesh(&d.join("m.ply"))),
        },
        Target {
            name: "mesh-obj",
            file: "m.obj",
            seed: |d| mesh_seed(d, "m.obj"),
            read: |d| ok(dens3r_mesh::io::read_mesh(&d.join("m.obj"))),
        },
        Target {
            name: "mesh-off",
            file: "m.off",
            seed: |_| b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n4 0 1 3 2\n".to_vec(),
            read: |d| ok(dens3r_mesh::io::read_mesh(&d.join("m.off"))),
        },
        Target {
            name: "mesh-glb",
            file: "m.glb",
            seed: |d| mesh_seed(d, "m.glb"),
            read: |d| ok(dens3r_mesh::io::read_mesh(&d.join("m.glb"))),
        },
        Target {
            name: "cameras-json",
            file: "cameras.json",
            seed: |d| scene_seed(d, "cameras.json"),
            read: read_scene,
        },
        Target {
            name: "scene-depth",
            file: "depth/0000.npy",
            seed: |d| scene_seed(d, "depth/0000.npy"),
            read: read_scene,
        },
        Target {
            name: "scene-image",
            file: "images/0000.png",
            seed: |d| scene_seed(d, "images/0000.png"),
            read: read_scene,
        },
        Target {
            name: "classes-json",
            file: "classes.json",
            seed: |d| scene_seed(d, "classes.json"),
            read: |d| ok(dens3r_scene::read_classes(&d.join("classes.json"))),
        },
        Target {
            name: "head-json",
            file: "head.json",
            seed: head_seed,
            read: |d| ok(Head::load(&d.join("head.json"))),
        },
        Target {
            name: "head-safetensors",
            file: "head.safetensors",
            seed: |d| {
                head_seed(d);
                std::fs::read(d.join("head.safetensors")).unwrap()
            },
            read: |d| ok(Head::load(&d.join("head.json"))),
        },
        Target {
            name: "pair-cache",
            file: "00112233445566778899aabbccddeeff.d3c",
            seed: pair_cache_seed,
            read: read_pair_cache,
        },
        Target { name: "feature-cache", file: "entry.feat", seed: feature_cache_seed, read: read_feature_cache },
        Target {
            name: "arch-toml",
            file: "arch.toml",
            seed: |d| {
                tiny_network(d);
                std::fs::read(d.join("arch.toml")).unwrap()
            },
            read: |d| ok(dens3r_train::Arch::read(&d.join("arch.toml")).and_then(|a| a.check())),
        },
        Target {
            name: "train-log",
            file: "log.jsonl",
            seed: |_| {
                b"{\"step\":0,\"lr\":0.0001,\"loss\":1.5,\"pts_glb\":1.2,\"pts_n\":3.0,\"match\":null,\"n\":null,\"grad_norm\":2.0}\n"
                    .to_vec()
            },
            read: |d| ok(dens3r_train::run::read_log(&d.join("log.jsonl"))),
        },
    ]
}

/// Sets up a case folder for `t` (companions and seed) and returns the seed bytes.
pub fn prepare(t: &Target, dir: &Path) -> Vec<u8> {
    std::fs::create_dir_all(dir).unwrap();
    let seed = (t.seed)(dir);
    if let Some(parent) = dir.join(t.file).parent() {
        std::fs::create_dir_all(parent).unwrap();
    }
    std::fs::write(dir.join(t.file), &seed).unwrap();
    seed
}

/// Writes `bytes` as the target's file and reads the folder.
pub fn run(t: &Target, dir: &Path, bytes: &[u8]) -> Result<(), String> {
    std::fs::write(dir.join(t.file), bytes).map_err(|e| e.to_string())?;
    (t.read)(dir)
}

/// The legacy-format fixture checkpoint with its system-info pickle replaced by lists nested
/// just under the depth bound, holding a memo reference nested in itself: mutants move the
/// depth and the sharing across the bounds.
fn deep_pickle() -> Vec<u8> {
    let legacy = fixture("tests/fixtures/pth/legacy.pth");
    // Pickles 1 and 2 (magic number, protocol) end at byte 0x15, the system info at 0x89.
    let mut p = legacy[..0x15].to_vec();
    p.extend([0x80, 2]);
    p.extend(std::iter::repeat_n(b']', 990));
    p.extend([b'q', 0, b'h', 0, b'h', 0, 0x86, b'a']);
    p.extend(std::iter::repeat_n(b'a', 989));
    p.push(b'.');
    p.extend_from_slice(&legacy[0x89..]);
    p
}

/// A safetensors file of three adjacent tensors (f32, i64, f16): mutants of its offsets make
/// overlapping, wrapping and out-of-file ranges.
fn spans_safetensors() -> Vec<u8> {
    let header = br#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"I64","shape":[1],"data_offsets":[8,16]},"c":{"dtype":"F16","shape":[4],"data_offsets":[16,24]}}"#;
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(header);
    out.extend((0..24u8).collect::<Vec<_>>());
    out
}
