//! The network on a GPU through burn's wgpu (or CUDA) backend: the same model code gives the
//! official PyTorch outputs of parity fixtures A, B and C (B and C where the team's shared
//! folder is present) within the CPU path's tolerance, and an
//! autodiff pass on the GPU gives the CPU's gradients. Runs on any adapter, a software one
//! included (Debian's mesa-vulkan-drivers: lavapipe); with none it says SKIPPED, and fails
//! instead when `DENS3R_REQUIRE_GPU=1` (as `scripts/test.sh` sets where a driver exists).
#![cfg(any(feature = "wgpu", feature = "cuda"))]

use dens3r_backbone::device::{cpu, is_gpu, network_device};
use dens3r_backbone::{Device, ModelConfig, Params, Tensor, TensorData, Weights};

use crate::fixtures::{parity, A};

fn gpu_or_skip() -> Option<Device> {
    match network_device(true) {
        Ok(d) => {
            assert!(is_gpu(&d), "network_device(true) gave the CPU");
            Some(d)
        }
        Err(e) => {
            assert!(std::env::var("DENS3R_REQUIRE_GPU").as_deref() != Ok("1"), "DENS3R_REQUIRE_GPU=1 but {e}");
            eprintln!("SKIPPED: {e}");
            None
        }
    }
}

#[test]
fn fixtures_match_pytorch_on_the_gpu() {
    let Some(device) = gpu_or_skip() else { return };
    crate::parity::assert_fixtures_match(&device, "the GPU");
}

/// Fixture A's network built from flat parameters on an autodiff device, and the gradient of
/// a scalar of its pointmaps with respect to every parameter.
fn grads(device: &Device) -> (f32, Vec<Vec<f32>>) {
    let dir = parity(A);
    let w = Weights::from_safetensors(&dir.join("weights.safetensors")).unwrap();
    let heads = dens3r_backbone::verify::heads_from_config(&dir.join("config.json")).unwrap();
    let config = ModelConfig::from_weights(&w, heads).unwrap();
    let params = Params::from_weights(&w, &config).unwrap();
    let tensors = params.tensors(device, &vec![true; params.values.len()]);
    let net = params.model(&tensors, device);
    let img = |name: &str| {
        let (shape, v) = dens3r_scene::npy::read_f32(&dir.join(name)).unwrap();
        Tensor::<4>::from_data(TensorData::new(v, [shape[0], shape[1], shape[2], shape[3]]), device)
    };
    let pred = net.forward(img("img1.npy"), img("img2.npy"));
    let [p1, p2] = &pred.views;
    let loss = (p1.pts3d.clone().square().mean() + p2.pts3d.clone().abs().mean()).sum();
    let value = loss.clone().into_data().try_to_vec::<f32>().unwrap()[0];
    let g = loss.backward();
    let grads = tensors
        .iter()
        .map(|t| t.grad(&g).map(|g| g.into_data().try_to_vec::<f32>().unwrap()).unwrap_or_default())
        .collect();
    (value, grads)
}

#[test]
fn gpu_gradients_equal_the_cpu_ones() {
    let Some(device) = gpu_or_skip() else { return };
    let (cpu_loss, cpu_g) = grads(&Device::autodiff(cpu()));
    let (gpu_loss, gpu_g) = grads(&Device::autodiff(device));
    assert!((cpu_loss - gpu_loss).abs() <= 1e-4 * cpu_loss.abs().max(1.0), "loss CPU {cpu_loss} GPU {gpu_loss}");
    let mut compared = 0;
    for (k, (a, b)) in cpu_g.iter().zip(&gpu_g).enumerate() {
        assert_eq!(a.len(), b.len(), "parameter {k}: gradient on one device only");
        let scale = a.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-6);
        let err = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(err <= 1e-3 * scale + 1e-6, "parameter {k}: max gradient difference {err} (largest {scale})");
        compared += (!a.is_empty()) as usize;
    }
    assert!(compared > 50, "only {compared} parameters had gradients");
}
