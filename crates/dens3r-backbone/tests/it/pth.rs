//! Native `.pth` reading against fixtures written by torch (tests/fixtures/pth/make.py): every
//! tensor's values equal the closed formulas the script used (f32, f16, bf16, views at a
//! storage offset sharing one storage, a Parameter, a 0-d tensor), `args.model` is read, the
//! state dict is found under `model` or at the top level, in the zip and the legacy format; a
//! pickle that calls `os.system` is refused by name without running it; a cut file is named.

use dens3r_backbone::pth::read_index;
use dens3r_backbone::Weights;
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/pth").join(name)
}

fn ramp(n: usize, scale: f32) -> Vec<f32> {
    (0..n).map(|i| i as f32 * scale - 1.0).collect()
}

fn check(w: &Weights, name: &str, shape: &[usize], want: &[f32], tol: f32) {
    let got = w.values(name, shape).unwrap_or_else(|| panic!("{name} not read as {shape:?}"));
    assert_eq!(got.len(), want.len(), "{name}");
    for (g, x) in got.iter().zip(want) {
        assert!((g - x).abs() <= tol * x.abs().max(1.0), "{name}: {g} vs {x}");
    }
}

#[test]
fn pth_tensors_equal_what_torch_saved() {
    for (file, args) in [("small.pth", true), ("toplevel.pth", false), ("legacy.pth", false)] {
        let w = Weights::from_safetensors(&fixture(file)).unwrap();
        check(&w, "enc.weight", &[3, 4], &ramp(12, 0.25), 0.0);
        let big = ramp(20, 0.5);
        check(&w, "dec.bias", &[4], &big[5..9], 0.0);
        check(&w, "dec.shared", &[2, 3], &big[10..16], 0.0);
        check(&w, "half.weight", &[2, 3], &ramp(6, 0.125), 1e-3);
        check(&w, "bf.weight", &[4], &ramp(4, 0.5), 1e-2);
        check(&w, "param", &[3], &ramp(3, 1.0), 0.0);
        check(&w, "scalar", &[], &[2.5], 0.0);
        let index = read_index(&fixture(file)).unwrap();
        assert_eq!(index.tensors.len(), 7, "{file}");
        let model = index.args_model.unwrap_or_default();
        assert_eq!(
            model.contains("enc_embed_dim=1024") && model.starts_with("AsymmetricCroCo3DStereo("),
            args,
            "{file}"
        );
    }
}

#[test]
fn code_in_a_pickle_is_refused_not_run() {
    // The evil command would write this file into the working folder.
    let marker = std::path::Path::new("dens3r-pwned-marker");
    let _ = std::fs::remove_file(marker);
    let e = Weights::from_safetensors(&fixture("evil.pth")).err().unwrap().to_string();
    assert!(e.contains("evil.pth") && e.contains("posix.system") || e.contains("os.system"), "{e}");
    assert!(e.contains("nothing was executed") && !e.contains('\n'), "{e}");
    assert!(!marker.exists(), "the pickle's command ran");
    // A truncated checkpoint is named, not a panic.
    let tmp = tempfile::tempdir().unwrap();
    for f in ["small.pth", "legacy.pth"] {
        let bytes = std::fs::read(fixture(f)).unwrap();
        let cut = tmp.path().join(f);
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let e = Weights::from_safetensors(&cut).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains(f) && !e.contains('\n'), "{f}: {e}");
    }
}

/// A Hugging Face model folder (`model.safetensors` + `config.json`) loads as its files do,
/// the head counts from its config (fixture A's 32-wide network has no head-dim-64 default).
#[test]
fn hugging_face_folder_loads_like_its_files() {
    let a = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/parity/A_shared_dec_48x64");
    let tmp = tempfile::tempdir().unwrap();
    let hf = tmp.path().join("naver-model");
    std::fs::create_dir_all(&hf).unwrap();
    std::fs::copy(a.join("weights.safetensors"), hf.join("model.safetensors")).unwrap();
    std::fs::copy(a.join("config.json"), hf.join("config.json")).unwrap();
    let device = dens3r_backbone::Device::flex();
    let (m1, _) = dens3r_backbone::verify::load_model(&hf, None, &device).unwrap();
    let (m2, _) =
        dens3r_backbone::verify::load_model(&a.join("weights.safetensors"), Some(&a.join("config.json")), &device)
            .unwrap();
    assert_eq!(m1.config, m2.config);
    // Without its config the file alone cannot give fixture A's head counts: the folder's
    // config.json was read.
    let e = dens3r_backbone::verify::load_model(&a.join("weights.safetensors"), None, &device).err().unwrap();
    assert!(e.path.ends_with("weights.safetensors") && e.message.contains("head counts"), "{e}");
    let e = dens3r_backbone::verify::load_model(tmp.path(), None, &device).err().unwrap();
    assert!(e.path == tmp.path() && e.message.contains("model.safetensors"), "{e}");
}

/// `convert`: a `.pth` becomes a folder whose `model.safetensors` holds what torch saved (f16 and
/// bf16 widened to f32 exactly) and whose `config.json` carries the constructor call, which gives
/// the head counts; a folder in, its config kept, and the network it holds unchanged: fixture A
/// converted still passes parity.
#[test]
fn convert_writes_a_folder_every_command_reads() {
    use dens3r_backbone::convert::to_folder;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("small");
    let c = to_folder(&fixture("small.pth"), &out).unwrap();
    assert_eq!((c.tensors, c.config), (7, true));
    let w = Weights::from_safetensors(&out.join("model.safetensors")).unwrap();
    check(&w, "enc.weight", &[3, 4], &ramp(12, 0.25), 0.0);
    check(&w, "dec.shared", &[2, 3], &ramp(20, 0.5)[10..16], 0.0);
    let original = Weights::from_safetensors(&fixture("small.pth")).unwrap();
    assert_eq!(w.values("half.weight", &[2, 3]), original.values("half.weight", &[2, 3]), "f16 widened exactly");
    assert_eq!(w.values("bf.weight", &[4]), original.values("bf.weight", &[4]), "bf16 widened exactly");
    assert_eq!(dens3r_backbone::verify::heads_from_config(&out.join("config.json")).unwrap(), Some((16, 12)));
    // A folder in: fixture A as a Hugging Face folder, converted, still passes parity.
    let a = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/parity/A_shared_dec_48x64");
    let hf = tmp.path().join("hf");
    std::fs::create_dir_all(&hf).unwrap();
    std::fs::copy(a.join("weights.safetensors"), hf.join("model.safetensors")).unwrap();
    std::fs::copy(a.join("config.json"), hf.join("config.json")).unwrap();
    let conv = tmp.path().join("conv");
    let c = to_folder(&hf, &conv).unwrap();
    assert!(c.config && c.args.is_none());
    let check_dir = tmp.path().join("A");
    std::fs::create_dir_all(&check_dir).unwrap();
    for e in std::fs::read_dir(&a).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), check_dir.join(e.file_name())).unwrap();
    }
    std::fs::copy(conv.join("model.safetensors"), check_dir.join("weights.safetensors")).unwrap();
    std::fs::copy(conv.join("config.json"), check_dir.join("config.json")).unwrap();
    let results = dens3r_backbone::verify::verify_dir(&check_dir, &dens3r_backbone::Device::flex()).unwrap();
    assert!(results.len() > 5 && results.iter().all(|r| r.pass), "converted fixture A fails parity");
    // Converting a folder into itself is refused; a missing input is named.
    let e = to_folder(&conv, &conv).unwrap_err();
    assert!(e.path == conv, "{e}");
    let e = to_folder(&tmp.path().join("none.pth"), &tmp.path().join("x")).unwrap_err();
    assert!(e.to_string().contains("none.pth"), "{e}");
}

/// The safetensors file of `header` (JSON) over `body`.
fn safetensors_bytes(header: &serde_json::Value, body: &[u8]) -> Vec<u8> {
    let h = serde_json::to_vec(header).unwrap();
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend(h);
    out.extend(body);
    out
}

/// Issue 66, 6: tensors sharing bytes are refused by name; an offset past 2^64 does not wrap
/// into the file; a tensor the network needs stored as an integer is reported with its dtype,
/// not as a missing key.
#[test]
fn overlapping_wrapping_and_integer_tensors_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let f = tmp.path().join("overlap.safetensors");
    let header = serde_json::json!({
        "a": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]},
        "b": {"dtype": "F32", "shape": [2], "data_offsets": [4, 12]},
    });
    std::fs::write(&f, safetensors_bytes(&header, &[0u8; 12])).unwrap();
    let e = Weights::from_safetensors(&f).err().unwrap().to_string();
    assert!(e.contains("'a'") && e.contains("'b'") && e.contains("share bytes"), "{e}");
    let header = serde_json::json!({
        "a": {"dtype": "U8", "shape": [7], "data_offsets": [u64::MAX - 7, u64::MAX]},
    });
    std::fs::write(&f, safetensors_bytes(&header, &[0u8; 8])).unwrap();
    let e = Weights::from_safetensors(&f).err().unwrap().to_string();
    assert!(e.contains("tensor 'a'"), "{e}");

    // Fixture A with one decoder weight's dtype relabelled I32 (the same 4 bytes a value).
    let a = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/parity/A_shared_dec_48x64");
    let bytes = std::fs::read(a.join("weights.safetensors")).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let key = "dec_blocks.1.mlp.fc1.weight";
    header[key]["dtype"] = serde_json::json!("I32");
    let ints = tmp.path().join("ints.safetensors");
    std::fs::write(&ints, safetensors_bytes(&header, &bytes[8 + n..])).unwrap();
    let device = dens3r_backbone::Device::flex();
    let e = dens3r_backbone::verify::load_model(&ints, Some(&a.join("config.json")), &device).err().unwrap();
    let e = e.to_string();
    assert!(e.contains(key) && e.contains("I32") && !e.contains("missing"), "{e}");
}
