//! The tensor seam: every numeric op the model needs, written once on burn. Everything else in
//! the crate calls these, so a backend quirk is fixed in one place.

use crate::config::RopeScaling;
use crate::cpu::{self, linear::LinearKernel, winograd::WinogradKernel};
use burn::tensor::module::{attention, conv2d, conv_transpose2d, interpolate};
use burn::tensor::ops::{
    AttentionModuleOptions, ConvOptions, ConvTransposeOptions, InterpolateMode, InterpolateOptions,
};
use burn::tensor::{Device, Tensor, TensorData};
use std::sync::Arc;

/// A linear layer: burn's `linear` with the weight stored `(in, out)`, or on the flex CPU
/// device [`cpu::linear`] holding the same values as raw buffers (one copy of the weights).
#[derive(Debug, Clone)]
pub enum Linear {
    /// Any backend: weight `(in, out)`, bias `(out)`.
    Burn(Box<(Tensor<2>, Option<Tensor<1>>)>),
    /// Flex CPU.
    Cpu(Arc<LinearKernel>),
}

impl Linear {
    /// From a PyTorch-layout `(out, in)` weight and optional `(out)` bias.
    pub fn new(weight: Tensor<2>, bias: Option<Tensor<1>>) -> Self {
        let [out, inp] = weight.dims();
        if cpu::serves(&weight.device()) {
            let w = cpu::to_vec(weight.transpose());
            return Self::Cpu(Arc::new(LinearKernel::new(w, bias.map(cpu::to_vec), inp, out)));
        }
        Self::Burn(Box::new((weight.transpose(), bias)))
    }

    /// Whether its products are bf16 (`--precision bf16` on the CPU when it was built); the
    /// attention beside it follows it ([`sdpa`]).
    pub fn is_bf16(&self) -> bool {
        matches!(self, Self::Cpu(k) if k.is_bf16())
    }

    /// `x @ W^T + b` over the last dimension.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        match self {
            Self::Cpu(k) if cpu::serves(&x.device()) => {
                let mut shape = x.dims();
                let rows = x.shape().num_elements() / k.inp;
                let device = x.device();
                let y = k.forward(&cpu::to_vec(x), rows);
                shape[D - 1] = k.out;
                cpu::from_vec(y, shape, &device)
            }
            Self::Cpu(k) => {
                let device = x.device();
                let w = cpu::from_vec(k.weight().into_owned(), [k.inp, k.out], &device);
                let b = k.bias().map(|b| cpu::from_vec(b.to_vec(), [k.out], &device));
                burn::tensor::module::linear(x, w, b)
            }
            Self::Burn(wb) => burn::tensor::module::linear(x, wb.0.clone(), wb.1.clone()),
        }
    }
}

/// LayerNorm over the last dimension (biased variance, like PyTorch).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    /// Scale, `(D)`.
    pub gamma: Tensor<1>,
    /// Shift, `(D)`.
    pub beta: Tensor<1>,
    /// Epsilon (1e-6 in every CroCo norm).
    pub eps: f64,
}

impl LayerNorm {
    /// Normalises `(B, N, D)` tokens.
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let d = x.dims()[2];
        let mean = x.clone().mean_dim(2);
        let centered = x - mean;
        let var = centered.clone().square().mean_dim(2);
        let normed = centered / var.add_scalar(self.eps).sqrt();
        normed * self.gamma.clone().reshape([1, 1, d]) + self.beta.clone().reshape([1, 1, d])
    }
}

/// A 2-D convolution with square kernel, stride and padding.
#[derive(Debug, Clone)]
pub struct Conv {
    kernel: ConvKernel,
    /// Output channels.
    pub out_ch: usize,
    /// Stride.
    pub stride: usize,
    /// Zero padding on every side.
    pub padding: usize,
}

/// Where a convolution's weights live: burn's tensors, or a raw-buffer kernel for the flex CPU
/// device, which holds them in its own layout (so the model does not keep them twice).
#[derive(Debug, Clone)]
enum ConvKernel {
    /// `(out, in, k, k)` weight and `(out)` bias for burn's convolution.
    Burn(Box<(Tensor<4>, Option<Tensor<1>>)>),
    /// The flex CPU kernel chosen for the shape.
    Cpu(Arc<FastConv>),
}

/// The CPU kernel chosen for a convolution's shape.
#[derive(Debug)]
pub(crate) enum FastConv {
    /// 3x3 / stride 1 / pad 1 with many output channels.
    Winograd(WinogradKernel, Option<Vec<f32>>),
    /// 3x3 / stride 1 / pad 1 with few output channels: nine `(out, in)` taps.
    Shifted(Vec<f32>, Option<Vec<f32>>),
    /// 1x1 / stride 1: `(out, in)`.
    Pointwise(Vec<f32>, Option<Vec<f32>>),
}

impl Conv {
    /// A convolution.
    pub fn new(weight: Tensor<4>, bias: Option<Tensor<1>>, stride: usize, padding: usize) -> Self {
        let [out, inp, kh, kw] = weight.dims();
        let fast = (cpu::serves(&weight.device()) && FastConv::serves(kh, kw, stride, padding))
            .then(|| FastConv::new(&cpu::to_vec(weight.clone()), bias.clone().map(cpu::to_vec), out, inp, kh));
        let kernel = match fast {
            Some(f) => ConvKernel::Cpu(Arc::new(f)),
            None => ConvKernel::Burn(Box::new((weight, bias))),
        };
        Self { kernel, out_ch: out, stride, padding }
    }

    /// Applies the convolution to `(B, C, H, W)`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let fast = match &self.kernel {
            ConvKernel::Burn(wb) => {
                let [_, _, k, kw] = wb.0.dims();
                if FastConv::serves(k, kw, self.stride, self.padding) && crate::autodiff_cpu::serves(&x.device()) {
                    return crate::autodiff_cpu::conv(x, wb.0.clone(), wb.1.clone());
                }
                let opts = ConvOptions::new([self.stride; 2], [self.padding; 2], [1, 1], 1);
                return conv2d(x, wb.0.clone(), wb.1.clone(), opts);
            }
            ConvKernel::Cpu(fast) => fast,
        };
        assert!(cpu::serves(&x.device()), "a convolution built on the flex CPU device got an input elsewhere");
        let [b, c, h, w] = x.dims();
        let out_ch = self.out_ch;
        let device = x.device();
        let data = cpu::to_vec(x);
        let mut out = Vec::with_capacity(b * out_ch * h * w);
        for img in data.chunks_exact(c * h * w) {
            out.extend(fast.run(img, c, out_ch, h, w));
        }
        cpu::from_vec(out, [b, out_ch, h, w], &device)
    }

    /// The convolution of one image `(C, h, w)` given as a raw buffer, `(out, h, w)`; `None`
    /// unless a CPU kernel serves it (built on the plain flex device, stride 1, 1x1 or 3x3).
    pub(crate) fn forward_raw(&self, img: &[f32], h: usize, w: usize) -> Option<Vec<f32>> {
        match &self.kernel {
            ConvKernel::Cpu(fast) => Some(fast.run(img, img.len() / (h * w), self.out_ch, h, w)),
            ConvKernel::Burn(_) => None,
        }
    }

    /// Whether [`Conv::forward_raw`] serves this convolution.
    pub(crate) fn has_raw(&self) -> bool {
        matches!(self.kernel, ConvKernel::Cpu(_))
    }
}

impl FastConv {
    /// Whether a kernel serves this shape: 3x3 / stride 1 / pad 1, or 1x1 / stride 1.
    pub(crate) fn serves(kh: usize, kw: usize, stride: usize, padding: usize) -> bool {
        matches!((kh, kw, stride, padding), (3, 3, 1, 1) | (1, 1, 1, 0))
    }

    /// The kernel for `(out, inp, k, k)` weights (`k` = 3 or 1; see [`FastConv::serves`]).
    pub(crate) fn new(weight: &[f32], bias: Option<Vec<f32>>, out: usize, inp: usize, k: usize) -> Self {
        match k {
            // Winograd's per-tile transforms cost ~ in + out channels per product of
            // in x out, so narrow outputs favour the shifted products; F(4x4) Winograd
            // still won at 128 -> 16 channels on 384x512 (68 vs 127 ms), hence 16.
            3 if out >= 16 => FastConv::Winograd(WinogradKernel::new(weight, out, inp), bias),
            3 => FastConv::Shifted(cpu::conv::taps_from_weight(weight, out, inp), bias),
            1 => FastConv::Pointwise(weight.to_vec(), bias),
            _ => panic!("no CPU convolution kernel for {k}x{k} weights"),
        }
    }

    /// The kernel training uses for `(out, inp, k, k)` weights: shifted products for 3x3, since
    /// its weights change at every step, so Winograd would transform them for each call, and on
    /// training's sizes that costs more than it saves (dens3r-s, 12 steps at 224x160, batch 2:
    /// 16.3 s with Winograd, 14.9 s without; 6 steps at 384x288, batch 1: 14.1 s, 13.3 s).
    pub(crate) fn for_training(weight: &[f32], out: usize, inp: usize, k: usize) -> Self {
        match k {
            3 => FastConv::Shifted(cpu::conv::taps_from_weight(weight, out, inp), None),
            _ => Self::new(weight, None, out, inp, k),
        }
    }

    /// One image `(c, h, w)` into `(out_ch, h, w)`.
    pub(crate) fn run(&self, img: &[f32], c: usize, out_ch: usize, h: usize, w: usize) -> Vec<f32> {
        match self {
            FastConv::Winograd(k, bias) => k.forward(img, h, w, bias.as_deref()),
            FastConv::Shifted(taps, bias) => cpu::conv::conv3x3_shifted(img, taps, bias.as_deref(), c, out_ch, h, w),
            FastConv::Pointwise(wt, bias) => cpu::conv::conv1x1(img, wt, bias.as_deref(), c, out_ch, h * w),
        }
    }
}

/// A transposed convolution with kernel = stride (non-overlapping upsampling).
#[derive(Debug, Clone)]
pub struct ConvTranspose {
    /// `(in, out, k, k)` (PyTorch layout).
    pub weight: Tensor<4>,
    /// `(out)`.
    pub bias: Tensor<1>,
    /// Kernel = stride.
    pub stride: usize,
}

impl ConvTranspose {
    /// Upsamples `(B, C, H, W)` by `stride`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let opts = ConvTransposeOptions::new([self.stride; 2], [0, 0], [0, 0], [1, 1], 1);
        conv_transpose2d(x, self.weight.clone(), Some(self.bias.clone()), opts)
    }
}

/// Bilinear x2 upsampling with `align_corners=True` (DPT).
pub fn upsample2x(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    if cpu::serves(&x.device()) {
        let device = x.device();
        let y = cpu::resample::upsample2x(&cpu::to_vec(x), b * c, h, w);
        return cpu::from_vec(y, [b, c, 2 * h, 2 * w], &device);
    }
    if crate::autodiff_cpu::serves(&x.device()) {
        return crate::autodiff_cpu::upsample2x(x);
    }
    if x.device() != Device::flex() {
        // GPU backends have no bilinear-interpolation backward (burn 0.22's CubeCL kernels).
        return upsample2x_by_matmul(x);
    }
    let opts =
        InterpolateOptions::new(InterpolateMode::Bilinear).with_align_corners(true).with_output_size([2 * h, 2 * w]);
    interpolate(x, opts)
}

/// [`upsample2x`] as two matrix products (rows, then columns), which every backend
/// differentiates.
fn upsample2x_by_matmul(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let x = x.reshape([b * c * h, w]).matmul(upsample2x_matrix(w, &device).transpose());
    let x = x.reshape([b * c, h, 2 * w]).swap_dims(1, 2).reshape([b * c * 2 * w, h]);
    let x = x.matmul(upsample2x_matrix(h, &device).transpose());
    x.reshape([b * c, 2 * w, 2 * h]).swap_dims(1, 2).reshape([b, c, 2 * h, 2 * w])
}

/// The `(2n, n)` matrix of linear interpolation from `n` samples to `2n` with
/// `align_corners=True`: output `o` reads `o (n - 1) / (2n - 1)`.
fn upsample2x_matrix(n: usize, device: &Device) -> Tensor<2> {
    let m = 2 * n;
    let mut a = vec![0f32; m * n];
    for o in 0..m {
        let src = if m > 1 { o as f64 * (n - 1) as f64 / (m - 1) as f64 } else { 0.0 };
        let i0 = (src.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        let f = (src - i0 as f64) as f32;
        a[o * n + i0] += 1.0 - f;
        a[o * n + i1] += f;
    }
    Tensor::from_data(TensorData::new(a, [m, n]), device)
}

/// `(B, C r^2, h, w) -> (B, C, h r, w r)`, PyTorch's `pixel_shuffle`.
pub fn pixel_shuffle(x: Tensor<4>, r: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let c_out = c / (r * r);
    x.reshape([b, c_out, r, r, h, w]).permute([0, 1, 4, 2, 5, 3]).reshape([b, c_out, h * r, w * r])
}

/// An element-wise op: the in-place CPU kernel on the flex device, the burn op elsewhere.
fn elementwise<const D: usize>(
    x: Tensor<D>,
    on_cpu: impl FnOnce(&mut [f32]),
    on_burn: impl FnOnce(Tensor<D>) -> Tensor<D>,
) -> Tensor<D> {
    if !cpu::serves(&x.device()) {
        return on_burn(x);
    }
    let (shape, device) = (x.dims(), x.device());
    let mut v = cpu::to_vec(x);
    on_cpu(&mut v);
    cpu::from_vec(v, shape, &device)
}

/// `max(x, 0)`.
pub fn relu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    elementwise(x, cpu::resample::relu_in_place, burn::tensor::activation::relu)
}

/// Exact (erf) GELU.
pub fn gelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    elementwise(x, cpu::pointwise::gelu_in_place, burn::tensor::activation::gelu)
}

/// Softmax attention of `(B, heads, N, Dh)` queries, keys and values, scaled by `Dh^-1/2`:
/// [`cpu::attention`] on the flex CPU device (its products in bf16 when `bf16`: a block built
/// in bf16, [`Linear::is_bf16`]), burn's fused op elsewhere.
pub fn sdpa(q: Tensor<4>, k: Tensor<4>, v: Tensor<4>, bf16: bool) -> Tensor<4> {
    if cpu::serves(&q.device()) {
        let ([b, h, nq, dh], nk, device) = (q.dims(), k.dims()[2], q.device());
        let (q, k, v) = (cpu::to_vec(q), cpu::to_vec(k), cpu::to_vec(v));
        let out = cpu::attention::attention_with(&q, &k, &v, b * h, nq, nk, dh, bf16);
        return cpu::from_vec(out, [b, h, nq, dh], &device);
    }
    attention(q, k, v, None, None, AttentionModuleOptions::default())
}

/// Precomputed RoPE-2D rotation for one set of token positions.
#[derive(Debug, Clone)]
pub struct Rope {
    cos_y: Tensor<2>,
    sin_y: Tensor<2>,
    cos_x: Tensor<2>,
    sin_x: Tensor<2>,
    /// The same four tables as raw `(N, Dh / 2)` buffers, for the flex CPU device.
    raw: Option<Arc<[Vec<f32>; 4]>>,
}

impl Rope {
    /// Tables for `(row, col)` positions and head dimension `head_dim` (spec 1.4): the first
    /// half of each head is rotated by the row, the second by the column, with rotate-half
    /// pairing and `inv_freq_k = base^(-2k / (head_dim / 2))`. Under
    /// [`RopeScaling::Interpolated`] positions are multiplied by `32 / S`, `S = max(pos) + 1`
    /// over both coordinates of this call.
    pub fn new(
        positions: &[(usize, usize)],
        head_dim: usize,
        base: f64,
        scaling: RopeScaling,
        device: &Device,
    ) -> Self {
        let half = head_dim / 2;
        let nfreq = half / 2;
        // The reference scales in float32 as t = arange(S) * 32 / S, S = max(pos) + 1.
        let s = (positions.iter().map(|&(r, c)| r.max(c)).max().unwrap_or(0) + 1) as f32;
        let position = |i: usize| match scaling {
            RopeScaling::Plain => i as f32,
            RopeScaling::Interpolated => i as f32 * 32.0 / s,
        };
        let table = |coord: &dyn Fn(&(usize, usize)) -> usize, f: fn(f32) -> f32| {
            let mut v = Vec::with_capacity(positions.len() * half);
            for p in positions {
                let t = position(coord(p));
                for _ in 0..2 {
                    for k in 0..nfreq {
                        let inv = (1.0 / base.powf(2.0 * k as f64 / half as f64)) as f32;
                        v.push(f(t * inv));
                    }
                }
            }
            Tensor::<2>::from_data(TensorData::new(v, [positions.len(), half]), device)
        };
        let (cos_y, sin_y) = (table(&|p| p.0, f32::cos), table(&|p| p.0, f32::sin));
        let (cos_x, sin_x) = (table(&|p| p.1, f32::cos), table(&|p| p.1, f32::sin));
        let raw =
            cpu::serves(device).then(|| Arc::new([&cos_y, &sin_y, &cos_x, &sin_x].map(|t| cpu::to_vec(t.clone()))));
        Self { cos_y, sin_y, cos_x, sin_x, raw }
    }

    /// Rotates `(B, heads, N, Dh)` queries or keys.
    pub fn apply(&self, x: Tensor<4>) -> Tensor<4> {
        let [b, h, n, d] = x.dims();
        if let Some(raw) = self.raw.as_ref().filter(|_| cpu::serves(&x.device())) {
            let device = x.device();
            let mut v = cpu::to_vec(x);
            cpu::pointwise::rope_in_place(&mut v, n, d, [&raw[0], &raw[1], &raw[2], &raw[3]]);
            return cpu::from_vec(v, [b, h, n, d], &device);
        }
        let half = d / 2;
        let y_part = x.clone().narrow(3, 0, half);
        let x_part = x.narrow(3, half, half);
        let rot = |t: Tensor<4>, cos: &Tensor<2>, sin: &Tensor<2>| {
            let f = half / 2;
            let lo = t.clone().narrow(3, 0, f);
            let hi = t.clone().narrow(3, f, f);
            let rotated = Tensor::cat(vec![hi.neg(), lo], 3);
            let c = cos.clone().reshape([1, 1, n, half]);
            let s = sin.clone().reshape([1, 1, n, half]);
            t * c + rotated * s
        };
        let out = Tensor::cat(vec![rot(y_part, &self.cos_y, &self.sin_y), rot(x_part, &self.cos_x, &self.sin_x)], 3);
        debug_assert_eq!(out.dims(), [b, h, n, d]);
        out
    }
}

/// Row-major `(row, col)` positions of an `h x w` token grid.
pub fn grid_positions(h: usize, w: usize) -> Vec<(usize, usize)> {
    (0..h).flat_map(|r| (0..w).map(move |c| (r, c))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The matrix form of the x2 bilinear upsampling equals the CPU kernel (itself tested
    /// against a direct f64 loop), odd sizes and a single row included.
    #[test]
    fn upsample_by_matmul_equals_the_kernel() {
        let device = Device::flex();
        for (b, c, h, w) in [(1, 1, 1, 5), (2, 3, 4, 7), (1, 2, 9, 6)] {
            let v: Vec<f32> = (0..b * c * h * w).map(|i| ((i * 37 % 101) as f32 / 10.0).sin()).collect();
            let x = Tensor::<4>::from_data(TensorData::new(v, [b, c, h, w]), &device);
            let a = upsample2x(x.clone()).into_data().try_to_vec::<f32>().unwrap();
            let m = upsample2x_by_matmul(x).into_data().try_to_vec::<f32>().unwrap();
            assert_eq!(a.len(), m.len());
            let err = a.iter().zip(&m).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
            assert!(err < 1e-6, "{b}x{c}x{h}x{w}: {err}");
        }
    }
}
