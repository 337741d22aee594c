//! Where the network runs: the CPU (burn's flex backend, where this crate's `cpu` kernels
//! serve inference) or a GPU through burn's CubeCL backends: CUDA (feature `cuda`) or wgpu
//! (feature `wgpu`: Vulkan / Metal / DX12, any vendor). The model code is the same on every
//! device; only the tensors' device differs.
//!
//! Commands take the CPU unless asked (`--gpu`): burn's default device is the first GPU
//! backend compiled in, so nothing here uses `Device::default()`.

use crate::BackboneError;
use burn::tensor::{Device, Tensor, TensorData};

/// The CPU inference device (flex, with this crate's kernels).
pub fn cpu() -> Device {
    Device::flex()
}

/// How to get a build with GPU support, for error messages.
pub const GPU_BUILD_HINT: &str =
    "rebuild with the default features (`gpu-network`: wgpu, for Vulkan / Metal / DX12) or `--features cuda`";

/// The inference device: the CPU, or with `gpu` the first GPU that answers (CUDA when built
/// with `cuda`, then wgpu's default adapter, which `CUBECL_WGPU_DEFAULT_DEVICE` can pick).
/// A GPU is checked by a small upload and read-back, so a missing driver is a one-line error
/// here rather than a panic in the middle of a run.
pub fn network_device(gpu: bool) -> Result<Device, BackboneError> {
    if !gpu {
        return Ok(cpu());
    }
    let candidates = gpu_candidates();
    if candidates.is_empty() {
        return Err(BackboneError::invalid(format!(
            "--gpu: this dens3r was built without GPU support for the network; {GPU_BUILD_HINT}"
        )));
    }
    let mut tried = Vec::new();
    for (name, make) in candidates {
        match probe(make) {
            Ok(d) => return Ok(d),
            Err(e) => tried.push(format!("{name}: {e}")),
        }
    }
    Err(BackboneError::invalid(format!(
        "--gpu: no GPU answered ({}); install a Vulkan / Metal / DX12 driver (or CUDA), or drop --gpu",
        tried.join("; ")
    )))
}

/// The training device: [`network_device`] with autodiff.
pub fn training_device(gpu: bool) -> Result<Device, BackboneError> {
    network_device(gpu).map(Device::autodiff)
}

/// Whether `device` is a GPU (not the flex CPU backend).
pub fn is_gpu(device: &Device) -> bool {
    *device != Device::flex()
}

type Maker = fn() -> Device;

#[allow(clippy::vec_init_then_push, unused_mut)]
fn gpu_candidates() -> Vec<(&'static str, Maker)> {
    let mut v: Vec<(&'static str, Maker)> = Vec::new();
    #[cfg(feature = "cuda")]
    v.push(("cuda", || Device::cuda(burn::tensor::DeviceIndex::Default)));
    #[cfg(feature = "wgpu")]
    v.push(("wgpu", || Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)));
    v
}

/// Builds the device and round-trips four numbers through it; backend initialisation panics
/// (no adapter, no driver) become an error without the panic's message on stderr.
fn probe(make: Maker) -> Result<Device, String> {
    let out = dens3r_io::panics::catch_quietly(|| {
        let d = make();
        let t = Tensor::<1>::from_data(TensorData::new(vec![1f32, 2.0, 3.0, 4.0], [4]), &d);
        let back = (t * 2.0).into_data().try_to_vec::<f32>().unwrap_or_default();
        (d, back)
    });
    match out {
        Ok((d, back)) if back == [2.0, 4.0, 6.0, 8.0] => Ok(d),
        Ok((_, back)) => Err(format!("a test computation gave {back:?}")),
        Err(e) => Err(e.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_is_flex_and_not_gpu() {
        let d = network_device(false).unwrap();
        assert!(!is_gpu(&d));
        assert!(training_device(false).unwrap().is_autodiff());
    }
}
