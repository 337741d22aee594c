//! Where the network runs: the CPU (burn's flex backend, where this crate's `cpu` kernels
//! serve inference) or a GPU through burn's CubeCL backends: CUDA (feature `cuda`) or wgpu
//! (feature `wgpu`: Vulkan / Metal / DX12, any vendor). The model code is the same on every
//! device; only the tensors' device differs.
//!
//! Commands take the CPU unless asked (`--gpu`): burn's default device is the first GPU
//! backend compiled in, so nothing here uses `Device::default()`.

use crate::params::Precision;
use crate::BackboneError;
use burn::tensor::{Device, FloatDType, Tensor, TensorData};

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
    network_device_at(gpu, Precision::F32)
}

/// The float precision `device` computes in (its default float dtype).
pub fn precision_of(device: &Device) -> Precision {
    match device.settings().float_dtype {
        FloatDType::F16 => Precision::F16,
        FloatDType::BF16 => Precision::BF16,
        _ => Precision::F32,
    }
}

/// Sets `device`'s default float dtype to `precision` before any tensor is made on it (burn
/// fixes a device's dtype at its first tensor, for the whole process). An error when the device
/// cannot compute in it, or already computes in another.
fn set_precision(device: &mut Device, precision: Precision) -> Result<(), String> {
    if !device.supports_dtype(precision.dtype()) {
        return Err(format!(
            "this device does not compute in {precision}; use another --precision (f32 works everywhere)"
        ));
    }
    match device.configure(precision.dtype()) {
        Ok(()) => Ok(()),
        Err(_) if precision_of(device) == precision => Ok(()),
        Err(_) => Err(format!(
            "this process already computes in {} on this device, so it cannot switch to {precision}",
            precision_of(device)
        )),
    }
}

/// [`network_device`] computing in `precision`. `F32` is the reference every parity check
/// uses; `F16` and `BF16` are opt-in (`--precision`): on a GPU they halve memory traffic and
/// use its half-precision units, at an error against f32 that `dens3r verify --precision`
/// measures and prints. On the CPU, `BF16` keeps the f32 device and sets the linear layers'
/// products to bf16 for the models loaded after this call ([`crate::cpu::set_matmul_precision`]:
/// about twice as fast where the CPU has AVX-512 BF16, the same numbers without it), `F32`
/// sets them back; `F16` runs burn's generic kernels there, for measuring its error, not for
/// speed.
pub fn network_device_at(gpu: bool, precision: Precision) -> Result<Device, BackboneError> {
    if !gpu {
        crate::cpu::set_matmul_precision(precision);
        if precision == Precision::BF16 {
            return Ok(cpu());
        }
        let mut d = cpu();
        set_precision(&mut d, precision)
            .map_err(|e| BackboneError::invalid(format!("--precision {precision}: {e}")))?;
        return Ok(d);
    }
    let candidates = gpu_candidates();
    if candidates.is_empty() {
        return Err(BackboneError::invalid(format!(
            "--gpu: this dens3r was built without GPU support for the network; {GPU_BUILD_HINT}"
        )));
    }
    let mut tried = Vec::new();
    for (name, make) in candidates {
        match probe(make, precision) {
            Ok(d) => return Ok(d),
            Err(Probe::Precision(e)) => {
                return Err(BackboneError::invalid(format!("--gpu --precision {precision}: the GPU ({name}): {e}")))
            }
            Err(Probe::Failed(e)) => tried.push(format!("{name}: {e}")),
        }
    }
    Err(BackboneError::invalid(format!(
        "--gpu: no GPU answered ({}); install a Vulkan / Metal / DX12 driver (or CUDA), or drop --gpu",
        tried.join("; ")
    )))
}

/// What `--precision bf16` computes in bf16 on the CPU (the rest stays f32), for messages.
pub const CPU_BF16_SCOPE: &str = "the linear layers' and attention's products";

/// A one-line note when `precision` gains no speed where the network runs: bf16 on a CPU
/// without AVX-512 BF16 (same numbers as with it, at f32's speed).
pub fn precision_note(gpu: bool, precision: Precision) -> Option<String> {
    (!gpu && precision == Precision::BF16 && !crate::cpu::bf16::native()).then(|| {
        "note: this CPU has no AVX-512 BF16, so --precision bf16 rounds as it would but runs at f32's speed \
         (the same numbers; f32 is exact)"
            .to_string()
    })
}

/// The training device: [`network_device`] with autodiff.
pub fn training_device(gpu: bool) -> Result<Device, BackboneError> {
    network_device(gpu).map(Device::autodiff)
}

/// The GPU's name as its driver reports it (e.g. "llvmpipe (LLVM 15.0.6, 256 bits)" for
/// lavapipe, Mesa's CPU Vulkan driver); `None` for the CPU or a backend that does not say.
pub fn gpu_name(device: &Device) -> Option<String> {
    if !is_gpu(device) {
        return None;
    }
    #[cfg(any(feature = "wgpu", feature = "cuda"))]
    return device.identity().map(|i| i.name);
    #[cfg(not(any(feature = "wgpu", feature = "cuda")))]
    None
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

/// Why a GPU candidate was not taken: it answered but cannot compute in the precision asked,
/// or it did not answer.
enum Probe {
    Precision(String),
    Failed(String),
}

/// Builds the device in `precision` and round-trips four numbers through it; backend
/// initialisation panics (no adapter, no driver) become an error without the panic's message
/// on stderr.
fn probe(make: Maker, precision: Precision) -> Result<Device, Probe> {
    let out = dens3r_io::panics::catch_quietly(|| {
        let mut d = make();
        set_precision(&mut d, precision).map(|()| {
            let t = Tensor::<1>::from_data(TensorData::new(vec![1f32, 2.0, 3.0, 4.0], [4]), &d);
            let back = (t * 2.0).into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default();
            (d, back)
        })
    });
    match out {
        Ok(Err(e)) => Err(Probe::Precision(e)),
        Ok(Ok((d, back))) if back == [2.0, 4.0, 6.0, 8.0] => Ok(d),
        Ok(Ok((_, back))) => Err(Probe::Failed(format!("a test computation gave {back:?}"))),
        Err(e) => Err(Probe::Failed(e.0)),
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
