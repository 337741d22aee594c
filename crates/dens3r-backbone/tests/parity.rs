//! Parity with the official PyTorch code on the fixtures in `../shared/fixtures/parity/`
//! (dumped from the reference implementation with small random weights; spec section 9).

use dens3r_backbone::config::RopeScaling;
use dens3r_backbone::ops::Rope;
use dens3r_backbone::verify::verify_dir;
use dens3r_backbone::{Device, Tensor, TensorData};
use std::path::PathBuf;

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/fixtures/parity")
}

#[test]
fn rope_matches_reference_tables() {
    let device = Device::default();
    for grid in ["3x4", "24x32", "48x64"] {
        let dir = fixtures().join("rope");
        let (ts, tok) = dens3r_scene::npy::read_f32(&dir.join(format!("tok_{grid}.npy"))).unwrap();
        let (_, out) = dens3r_scene::npy::read_f32(&dir.join(format!("out_{grid}.npy"))).unwrap();
        let (h, w): (usize, usize) = {
            let mut it = grid.split('x').map(|s| s.parse().unwrap());
            (it.next().unwrap(), it.next().unwrap())
        };
        let pos: Vec<(usize, usize)> = (0..h).flat_map(|r| (0..w).map(move |c| (r, c))).collect();
        assert_eq!(ts, vec![1, 2, h * w, 16]);
        let rope = Rope::new(&pos, 16, 100.0, RopeScaling::Interpolated, &device);
        let x = Tensor::<4>::from_data(TensorData::new(tok, [1, 2, h * w, 16]), &device);
        let got = rope.apply(x).to_data().try_to_vec::<f32>().unwrap();
        let err = got.iter().zip(&out).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(err < 1e-5, "{grid}: max error {err}");
    }
}

#[test]
fn fixtures_match_the_pytorch_reference() {
    let device = Device::default();
    for case in ["A_shared_dec_48x64", "B_two_dec_descconf_48x64_64x48", "C_self_pair_48x64"] {
        let results = verify_dir(&fixtures().join(case), &device).unwrap_or_else(|e| panic!("{case}: {e}"));
        let failed: Vec<String> = results
            .iter()
            .filter(|r| !r.pass)
            .map(|r| format!("{} abs {:.2e} rel {:.2e}", r.name, r.max_abs, r.max_rel))
            .collect();
        assert!(failed.is_empty(), "{case}: {failed:?}");
        assert!(results.len() >= 10, "{case}: only {} arrays compared", results.len());
    }
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

#[test]
fn verify_fails_on_a_perturbed_reference() {
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&fixtures().join("A_shared_dec_48x64"), dir.path());
    let p = dir.path().join("pred1_normal.npy");
    let (shape, mut v) = dens3r_scene::npy::read_f32(&p).unwrap();
    v[1234] += 1e-3;
    dens3r_scene::npy::write_f32(&p, &shape, &v).unwrap();
    let results = verify_dir(dir.path(), &Device::default()).unwrap();
    let bad: Vec<_> = results.iter().filter(|r| !r.pass).map(|r| r.name.as_str()).collect();
    assert_eq!(bad, ["pred1_normal"]);
    let r = results.iter().find(|r| r.name == "pred1_normal").unwrap();
    assert!((r.max_abs - 1e-3).abs() < 1e-4, "{}", r.max_abs);
}

#[test]
fn partial_or_misshaped_checkpoint_lists_the_keys() {
    use dens3r_backbone::{Dens3r, ModelConfig, Weights};
    let src = std::fs::read(fixtures().join("A_shared_dec_48x64/weights.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&src).unwrap();
    let mut keep: Vec<(String, safetensors::tensor::TensorView)> = Vec::new();
    let odd = vec![0u8; 4 * 7];
    for (name, view) in st.tensors() {
        match name.as_str() {
            "enc_blocks.1.mlp.fc2.bias" => continue,
            "dec_norm.weight" => {
                keep.push((name, safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![7], &odd).unwrap()))
            }
            _ => keep.push((name, view)),
        }
    }
    let bytes = safetensors::serialize(keep, None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.safetensors");
    std::fs::write(&path, bytes).unwrap();
    let w = Weights::from_safetensors(&path).unwrap();
    let cfg = ModelConfig::from_weights(&w, Some((2, 2))).unwrap();
    let err = Dens3r::load(&w, cfg, &Device::default()).err().expect("must fail").to_string();
    assert!(err.contains("broken.safetensors"), "{err}");
    assert!(err.contains("missing 1 keys: enc_blocks.1.mlp.fc2.bias"), "{err}");
    assert!(err.contains("dec_norm.weight: [7], expected [32]"), "{err}");
    // A truncated download: the header promises bytes the file does not have.
    std::fs::write(&path, &src[..src.len() - 100]).unwrap();
    let err = Weights::from_safetensors(&path).err().unwrap().to_string();
    assert!(err.contains("broken.safetensors") && err.contains("do not hold"), "{err}");
    // Not a checkpoint at all.
    std::fs::write(&path, b"garbage").unwrap();
    let err = Weights::from_safetensors(&path).err().unwrap().to_string();
    assert!(err.contains("not a valid safetensors file"), "{err}");
}
