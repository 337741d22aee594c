//! Hand-written CPU kernels for the two ops where burn's `flex` backend trails PyTorch's
//! oneDNN (3x3 convolution and softmax attention), on raw buffers and the same `gemm` crate
//! flex uses. [`crate::ops`] calls them only for tensors on the plain flex device; on GPU
//! backends and under autodiff the burn ops run, so gradients and GPU paths are untouched.

pub mod alloc;
pub mod attention;
pub mod conv;
pub mod linear;
pub mod pointwise;
pub mod resample;
pub mod winograd;

use burn::tensor::{Device, Tensor, TensorData};

/// Runs `f` compiled for AVX2 + FMA when the CPU has them: kernels written over plain loops
/// or lane arrays are then vectorised at that width (the crate is built for baseline x86-64).
#[inline(always)]
pub(crate) fn with_avx2<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
        #[target_feature(enable = "avx2,fma")]
        unsafe fn avx2<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        // SAFETY: the features were just detected.
        return unsafe { avx2(f) };
    }
    f()
}

/// Whether `device` is the plain (non-autodiff) flex CPU device these kernels serve.
pub fn serves(device: &Device) -> bool {
    *device == Device::flex()
}

/// The tensor's values in logical (row-major) order.
pub(crate) fn to_vec<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor data")
}

/// A tensor from row-major values.
pub(crate) fn from_vec<const D: usize>(v: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), device)
}
