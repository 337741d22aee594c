//! Hand-written CPU kernels for the two ops where burn's `flex` backend trails PyTorch's
//! oneDNN (3x3 convolution and softmax attention), on raw buffers and the same `gemm` crate
//! flex uses. [`crate::ops`] calls them for tensors on the plain flex device, and
//! [`crate::autodiff_cpu`] (convolutions and their gradients, upsampling and its gradient) on
//! the autodiff flex device; on GPU backends the burn ops run.

pub mod alloc;
pub mod attention;
pub mod bf16;
pub mod conv;
pub mod linear;
pub mod pointwise;
pub mod resample;
pub mod winograd;

use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};

/// Whether linear layers built from now on take bf16 products.
static MATMUL_BF16: AtomicBool = AtomicBool::new(false);

/// Sets the precision of the CPU's linear layers built from now on, for the whole process (as
/// PyTorch's `set_float32_matmul_precision`): `BF16` rounds their weights and inputs to bf16
/// and sums the exact products in f32 ([`bf16`]; twice the multiplies per instruction on
/// CPUs with AVX-512 BF16); `F32` (the default, and what `F16` gives here) is exact f32.
/// Attention follows the precision of its block's projections ([`crate::ops::sdpa`]);
/// convolutions, normalisation and activations stay f32 either way.
pub fn set_matmul_precision(precision: crate::Precision) {
    MATMUL_BF16.store(precision == crate::Precision::BF16, Ordering::Relaxed);
}

/// The precision [`set_matmul_precision`] set.
pub fn matmul_precision() -> crate::Precision {
    if MATMUL_BF16.load(Ordering::Relaxed) {
        crate::Precision::BF16
    } else {
        crate::Precision::F32
    }
}

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

/// `dst (m x n) [+]= lhs (m x k) * rhs (k x n)`, lhs dense row-major, `rhs[(r, c)]` at
/// `rhs[r * rhs_rs + c * rhs_cs]` (row-major when `rhs_cs` is 1; a transposed view otherwise),
/// dst row-major with row stride `dst_rs`; split over output columns into single-threaded
/// `gemm` calls on rayon (parts of at least `min_cols` columns): on this backbone's shapes that
/// keeps every core busy where one multithreaded call often does not.
#[allow(clippy::too_many_arguments)]
pub(crate) fn gemm_by_columns(
    lhs: &[f32],
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
    dst: &mut [f32],
    dst_rs: usize,
    (m, k, n): (usize, usize, usize),
    accumulate: bool,
    min_cols: usize,
) {
    assert!(lhs.len() >= m * k, "gemm lhs too small");
    assert!(k == 0 || n == 0 || rhs.len() > (k - 1) * rhs_rs + (n - 1) * rhs_cs, "gemm rhs too small");
    assert!(m == 0 || dst.len() >= (m - 1) * dst_rs + n, "gemm dst too small");
    let parts = (4 * rayon::current_num_threads()).min(n.div_ceil(min_cols)).max(1);
    let width = n.div_ceil(parts).next_multiple_of(16);
    let dst_ptr = SendPtr(dst.as_mut_ptr());
    (0..n.div_ceil(width)).into_par_iter().for_each(|p| {
        let n0 = p * width;
        let nn = width.min(n - n0);
        let dst_ptr = &dst_ptr;
        // SAFETY: part p touches only columns n0..n0+nn of dst, disjoint from every other
        // part; the asserts above keep every matrix access inside its slice.
        unsafe {
            gemm::gemm(
                m,
                nn,
                k,
                dst_ptr.0.add(n0),
                1,
                dst_rs as isize,
                accumulate,
                lhs.as_ptr(),
                1,
                k as isize,
                rhs.as_ptr().add(n0 * rhs_cs),
                rhs_cs as isize,
                rhs_rs as isize,
                1.0,
                1.0,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
    });
}

/// A buffer's start, shared with rayon workers that each write a disjoint range of it.
pub(crate) struct SendPtr(pub(crate) *mut f32);
// SAFETY: used only to hand disjoint ranges of one buffer (columns of a product, rows of a
// convolution's bands) to rayon workers, while the buffer outlives them.
unsafe impl Sync for SendPtr {}

/// Seeded values in `[-scale, scale]` for the kernels' tests.
#[cfg(test)]
pub(crate) fn test_values(n: usize, seed: u64, scale: f32) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
        })
        .collect()
}

/// Reference 3x3 / stride 1 / pad 1 convolution of one image in f64, for the kernels' tests.
#[cfg(test)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn direct_conv3x3(
    x: &[f32],
    wt: &[f32],
    cin: usize,
    cout: usize,
    h: usize,
    w: usize,
    bias: &[f32],
) -> Vec<f64> {
    let mut y = vec![0.0f64; cout * h * w];
    for o in 0..cout {
        for yy in 0..h {
            for xx in 0..w {
                let mut acc = bias[o] as f64;
                for i in 0..cin {
                    for ky in 0..3 {
                        for kx in 0..3 {
                            let (sy, sx) = (yy as isize + ky as isize - 1, xx as isize + kx as isize - 1);
                            if sy < 0 || sx < 0 || sy >= h as isize || sx >= w as isize {
                                continue;
                            }
                            acc += wt[((o * cin + i) * 3 + ky) * 3 + kx] as f64
                                * x[(i * h + sy as usize) * w + sx as usize] as f64;
                        }
                    }
                }
                y[(o * h + yy) * w + xx] = acc;
            }
        }
    }
    y
}

/// Whether `device` is the plain (non-autodiff) flex CPU device computing in f32, which these
/// kernels serve. Burn's device equality ignores autodiff, so it is checked apart: the kernels
/// work on host copies and would cut the gradient graph. A flex device set to f16 / bf16
/// (`--precision`) runs burn's own kernels in that precision.
pub fn serves(device: &Device) -> bool {
    *device == Device::flex() && !device.is_autodiff() && crate::device::precision_of(device) == crate::Precision::F32
}

/// The tensor's values in logical (row-major) order.
pub(crate) fn to_vec<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor data")
}

/// A tensor from row-major values.
pub(crate) fn from_vec<const D: usize>(v: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), device)
}
