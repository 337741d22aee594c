//! Training's heaviest ops on the flex CPU device as differentiable ops (a burn backend
//! extension) on [`crate::cpu`]'s kernels:
//! - the backbone's 3x3 (stride 1, pad 1) and 1x1 convolutions: forward and input gradient by
//!   shifted or pointwise products, the weight gradient as nine (3x3) or one (1x1)
//!   matrix products over the padded input's shifted views, read transposed (burn's own `conv2d` backward
//!   computes it as a convolution with an output-sized kernel, one thin product per input
//!   channel, which took most of a training step's convolution time);
//! - the DPT's bilinear x2 upsampling (align corners), forward and its adjoint in two separable
//!   passes (burn's interpolation backward computes every pixel's weights again).
//!
//! Used by [`crate::ops`] on the autodiff flex device in f32; every other device keeps burn's
//! ops.

use crate::cpu;
use crate::ops::FastConv;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::autodiff::{Autodiff, NodeId};
use burn::backend::flex::FlexTensor;
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Backend, Dispatch, Flex, TensorMetadata};
use burn::tensor::{Device, Tensor, TensorData};

/// The differentiable ops.
#[backend_extension(Flex, Autodiff)]
pub trait CpuTrainOps: Backend {
    /// Convolution without bias: `x (B, C, H, W)`, `weight (O, C, k, k)` with k = 3 (stride 1,
    /// pad 1) or 1 (stride 1), into `(B, O, H, W)`.
    fn fast_conv(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self>;
    /// Bilinear x2 upsampling with aligned corners, `(B, C, H, W)` into `(B, C, 2H, 2W)`.
    fn fast_upsample2x(x: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// The gradients of [`CpuTrainOps`] on the inner backend.
pub trait CpuTrainGrads: Backend {
    /// The convolution's `dL/dx` from `dL/dy` and the weights.
    fn fast_conv_input_grad(dy: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self>;
    /// The convolution's `dL/dweight` from the input and `dL/dy`, for a `k x k` kernel.
    fn fast_conv_weight_grad(x: FloatTensor<Self>, dy: FloatTensor<Self>, k: usize) -> FloatTensor<Self>;
    /// The upsampling's `dL/dx` from `dL/dy`.
    fn fast_upsample2x_grad(dy: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// Whether training's ops on `device` take this path: the autodiff flex device computing in
/// f32.
pub fn serves(device: &Device) -> bool {
    *device == Device::flex() && device.is_autodiff() && crate::device::precision_of(device) == crate::Precision::F32
}

/// `conv(x, weight) + bias` through [`CpuTrainOps`] (see [`serves`] for where it applies).
pub fn conv(x: Tensor<4>, weight: Tensor<4>, bias: Option<Tensor<1>>) -> Tensor<4> {
    let out = weight.dims()[0];
    let y = Tensor::<4>::from_dispatch(<Dispatch as CpuTrainOps>::fast_conv(x.into_dispatch(), weight.into_dispatch()));
    match bias {
        Some(b) => y + b.reshape([1, out, 1, 1]),
        None => y,
    }
}

/// Bilinear x2 upsampling (aligned corners) through [`CpuTrainOps`].
pub fn upsample2x(x: Tensor<4>) -> Tensor<4> {
    Tensor::<4>::from_dispatch(<Dispatch as CpuTrainOps>::fast_upsample2x(x.into_dispatch()))
}

/// A flex tensor's dimensions and the tensor made contiguous (f32 only: [`serves`] keeps
/// other precisions off this path).
fn values<const D: usize>(t: FlexTensor) -> ([usize; D], FlexTensor) {
    let dims: [usize; D] = t.shape().dims();
    (dims, t.to_contiguous())
}

fn slice(t: &FlexTensor) -> &[f32] {
    t.as_slice::<f32>().expect("the CPU training ops run on f32 tensors")
}

fn tensor<const D: usize>(v: Vec<f32>, shape: [usize; D]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(v, shape))
}

/// Every image of `x (b, c, h, w)` through `kernel` into `(b, out, h, w)`.
fn run_images(kernel: &FastConv, x: &[f32], [b, c, h, w]: [usize; 4], out: usize) -> FlexTensor {
    let mut y = Vec::with_capacity(b * out * h * w);
    for img in x.chunks_exact(c * h * w) {
        y.extend(kernel.run(img, c, out, h, w));
    }
    tensor(y, [b, out, h, w])
}

impl CpuTrainOps for Flex {
    fn fast_conv(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        let (xd, x) = values::<4>(x);
        let ([out, inp, k, _], weight) = values::<4>(weight);
        assert_eq!(xd[1], inp, "fast_conv: the input has {} channels, the weights {inp}", xd[1]);
        run_images(&FastConv::for_training(slice(&weight), out, inp, k), slice(&x), xd, out)
    }

    fn fast_upsample2x(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let ([b, c, h, w], x) = values::<4>(x);
        tensor(cpu::resample::upsample2x(slice(&x), b * c, h, w), [b, c, 2 * h, 2 * w])
    }
}

impl CpuTrainGrads for Flex {
    fn fast_conv_input_grad(dy: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        let (dyd, dy) = values::<4>(dy);
        let ([out, inp, k, _], weight) = values::<4>(weight);
        let back = match k {
            3 => cpu::conv::flip_transpose3x3(slice(&weight), out, inp),
            _ => cpu::conv::transpose(slice(&weight), out, inp),
        };
        run_images(&FastConv::for_training(&back, inp, out, k), slice(&dy), dyd, inp)
    }

    fn fast_conv_weight_grad(x: FloatTensor<Self>, dy: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        let ([_, inp, h, w], x) = values::<4>(x);
        let ([_, out, _, _], dy) = values::<4>(dy);
        // Summed over the images (3x3: as tap matrices, turned into PyTorch's layout once).
        let mut dw = vec![0.0f32; out * inp * k * k];
        for (xi, gi) in slice(&x).chunks_exact(inp * h * w).zip(slice(&dy).chunks_exact(out * h * w)) {
            match k {
                3 => cpu::conv::conv3x3_weight_grad(xi, gi, inp, out, h, w, &mut dw),
                _ => cpu::conv::conv1x1_weight_grad(xi, gi, inp, out, h * w, &mut dw),
            }
        }
        if k == 3 {
            dw = cpu::conv::weight_from_taps(&dw, out, inp);
        }
        tensor(dw, [out, inp, k, k])
    }

    fn fast_upsample2x_grad(dy: FloatTensor<Self>) -> FloatTensor<Self> {
        let ([b, c, h2, w2], dy) = values::<4>(dy);
        let (h, w) = (h2 / 2, w2 / 2);
        tensor(cpu::resample::upsample2x_backward(slice(&dy), b * c, h, w), [b, c, h, w])
    }
}

#[derive(Debug)]
struct FastConvBackward;

impl<B: Backend + CpuTrainGrads> Backward<B, 2> for FastConvBackward {
    type State = (NodeId, NodeId);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, checkpointer: &mut Checkpointer) {
        let [node_x, node_weight] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x_state, weight_state) = ops.state;
        let x = checkpointer.retrieve_node_output::<B::FloatTensorPrimitive>(x_state);
        let weight = checkpointer.retrieve_node_output::<B::FloatTensorPrimitive>(weight_state);
        let k = weight.shape()[2];
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::fast_conv_input_grad(grad.clone(), weight));
        }
        if let Some(node) = node_weight {
            grads.register::<B>(node.id, B::fast_conv_weight_grad(x, grad, k));
        }
    }
}

#[derive(Debug)]
struct UpsampleBackward;

impl<B: Backend + CpuTrainGrads> Backward<B, 1> for UpsampleBackward {
    type State = ();

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_x] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::fast_upsample2x_grad(grad));
        }
    }
}

impl<B: Backend + CpuTrainOps + CpuTrainGrads, C: CheckpointStrategy> CpuTrainOps for Autodiff<B, C> {
    fn fast_conv(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        match FastConvBackward.prepare::<C>([x.node(), weight.node()]).compute_bound().stateful() {
            OpsKind::Tracked(mut prep) => {
                let x_state = prep.checkpoint(&x);
                let weight_state = prep.checkpoint(&weight);
                prep.finish((x_state, weight_state), B::fast_conv(x.into_primitive(), weight.into_primitive()))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::fast_conv(x.into_primitive(), weight.into_primitive())),
        }
    }

    fn fast_upsample2x(x: FloatTensor<Self>) -> FloatTensor<Self> {
        match UpsampleBackward.prepare::<C>([x.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((), B::fast_upsample2x(x.into_primitive())),
            OpsKind::UnTracked(prep) => prep.finish(B::fast_upsample2x(x.into_primitive())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::module::conv2d;
    use burn::tensor::ops::ConvOptions;

    fn rnd(shape: [usize; 4], seed: u64, device: &Device) -> Tensor<4> {
        let n = shape.iter().product();
        Tensor::from_data(TensorData::new(cpu::test_values(n, seed, 1.0), shape), device)
    }

    fn close(a: Tensor<4>, b: Tensor<4>, what: &str) {
        let (a, b) = (cpu::to_vec(a), cpu::to_vec(b));
        let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1.0);
        for (i, (p, q)) in a.iter().zip(&b).enumerate() {
            assert!((p - q).abs() <= 1e-4 * scale, "{what} [{i}]: {p} vs {q}");
        }
    }

    /// The op's output and its three gradients (input, weight, bias) against burn's own
    /// `conv2d` and its autodiff, on the same autodiff device: 3x3 and 1x1.
    #[test]
    fn matches_burn_conv2d_and_its_gradients() {
        let device = Device::flex().autodiff();
        assert!(serves(&device));
        for &(b, c, o, k, h, w) in &[(2, 5, 20, 3, 9, 13), (1, 7, 3, 3, 6, 5), (2, 6, 4, 1, 5, 8)] {
            let x0 = rnd([b, c, h, w], 1, &device);
            let w0 = rnd([o, c, k, k], 2, &device);
            let b0 = Tensor::<1>::from_data(TensorData::new(cpu::test_values(o, 3, 1.0), [o]), &device);
            let up = rnd([b, o, h, w], 4, &device);
            let run = |fast: bool| {
                let (x, wt, bias) = (x0.clone().require_grad(), w0.clone().require_grad(), b0.clone().require_grad());
                let y = if fast {
                    conv(x.clone(), wt.clone(), Some(bias.clone()))
                } else {
                    conv2d(x.clone(), wt.clone(), Some(bias.clone()), ConvOptions::new([1, 1], [k / 2; 2], [1, 1], 1))
                };
                let grads = (y.clone() * up.clone()).sum().backward();
                let g = |t: &Tensor<4>| t.grad(&grads).expect("gradient");
                (y.detach(), g(&x), g(&wt), bias.grad(&grads).expect("bias gradient").reshape([1, 1, 1, o]))
            };
            let (fast, slow) = (run(true), run(false));
            let tag = format!("{k}x{k} {c}->{o}");
            close(fast.0, slow.0, &format!("{tag} output"));
            close(fast.1, slow.1, &format!("{tag} input gradient"));
            close(fast.2, slow.2, &format!("{tag} weight gradient"));
            close(fast.3, slow.3, &format!("{tag} bias gradient"));
        }
    }

    /// The upsampling and its gradient against burn's `interpolate` (bilinear, aligned corners)
    /// and its autodiff, odd and even sizes, a size of one included.
    #[test]
    fn upsampling_matches_burn_interpolate_and_its_gradient() {
        use burn::tensor::module::interpolate;
        use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
        let device = Device::flex().autodiff();
        for &(b, c, h, w) in &[(2, 3, 5, 8), (1, 2, 1, 7), (1, 4, 6, 1)] {
            let x0 = rnd([b, c, h, w], 5, &device);
            let up = rnd([b, c, 2 * h, 2 * w], 6, &device);
            let run = |fast: bool| {
                let x = x0.clone().require_grad();
                let y = if fast {
                    upsample2x(x.clone())
                } else {
                    let opts = InterpolateOptions::new(InterpolateMode::Bilinear)
                        .with_align_corners(true)
                        .with_output_size([2 * h, 2 * w]);
                    interpolate(x.clone(), opts)
                };
                let grads = (y.clone() * up.clone()).sum().backward();
                (y.detach(), x.grad(&grads).expect("gradient"))
            };
            let (fast, slow) = (run(true), run(false));
            close(fast.0, slow.0, &format!("({b},{c},{h},{w}) output"));
            close(fast.1, slow.1, &format!("({b},{c},{h},{w}) input gradient"));
        }
    }
}
