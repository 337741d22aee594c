//! Softmax attention on raw `f32` buffers: for each (batch, head) and block of queries,
//! `S = Q K^T / sqrt(Dh)` and `O = softmax(S) V` as two products on the `gemm` crate, with the
//! blocks spread over rayon. The score block stays in cache; nothing of size `N x N` is ever
//! allocated per head.

use gemm::Parallelism;
use rayon::prelude::*;

/// Query rows per block.
const BLOCK: usize = 64;

/// `softmax(q k^T / sqrt(dh)) v` for row-major `q: (bh, nq, dh)`, `k, v: (bh, nk, dh)`.
pub fn attention(q: &[f32], k: &[f32], v: &[f32], bh: usize, nq: usize, nk: usize, dh: usize) -> Vec<f32> {
    run(q, k, v, (bh, nq, nk, dh), &Products::F32)
}

/// [`attention`] with its two products in bf16 when `bf16` (as [`super::bf16`]'s linear
/// layers: queries, keys, values and the softmax's unnormalised weights rounded to bf16,
/// exact products summed in f32; the scores, the exponentials, their sums and the
/// normalisation stay f32); on `VDPBF16PS` where the CPU has AVX-512 BF16, else the rounded
/// values through the f32 kernel.
#[allow(clippy::too_many_arguments)]
pub fn attention_with(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    bh: usize,
    nq: usize,
    nk: usize,
    dh: usize,
    bf16: bool,
) -> Vec<f32> {
    if !bf16 {
        return attention(q, k, v, bh, nq, nk, dh);
    }
    // Sizes checked before the operands are rounded or packed (`run` checks them again).
    let dims = (bh, nq, nk, dh);
    check(q, k, v, dims);
    if !super::bf16::native() {
        use super::bf16::rounded;
        return run(&rounded(q), &rounded(k), &rounded(v), dims, &Products::Rounded);
    }
    // Each head's keys (transposed: dh x nk) and values (nk x dh) packed once for all its
    // query blocks.
    let packed = (0..bh)
        .into_par_iter()
        .map(|h| {
            let (kh, vh) = (&k[h * nk * dh..][..nk * dh], &v[h * nk * dh..][..nk * dh]);
            let (mut pk, mut pv) = (Vec::new(), Vec::new());
            super::bf16::pack(kh, dh, nk, (1, dh), &mut pk);
            super::bf16::pack(vh, nk, dh, (dh, 1), &mut pv);
            (pk, pv)
        })
        .collect();
    run(q, k, v, dims, &Products::Packed(packed))
}

/// How [`run`] multiplies.
enum Products {
    /// f32 operands.
    F32,
    /// Operands already rounded to bf16; round the softmax's weights too.
    Rounded,
    /// On `VDPBF16PS`: each head's packed keys (transposed) and values.
    Packed(Vec<(Vec<u32>, Vec<u32>)>),
}

fn check(q: &[f32], k: &[f32], v: &[f32], (bh, nq, nk, dh): (usize, usize, usize, usize)) {
    assert_eq!(q.len(), bh * nq * dh, "query size mismatch");
    assert_eq!(k.len(), bh * nk * dh, "key size mismatch");
    assert_eq!(v.len(), bh * nk * dh, "value size mismatch");
}

fn run(q: &[f32], k: &[f32], v: &[f32], dims: (usize, usize, usize, usize), products: &Products) -> Vec<f32> {
    check(q, k, v, dims);
    let (bh, nq, nk, dh) = dims;
    let mut out = vec![0.0f32; bh * nq * dh];
    let scale = 1.0 / (dh as f32).sqrt();
    out.par_chunks_mut(BLOCK * dh).enumerate().for_each_init(
        || (vec![0.0f32; BLOCK * nk], Vec::new()),
        |(scores, pairs), (chunk, o)| {
            // Blocks never straddle heads when nq is a multiple of BLOCK; otherwise split.
            let row0 = chunk * BLOCK;
            let mut done = 0;
            while done < o.len() / dh {
                let row = row0 + done;
                let (head, qi) = (row / nq, row % nq);
                let rows = (o.len() / dh - done).min(nq - qi);
                let qb = &q[(head * nq + qi) * dh..][..rows * dh];
                let kh = &k[head * nk * dh..][..nk * dh];
                let vh = &v[head * nk * dh..][..nk * dh];
                let s = &mut scores[..rows * nk];
                if let Products::Packed(packed) = products {
                    super::bf16::pairs_into(qb, rows, dh, pairs);
                    super::bf16::product(pairs, rows, dh, &packed[head].0, nk, s);
                    s.iter_mut().for_each(|x| *x *= scale);
                } else {
                    // SAFETY: row-major (rows x dh) * (dh x nk, i.e. k transposed) -> (rows x nk).
                    unsafe {
                        gemm::gemm(
                            rows,
                            nk,
                            dh,
                            s.as_mut_ptr(),
                            1,
                            nk as isize,
                            false,
                            qb.as_ptr(),
                            1,
                            dh as isize,
                            kh.as_ptr(),
                            dh as isize,
                            1,
                            0.0,
                            scale,
                            false,
                            false,
                            false,
                            Parallelism::None,
                        );
                    }
                }
                let mut sums = [0.0f32; BLOCK];
                for (srow, sum) in s.chunks_exact_mut(nk).zip(sums.iter_mut()) {
                    *sum = exp_row(srow);
                }
                let ob = &mut o[done * dh..][..rows * dh];
                match products {
                    Products::Packed(packed) => {
                        super::bf16::pairs_into(s, rows, nk, pairs);
                        super::bf16::product(pairs, rows, nk, &packed[head].1, dh, ob);
                    }
                    _ => {
                        if matches!(products, Products::Rounded) {
                            super::with_avx2(|| s.iter_mut().for_each(|x| *x = super::bf16::round(*x)));
                        }
                        // SAFETY: row-major (rows x nk) * (nk x dh) -> (rows x dh).
                        unsafe {
                            gemm::gemm(
                                rows,
                                dh,
                                nk,
                                ob.as_mut_ptr(),
                                1,
                                dh as isize,
                                false,
                                s.as_ptr(),
                                1,
                                nk as isize,
                                vh.as_ptr(),
                                1,
                                dh as isize,
                                0.0,
                                1.0,
                                false,
                                false,
                                false,
                                Parallelism::None,
                            );
                        }
                    }
                }
                for (orow, sum) in ob.chunks_exact_mut(dh).zip(&sums) {
                    let inv = 1.0 / sum;
                    orow.iter_mut().for_each(|x| *x *= inv);
                }
                done += rows;
            }
        },
    );
    out
}

/// `row <- exp(row - max(row))`, returning the sum (the softmax before normalisation, which
/// is applied to the output rows instead); on AVX2 + FMA when the CPU has them.
fn exp_row(row: &mut [f32]) -> f32 {
    super::with_avx2(|| exp_row_lanes(row))
}

/// Written over 8 independent lanes so the compiler vectorises the max, the exponentials and
/// the sum (a single running max or sum is a serial dependency it may not reorder).
#[inline(always)]
fn exp_row_lanes(row: &mut [f32]) -> f32 {
    const L: usize = 8;
    let mut m = [f32::NEG_INFINITY; L];
    let mut chunks = row.chunks_exact(L);
    for c in &mut chunks {
        for i in 0..L {
            m[i] = if c[i] > m[i] { c[i] } else { m[i] };
        }
    }
    let mut max = m.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    max = chunks.remainder().iter().copied().fold(max, f32::max);
    let mut s = [0.0f32; L];
    let mut chunks = row.chunks_exact_mut(L);
    for c in &mut chunks {
        for i in 0..L {
            c[i] = exp_approx(c[i] - max);
            s[i] += c[i];
        }
    }
    let mut sum: f32 = s.iter().sum();
    for x in chunks.into_remainder() {
        *x = exp_approx(*x - max);
        sum += *x;
    }
    sum
}

/// `e^x` for `x <= 0` to about 2 ulp, branch-free so the softmax loop vectorises
/// (Cody-Waite range reduction, degree-6 polynomial, exponent bits for `2^n`; rounding to
/// the nearest integer by the 1.5 * 2^23 trick, which needs no SSE4.1).
#[inline(always)]
pub(crate) fn exp_approx(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0;
    let x = x.max(-87.0);
    let k = x * std::f32::consts::LOG2_E + ROUND;
    let n = k - ROUND;
    let r = x - n * 0.693_145_75 - n * 1.428_606_8e-6;
    let p = 1.0
        + r * (1.0 + r * (0.5 + r * (0.166_666_67 + r * (0.041_666_668 + r * (0.008_333_334 + r * 0.001_388_889)))));
    // k's low mantissa bits hold n (two's complement): 2^n without a float-to-int conversion.
    let n_bits = k.to_bits().wrapping_sub(ROUND.to_bits());
    p * f32::from_bits(n_bits.wrapping_add(127) << 23)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_is_accurate() {
        for i in 0..=86_000 {
            let x = -(i as f32) * 1e-3;
            let (got, want) = (exp_approx(x) as f64, (x as f64).exp());
            assert!((got - want).abs() <= 4e-7 * want, "exp({x}) = {got}, want {want}");
        }
    }

    /// Softmax attention in f64 of one head's row.
    fn exact_row(
        q: &[f32],
        k: &[f32],
        v: &[f32],
        (h, i): (usize, usize),
        (nq, nk, dh): (usize, usize, usize),
    ) -> Vec<f64> {
        let sc: Vec<f64> = (0..nk)
            .map(|j| {
                (0..dh).map(|d| q[(h * nq + i) * dh + d] as f64 * k[(h * nk + j) * dh + d] as f64).sum::<f64>()
                    / (dh as f64).sqrt()
            })
            .collect();
        let m = sc.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let e: Vec<f64> = sc.iter().map(|x| (x - m).exp()).collect();
        let z: f64 = e.iter().sum();
        (0..dh).map(|d| (0..nk).map(|j| e[j] / z * v[(h * nk + j) * dh + d] as f64).sum()).collect()
    }

    #[test]
    fn bf16_attention_stays_near_exact_and_its_kernels_agree() {
        // Values within +-3: bf16's 8-bit mantissa moves the output by about 1% of them.
        for &(bh, nq, nk, dh) in &[(3, 70, 50, 8), (2, 128, 129, 16), (1, 5, 200, 64)] {
            let (q, k, v) = (
                crate::cpu::test_values(bh * nq * dh, 1, 3.0),
                crate::cpu::test_values(bh * nk * dh, 2, 3.0),
                crate::cpu::test_values(bh * nk * dh, 3, 3.0),
            );
            let got = attention_with(&q, &k, &v, bh, nq, nk, dh, true);
            let f32_out = attention(&q, &k, &v, bh, nq, nk, dh);
            let round = crate::cpu::bf16::rounded;
            let rounded = run(&round(&q), &round(&k), &round(&v), (bh, nq, nk, dh), &Products::Rounded);
            let (mut worst, mut moved, mut apart) = (0.0f64, 0.0f64, 0.0f64);
            for h in 0..bh {
                for i in 0..nq {
                    for (d, want) in exact_row(&q, &k, &v, (h, i), (nq, nk, dh)).into_iter().enumerate() {
                        let at = (h * nq + i) * dh + d;
                        worst = worst.max((got[at] as f64 - want).abs());
                        moved = moved.max((got[at] - f32_out[at]).abs() as f64);
                        apart = apart.max((got[at] - rounded[at]).abs() as f64);
                    }
                }
            }
            eprintln!(
                "({bh},{nq},{nk},{dh}): bf16 {worst:.2e} off the exact, {moved:.2e} off f32, paths {apart:.2e} apart"
            );
            assert!(worst < 0.05, "({bh},{nq},{nk},{dh}) bf16 attention {worst} off the exact");
            assert!(moved > 1e-4, "({bh},{nq},{nk},{dh}) bf16 gave f32's output");
            // The AVX-512 BF16 kernel and the rounded values through the f32 one: the same
            // operands, sums in another order (an exponential may round to the next bf16).
            // Without AVX-512 BF16 both are the second, and there is nothing to compare.
            if crate::cpu::bf16::native() {
                assert!(apart < 1e-4, "({bh},{nq},{nk},{dh}) the two bf16 paths {apart} apart");
            } else {
                eprintln!("no AVX-512 BF16 here: one bf16 path only, the kernels not compared");
            }
        }
    }

    #[test]
    fn matches_naive_attention() {
        let mut seed = 0u64;
        let mut rnd = |n: usize| {
            seed += 1;
            crate::cpu::test_values(n, seed, 3.0)
        };
        // nq not a multiple of the block, nq != nk (cross-attention), several heads.
        for &(bh, nq, nk, dh) in &[(3, 70, 50, 8), (2, 128, 128, 16), (1, 5, 200, 4)] {
            let (q, k, v) = (rnd(bh * nq * dh), rnd(bh * nk * dh), rnd(bh * nk * dh));
            let got = attention(&q, &k, &v, bh, nq, nk, dh);
            for h in 0..bh {
                for i in 0..nq {
                    let sc: Vec<f64> = (0..nk)
                        .map(|j| {
                            (0..dh)
                                .map(|d| q[(h * nq + i) * dh + d] as f64 * k[(h * nk + j) * dh + d] as f64)
                                .sum::<f64>()
                                / (dh as f64).sqrt()
                        })
                        .collect();
                    let m = sc.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    let e: Vec<f64> = sc.iter().map(|x| (x - m).exp()).collect();
                    let z: f64 = e.iter().sum();
                    for d in 0..dh {
                        let want: f64 = (0..nk).map(|j| e[j] / z * v[(h * nk + j) * dh + d] as f64).sum();
                        let g = got[(h * nq + i) * dh + d] as f64;
                        assert!((g - want).abs() < 1e-5, "bh {h} row {i} dim {d}: {g} vs {want}");
                    }
                }
            }
        }
    }
}
