//! `x W^T + b` on raw buffers. The product is split over output features into a few
//! single-threaded `gemm` calls run on rayon: on the backbone's shapes (768 tokens x 1024..4096)
//! this keeps both cores busy where one multithreaded call often does not. With the matmul
//! precision at bf16 ([`super::set_matmul_precision`]) the weight is kept in bf16 and the
//! product is [`super::bf16`]'s.

use super::bf16::Bf16Weight;
use std::borrow::Cow;

/// A linear layer's weight as `(in, out)`: f32 row-major, or packed bf16.
#[derive(Debug, Clone)]
enum Weight {
    F32(Vec<f32>),
    Bf16(Bf16Weight),
}

/// A linear layer's weight as `(in, out)` row-major, with its bias.
#[derive(Debug, Clone)]
pub struct LinearKernel {
    w: Weight,
    b: Option<Vec<f32>>,
    /// Input features.
    pub inp: usize,
    /// Output features.
    pub out: usize,
}

impl LinearKernel {
    /// From an `(in, out)` row-major weight and an optional `(out)` bias, in the matmul
    /// precision set now ([`super::matmul_precision`]).
    pub fn new(w_in_out: Vec<f32>, bias: Option<Vec<f32>>, inp: usize, out: usize) -> Self {
        assert_eq!(w_in_out.len(), inp * out, "linear weight size mismatch");
        assert!(bias.as_ref().is_none_or(|b| b.len() == out), "linear bias size mismatch");
        let w = match super::matmul_precision() {
            crate::Precision::BF16 => Weight::Bf16(Bf16Weight::new(&w_in_out, inp, out)),
            _ => Weight::F32(w_in_out),
        };
        Self { w, b: bias, inp, out }
    }

    /// The `(in, out)` row-major weight (bf16 values widened, for a bf16 kernel).
    pub fn weight(&self) -> Cow<'_, [f32]> {
        match &self.w {
            Weight::F32(w) => Cow::Borrowed(w),
            Weight::Bf16(w) => Cow::Owned(w.to_f32()),
        }
    }

    /// Whether its products are bf16 ([`super::set_matmul_precision`] when it was built).
    pub fn is_bf16(&self) -> bool {
        matches!(self.w, Weight::Bf16(_))
    }

    /// The bias.
    pub fn bias(&self) -> Option<&[f32]> {
        self.b.as_deref()
    }

    /// `(rows, in) -> (rows, out)`.
    pub fn forward(&self, x: &[f32], rows: usize) -> Vec<f32> {
        let (k, n) = (self.inp, self.out);
        assert_eq!(x.len(), rows * k, "linear input size mismatch");
        let mut y = vec![0.0f32; rows * n];
        if let Some(b) = &self.b {
            y.chunks_exact_mut(n).for_each(|r| r.copy_from_slice(b));
        }
        match &self.w {
            Weight::F32(w) => super::gemm_by_columns(x, w, (n, 1), &mut y, n, (rows, k, n), self.b.is_some(), 64),
            Weight::Bf16(w) => w.matmul(x, rows, &mut y, self.b.is_some()),
        }
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_naive_product() {
        let mut seed = 0u64;
        let mut rnd = |n: usize| {
            seed += 1;
            crate::cpu::test_values(n, seed, 1.0)
        };
        for &(rows, k, n, bias) in &[(5, 7, 3, true), (33, 64, 200, false), (1, 16, 1000, true)] {
            let (x, w) = (rnd(rows * k), rnd(k * n));
            let b = bias.then(|| rnd(n));
            let got = LinearKernel::new(w.clone(), b.clone(), k, n).forward(&x, rows);
            for r in 0..rows {
                for j in 0..n {
                    let want: f64 = b.as_ref().map_or(0.0, |b| b[j] as f64)
                        + (0..k).map(|i| x[r * k + i] as f64 * w[i * n + j] as f64).sum::<f64>();
                    assert!((got[r * n + j] as f64 - want).abs() < 1e-5, "({rows},{k},{n}) [{r},{j}]");
                }
            }
        }
    }
}
