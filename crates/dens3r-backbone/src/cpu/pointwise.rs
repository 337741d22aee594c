//! Per-element kernels on raw buffers: exact-erf GELU and the RoPE-2D rotation. burn's
//! generic versions cost 10-12 ns per element here (several passes, temporaries); these are
//! one pass, vectorised, rayon over rows.

use crate::cpu::attention::exp_approx;
use rayon::prelude::*;

/// `erf(x)` to 2e-7 absolute (Abramowitz & Stegun 7.1.26 with an accurate exponential),
/// branch-free.
#[inline(always)]
fn erf(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let poly = t * (0.254_829_6 + t * (-0.284_496_74 + t * (1.421_413_8 + t * (-1.453_152 + t * 1.061_405_4))));
    let y = 1.0 - poly * exp_approx(-a * a);
    y.copysign(x)
}

/// `x * (1 + erf(x / sqrt 2)) / 2` in place (PyTorch's default, exact GELU).
pub fn gelu_in_place(x: &mut [f32]) {
    x.par_chunks_mut(1 << 14).for_each(|c| super::with_avx2(|| gelu_chunk(c)));
}

#[inline(always)]
fn gelu_chunk(c: &mut [f32]) {
    for v in c.iter_mut() {
        *v = 0.5 * *v * (1.0 + erf(*v * std::f32::consts::FRAC_1_SQRT_2));
    }
}

/// Applies RoPE-2D in place to `rows` vectors of `dim` values laid out `(B*heads, N, dim)`:
/// the first half of each vector is rotated with the row tables, the second with the column
/// tables, each half pairing element `k` with `k + half / 2` (rotate-half). `cos_*` / `sin_*`
/// are `(N, dim / 2)`.
pub fn rope_in_place(x: &mut [f32], n: usize, dim: usize, tables: [&[f32]; 4]) {
    let half = dim / 2;
    let [cos_y, sin_y, cos_x, sin_x] = tables;
    assert!(tables.iter().all(|t| t.len() == n * half), "RoPE table size mismatch");
    assert_eq!(x.len() % (n * dim), 0, "RoPE input size mismatch");
    x.par_chunks_mut(n * dim).for_each(|head| {
        super::with_avx2(|| {
            for (i, v) in head.chunks_exact_mut(dim).enumerate() {
                let (vy, vx) = v.split_at_mut(half);
                rotate(vy, &cos_y[i * half..][..half], &sin_y[i * half..][..half]);
                rotate(vx, &cos_x[i * half..][..half], &sin_x[i * half..][..half]);
            }
        })
    });
}

/// `t * cos + rotate_half(t) * sin` with `rotate_half([lo, hi]) = [-hi, lo]`.
#[inline(always)]
fn rotate(t: &mut [f32], cos: &[f32], sin: &[f32]) {
    let f = t.len() / 2;
    let (lo, hi) = t.split_at_mut(f);
    for k in 0..f {
        let (a, b) = (lo[k], hi[k]);
        lo[k] = a * cos[k] - b * sin[k];
        hi[k] = b * cos[f + k] + a * sin[f + k];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// erf by its Maclaurin series / continued fraction in f64, as an independent reference.
    fn erf64(x: f64) -> f64 {
        if x.abs() < 3.0 {
            let mut sum = 0.0;
            let mut term = x;
            let mut k = 0.0;
            while term.abs() > 1e-17 {
                sum += term / (2.0 * k + 1.0);
                k += 1.0;
                term *= -x * x / k;
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc continued fraction (Lentz), accurate for |x| >= 3
            let a = x.abs();
            let mut f = a;
            let (mut c, mut d) = (a, 0.0);
            for i in 1..200 {
                let an = i as f64 / 2.0;
                d = 1.0 / (a + an * d);
                c = a + an / c;
                f *= c * d;
            }
            let erfc = (-a * a).exp() / f / std::f64::consts::PI.sqrt();
            (1.0 - erfc).copysign(x)
        }
    }

    #[test]
    fn gelu_matches_f64_reference() {
        let xs: Vec<f32> = (-8000..=8000).map(|i| i as f32 * 1e-3).collect();
        let mut g = xs.clone();
        gelu_in_place(&mut g);
        for (&x, &y) in xs.iter().zip(&g) {
            let want = 0.5 * x as f64 * (1.0 + erf64(x as f64 / 2f64.sqrt()));
            assert!((y as f64 - want).abs() < 4e-7 * (1.0 + x.abs() as f64), "gelu({x}) = {y}, want {want}");
        }
    }

    #[test]
    fn rope_rotates_pairs() {
        // One head, two tokens, dim 8: pairs (0,1),(2,3) per half after rotate-half pairing.
        let (n, dim) = (2, 8);
        let x: Vec<f32> = (0..n * dim).map(|i| i as f32 + 1.0).collect();
        let ang = |i: usize, k: usize| (i as f32 + 1.0) * (k as f32 + 0.5);
        let table = |f: fn(f32) -> f32, sh: f32| -> Vec<f32> {
            (0..n).flat_map(|i| (0..4).map(move |k| f(ang(i, k % 2) + sh))).collect()
        };
        let (cy, sy, cx, sx) = (table(f32::cos, 0.0), table(f32::sin, 0.0), table(f32::cos, 1.0), table(f32::sin, 1.0));
        let mut y = x.clone();
        rope_in_place(&mut y, n, dim, [&cy, &sy, &cx, &sx]);
        for i in 0..n {
            for (h, (c, s)) in [(&cy, &sy), (&cx, &sx)].into_iter().enumerate() {
                let v = &x[i * dim + 4 * h..][..4];
                let o = &y[i * dim + 4 * h..][..4];
                for k in 0..2 {
                    // rotation of the pair (v[k], v[k + 2]) by the table angle at k
                    let (cs, sn) = (c[i * 4 + k], s[i * 4 + k]);
                    assert!((o[k] - (v[k] * cs - v[k + 2] * sn)).abs() < 1e-5);
                    assert!((o[k + 2] - (v[k + 2] * cs + v[k] * sn)).abs() < 1e-5);
                }
            }
        }
    }
}
