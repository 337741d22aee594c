//! Parity with the official PyTorch code on the parity fixtures (dumped from the reference
//! implementation with small random weights; spec section 9): fixture A and the RoPE tables
//! from the repository, fixtures B and C and the full-size key listings from `../shared/`
//! when it is present.

use dens3r_backbone::config::RopeScaling;
use dens3r_backbone::ops::Rope;
use dens3r_backbone::verify::verify_dir;
use dens3r_backbone::{Tensor, TensorData};

use crate::fixtures::{parity, shared, shared_parity, A};

#[test]
fn rope_matches_reference_tables() {
    let device = dens3r_backbone::device::cpu();
    for grid in ["3x4", "24x32", "48x64"] {
        let dir = parity("rope");
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

/// Fixture A, and B (two decoders, descriptor confidence, 48x64 beside 64x48) and C (a
/// self-pair) where the team's shared folder is present, verified on `device` within the
/// spec's tolerance; `on` names the device in messages.
pub(crate) fn assert_fixtures_match(device: &dens3r_backbone::Device, on: &str) {
    let mut cases = vec![(A, parity(A))];
    for case in ["B_two_dec_descconf_48x64_64x48", "C_self_pair_48x64"] {
        cases.extend(shared_parity(case, &format!("parity fixture {case} on {on}")).map(|p| (case, p)));
    }
    for (case, dir) in cases {
        let results = verify_dir(&dir, device).unwrap_or_else(|e| panic!("{case}: {e}"));
        let failed: Vec<String> = results
            .iter()
            .filter(|r| !r.pass)
            .map(|r| format!("{} abs {:.2e} rel {:.2e}", r.name, r.max_abs, r.max_rel))
            .collect();
        assert!(failed.is_empty(), "{case} on {on}: off the PyTorch reference: {failed:?}");
        assert!(results.len() >= 10, "{case}: only {} arrays compared", results.len());
        let worst = results.iter().map(|r| r.max_abs).fold(0.0, f64::max);
        eprintln!("parity on {on}, {case}: {} arrays, max abs error {worst:.2e}", results.len());
    }
}

#[test]
fn fixtures_match_the_pytorch_reference() {
    assert_fixtures_match(&dens3r_backbone::device::cpu(), "the CPU");
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
    copy_dir(&parity(A), dir.path());
    let p = dir.path().join("pred1_normal.npy");
    let (shape, mut v) = dens3r_scene::npy::read_f32(&p).unwrap();
    v[1234] += 1e-3;
    dens3r_scene::npy::write_f32(&p, &shape, &v).unwrap();
    let results = verify_dir(dir.path(), &dens3r_backbone::device::cpu()).unwrap();
    let bad: Vec<_> = results.iter().filter(|r| !r.pass).map(|r| r.name.as_str()).collect();
    assert_eq!(bad, ["pred1_normal"]);
    let r = results.iter().find(|r| r.name == "pred1_normal").unwrap();
    assert!((r.max_abs - 1e-3).abs() < 1e-4, "{}", r.max_abs);
}

#[test]
fn partial_or_misshaped_checkpoint_lists_the_keys() {
    use dens3r_backbone::{Dens3r, ModelConfig, Weights};
    let src = std::fs::read(parity(A).join("weights.safetensors")).unwrap();
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
    let err = Dens3r::load(&w, cfg, &dens3r_backbone::device::cpu()).err().expect("must fail").to_string();
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

/// A header-only checkpoint of a full-size key listing (`name<TAB>(d0, d1, ...)` per line): a
/// safetensors file of zeros whose data is a hole, so no gigabytes are written.
fn sparse_checkpoint(listing: &std::path::Path, dir: &std::path::Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(listing).unwrap();
    let mut header = serde_json::Map::new();
    let mut offset = 0u64;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let (name, shape) = line.split_once('\t').unwrap_or_else(|| panic!("{}: bad line {line:?}", listing.display()));
        let shape: Vec<u64> = shape
            .trim_matches(|c| c == '(' || c == ')')
            .split(',')
            .filter(|s| !s.trim().is_empty())
            .map(|s| s.trim().parse().unwrap())
            .collect();
        let bytes = 4 * shape.iter().product::<u64>();
        header.insert(
            name.into(),
            serde_json::json!({"dtype": "F32", "shape": shape, "data_offsets": [offset, offset + bytes]}),
        );
        offset += bytes;
    }
    let mut h = serde_json::to_vec(&header).unwrap();
    h.resize(h.len().next_multiple_of(8), b' ');
    let path = dir.join(listing.file_stem().unwrap()).with_extension("safetensors");
    let mut bytes = (h.len() as u64).to_le_bytes().to_vec();
    bytes.extend(h);
    std::fs::write(&path, &bytes).unwrap();
    std::fs::OpenOptions::new().write(true).open(&path).unwrap().set_len(bytes.len() as u64 + offset).unwrap();
    path
}

/// The architecture read from the shapes of the official full-size checkpoints (key listings
/// dumped from the released files): Dens3R with a shared decoder is the paper's model
/// (`ModelConfig::dens3r_full`), the other variants differ where their files do.
#[test]
fn full_size_key_listings_give_the_official_architectures() {
    use dens3r_backbone::config::ModelConfig;
    use dens3r_backbone::Weights;
    let Some(keys) = shared("fixtures/keys", "config from the full-size key listings") else { return };
    let dir = tempfile::tempdir().unwrap();
    let config = |file: &str| {
        let w = Weights::from_safetensors(&sparse_checkpoint(&keys.join(file), dir.path())).unwrap();
        ModelConfig::from_weights(&w, Some((16, 12)))
    };
    let dens3r = config("keys_dens3r_shared_dec.txt").unwrap();
    assert_eq!(dens3r, ModelConfig::dens3r_full());
    let two = config("keys_dens3r_two_dec_descconf_atm.txt").unwrap();
    assert_eq!(
        ModelConfig { shared_decoder: true, desc_conf: false, ..two.clone() },
        ModelConfig::dens3r_full(),
        "only the second decoder and desc_conf differ"
    );
    assert!(!two.shared_decoder && two.desc_conf);
    for file in
        ["keys_DUSt3R_ViTLarge_BaseDecoder_512_dpt.txt", "keys_MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.txt"]
    {
        let c = config(file).unwrap();
        let mast3r = file.starts_with("keys_MASt3R");
        assert_eq!((c.enc_dim, c.enc_depth, c.dec_dim, c.dec_depth, c.patch), (1024, 24, 768, 12, 16), "{file}");
        assert_eq!(c.rope, RopeScaling::Plain, "{file}: upstream RoPE");
        assert!(!c.shared_decoder && c.has_conf && c.normal_head.is_none(), "{file}");
        assert_eq!((c.head1.prefix.as_str(), c.head2.prefix.as_str()), ("downstream_head1", "downstream_head2"));
        assert_eq!(c.head1.dpt().unwrap().layer_dims, [96, 192, 384, 768], "{file}");
        assert_eq!(
            (c.desc_dim, c.desc_conf, c.head1.mlp_hidden.is_some()),
            if mast3r { (24, true, true) } else { (0, false, false) }
        );
    }
    // DUSt3R's linear heads: `downstream_headK.proj` of (4 x 16 x 16, 768), spec section 4.
    let c = config("keys_DUSt3R_ViTLarge_BaseDecoder_512_linear.txt").unwrap();
    for h in [&c.head1, &c.head2] {
        assert_eq!(h.decoder, dens3r_backbone::config::PtsDecoder::Linear { out_channels: 4 });
        assert!(h.mlp_hidden.is_none());
    }
    assert!(c.has_conf && c.desc_dim == 0 && c.normal_head.is_none() && !c.shared_decoder);
}
