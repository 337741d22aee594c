//! Linear layers with bf16 products (`--precision bf16` on the CPU): the weight stored as
//! bfloat16, the input rounded to bfloat16 (nearest even), each product exact and summed in
//! f32, as PyTorch's `set_float32_matmul_precision("medium")` does (attention's products take
//! the same kernel, [`super::attention::attention_with`]); everything else stays f32.
//! On CPUs with AVX-512 BF16 (AMD Zen 4 and later, Intel Cooper Lake / Sapphire Rapids and
//! later) `VDPBF16PS` does two such products per f32 lane, twice the multiplies of an f32 FMA;
//! elsewhere the rounded values are multiplied by the f32 kernel (the same sums in another
//! order, no faster than f32).

use super::SendPtr;
use rayon::prelude::*;

/// Columns of a packed panel (four 16-lane registers).
const NR: usize = 64;
/// Rows of a tile.
const MR: usize = 6;
/// Input pairs per cache block (the panel's block: 64 KB).
const KC: usize = 256;
/// Rows per rayon task (a multiple of `MR`).
const ROWS_PER_TASK: usize = 16 * MR;

/// bf16 bits of `x`, rounded to nearest even, NaN kept NaN (as `half` rounds; branch-free,
/// so that a row's conversion vectorises).
#[inline(always)]
fn bf16_bits(x: f32) -> u16 {
    let b = x.to_bits();
    let rounded = b.wrapping_add(0x7fff + ((b >> 16) & 1)) >> 16;
    let nan = (b & 0x7fff_ffff) > 0x7f80_0000;
    (if nan { (b >> 16) | 0x40 } else { rounded }) as u16
}

/// Two bf16 values in one word, `lo` in the low half: the operand layout of `VDPBF16PS`.
fn pair(lo: f32, hi: f32) -> u32 {
    bf16_bits(lo) as u32 | (bf16_bits(hi) as u32) << 16
}

/// The f32 values of a word's two bf16 halves `(lo, hi)`.
fn unpair(w: u32) -> (f32, f32) {
    (f32::from_bits(w << 16), f32::from_bits(w & 0xffff_0000))
}

/// Whether this CPU runs the AVX-512 BF16 kernel.
pub fn native() -> bool {
    #[cfg(target_arch = "x86_64")]
    return is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512bf16");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// How a [`Bf16Weight`] is stored.
#[derive(Debug, Clone)]
enum Store {
    /// For the AVX-512 BF16 kernel: panels of [`NR`] output columns, in each the input
    /// features in pairs (`k` padded to even, columns past `n` zero).
    Packed(Vec<u32>),
    /// The bf16 values widened to f32, `(in, out)` row-major, for the f32 kernel.
    Widened(Vec<f32>),
}

/// A linear layer's `(in, out)` weight rounded to bf16, stored for this CPU's kernel.
#[derive(Debug, Clone)]
pub struct Bf16Weight {
    store: Store,
    /// Input features.
    pub k: usize,
    /// Output features.
    pub n: usize,
}

impl Bf16Weight {
    /// Rounds an `(in, out)` row-major f32 weight to bf16, packed for `VDPBF16PS` where the
    /// CPU has it.
    pub fn new(w: &[f32], k: usize, n: usize) -> Self {
        Self::stored(w, k, n, native())
    }

    /// [`new`](Self::new), packed (the CPU must have AVX-512 BF16 to multiply it) or widened.
    pub(crate) fn stored(w: &[f32], k: usize, n: usize, packed: bool) -> Self {
        assert_eq!(w.len(), k * n, "bf16 weight size mismatch");
        if !packed {
            return Self { store: Store::Widened(rounded(w)), k, n };
        }
        let mut packed = Vec::new();
        pack(w, k, n, (n, 1), &mut packed);
        Self { store: Store::Packed(packed), k, n }
    }

    /// Input feature pairs.
    fn kp(&self) -> usize {
        self.k.div_ceil(2)
    }

    /// The weight as f32 `(in, out)` row-major (the bf16 values, exactly).
    pub fn to_f32(&self) -> Vec<f32> {
        let (k, n, kp) = (self.k, self.n, self.kp());
        let packed = match &self.store {
            Store::Widened(w) => return w.clone(),
            Store::Packed(p) => p,
        };
        let mut w = vec![0.0f32; k * n];
        for col in 0..n {
            let (panel, c) = (col / NR, col % NR);
            for p in 0..kp {
                let (lo, hi) = unpair(packed[(panel * kp + p) * NR + c]);
                w[2 * p * n + col] = lo;
                if 2 * p + 1 < k {
                    w[(2 * p + 1) * n + col] = hi;
                }
            }
        }
        w
    }

    /// `y (rows x out) [+]= x (rows x in) * W`, `x` rounded to bf16 first; `accumulate` adds to
    /// what `y` holds (a bias), else overwrites it.
    pub fn matmul(&self, x: &[f32], rows: usize, y: &mut [f32], accumulate: bool) {
        let (k, n) = (self.k, self.n);
        assert_eq!(x.len(), rows * k, "bf16 matmul input size mismatch");
        assert_eq!(y.len(), rows * n, "bf16 matmul output size mismatch");
        if k == 0 {
            if !accumulate {
                y.fill(0.0);
            }
            return;
        }
        match &self.store {
            Store::Packed(packed) => self.matmul_packed(packed, x, rows, y, accumulate),
            Store::Widened(w) => {
                super::gemm_by_columns(&rounded(x), w, (n, 1), y, n, (rows, k, n), accumulate, 64);
            }
        }
    }

    /// The product on `VDPBF16PS`, over [`Store::Packed`] panels, in tasks of (panel, rows).
    fn matmul_packed(&self, packed: &[u32], x: &[f32], rows: usize, y: &mut [f32], accumulate: bool) {
        let (k, n, kp) = (self.k, self.n, self.kp());
        let xp = pairs(x, rows, k);
        let (panels, chunks) = (n.div_ceil(NR), rows.next_multiple_of(MR).div_ceil(ROWS_PER_TASK));
        let y_ptr = SendPtr(y.as_mut_ptr());
        (0..panels * chunks).into_par_iter().for_each(|t| {
            let (panel, chunk) = (t / chunks, t % chunks);
            let r = chunk * ROWS_PER_TASK..((chunk + 1) * ROWS_PER_TASK).min(rows);
            // SAFETY: `y` holds rows x n values; this task writes rows r of panel's columns
            // only, disjoint from every other task's (panel, chunk).
            unsafe {
                panel_rows(&xp, kp, r, &packed[panel * kp * NR..(panel + 1) * kp * NR], panel, n, &y_ptr, accumulate)
            };
        });
    }
}

/// `x (rows x k, row-major)` rounded to bf16 pairs: `rows` padded to whole tiles with zero
/// rows, each row `k.div_ceil(2)` words (an odd `k`'s last paired with zero).
fn pairs(x: &[f32], rows: usize, k: usize) -> Vec<u32> {
    let kp = k.div_ceil(2);
    let mut xp = vec![0u32; rows.next_multiple_of(MR) * kp];
    if kp == 0 {
        return xp;
    }
    xp.par_chunks_mut(kp).zip(x.par_chunks(k)).for_each(|(dst, row)| pair_row(row, dst));
    xp
}

/// [`pairs`] on this thread, into `dst` (for small blocks, where a parallel split costs more
/// than it saves).
pub(crate) fn pairs_into(x: &[f32], rows: usize, k: usize, dst: &mut Vec<u32>) {
    let kp = k.div_ceil(2);
    dst.clear();
    dst.resize(rows.next_multiple_of(MR) * kp, 0);
    if kp == 0 {
        return;
    }
    dst.chunks_exact_mut(kp).zip(x[..rows * k].chunks_exact(k)).for_each(|(d, row)| pair_row(row, d));
}

/// One row of `k` values into `k.div_ceil(2)` pair words.
fn pair_row(row: &[f32], dst: &mut [u32]) {
    super::with_avx2(|| {
        for (d, two) in dst.iter_mut().zip(row.chunks_exact(2)) {
            *d = pair(two[0], two[1]);
        }
    });
    if row.len() % 2 == 1 {
        dst[row.len() / 2] = pair(row[row.len() - 1], 0.0);
    }
}

/// `y (rows x n, contiguous) = xp (rows x k, from [`pairs_into`]) * packed (k x n, from
/// [`pack`])` on `VDPBF16PS`, on this thread. The CPU must have AVX-512 BF16.
pub(crate) fn product(xp: &[u32], rows: usize, k: usize, packed: &[u32], n: usize, y: &mut [f32]) {
    let kp = k.div_ceil(2);
    assert!(xp.len() >= rows.next_multiple_of(MR) * kp, "bf16 product input too small");
    assert!(packed.len() >= n.div_ceil(NR) * kp * NR, "bf16 product weight too small");
    assert!(y.len() >= rows * n, "bf16 product output too small");
    if kp == 0 {
        y[..rows * n].fill(0.0);
        return;
    }
    let y_ptr = SendPtr(y.as_mut_ptr());
    for panel in 0..n.div_ceil(NR) {
        // SAFETY: the asserts above; this thread alone writes y.
        unsafe {
            panel_rows(xp, kp, 0..rows, &packed[panel * kp * NR..(panel + 1) * kp * NR], panel, n, &y_ptr, false)
        };
    }
}

/// Packs `w (k x n)`, element `(i, j)` at `w[i * rs + j * cs]` (row-major, or a transposed
/// view), into `dst` as bf16 panels of [`NR`] columns, in each the `k` rows in pairs (`k`
/// padded to even, columns past `n` zero); the panels on rayon.
pub(crate) fn pack(w: &[f32], k: usize, n: usize, (rs, cs): (usize, usize), dst: &mut Vec<u32>) {
    let (kp, panels) = (k.div_ceil(2), n.div_ceil(NR));
    dst.clear();
    dst.resize(panels * kp * NR, 0);
    if kp == 0 {
        return;
    }
    dst.par_chunks_mut(kp * NR).enumerate().for_each(|(panel, dst)| {
        let (j0, cols) = (panel * NR, NR.min(n - panel * NR));
        super::with_avx2(|| {
            for (p, d) in dst.chunks_exact_mut(NR).enumerate() {
                let (lo, hi) = (2 * p * rs, 2 * p + 1 < k);
                let at = |i: usize, c: usize| if i == lo || hi { w[i + (j0 + c) * cs] } else { 0.0 };
                if cs == 1 && hi {
                    // Contiguous rows (a weight): slices, which vectorise.
                    let (l, h) = (&w[lo + j0..][..cols], &w[lo + rs + j0..][..cols]);
                    d.iter_mut().zip(l).zip(h).for_each(|((d, &l), &h)| *d = pair(l, h));
                } else {
                    d[..cols].iter_mut().enumerate().for_each(|(c, d)| *d = pair(at(lo, c), at(lo + rs, c)));
                }
            }
        });
    });
}

/// Rows `r` (starting at a whole tile) of one panel's columns of `y (.. x n)`: `xp`'s pairs
/// (`kp` words a row, padded to whole tiles) times the panel `b` (`kp` rows of NR words), in
/// groups of [`ROWS_PER_TASK`] rows and blocks of [`KC`] pairs, so the panel's block stays in
/// cache across a group's tiles.
///
/// # Safety
/// `y` must hold `r.end` rows of `n` values, no other thread may touch those rows of this
/// panel's columns, and the CPU must have AVX-512 BF16 ([`native`]).
#[allow(clippy::too_many_arguments)]
unsafe fn panel_rows(
    xp: &[u32],
    kp: usize,
    r: std::ops::Range<usize>,
    b: &[u32],
    panel: usize,
    n: usize,
    y: &SendPtr,
    accumulate: bool,
) {
    assert!(native(), "the AVX-512 BF16 kernel on a CPU without it");
    let (c0, cols) = (panel * NR, NR.min(n - panel * NR));
    assert!(xp.len() >= r.end.next_multiple_of(MR) * kp && b.len() >= kp * NR, "bf16 panel out of bounds");
    // The tiles of up to ROWS_PER_TASK rows at a time, on the stack (24 KB): no allocation in
    // a call that attention makes per block and panel.
    let mut tiles = [[[0.0f32; NR]; MR]; ROWS_PER_TASK / MR];
    for g0 in r.clone().step_by(ROWS_PER_TASK) {
        let g1 = (g0 + ROWS_PER_TASK).min(r.end);
        let tiles = &mut tiles[..(g1 - g0).div_ceil(MR)];
        for p0 in (0..kp).step_by(KC) {
            let len = KC.min(kp - p0);
            let b = &b[p0 * NR..(p0 + len) * NR];
            for (i, tile) in tiles.iter_mut().enumerate() {
                let a = &xp[(g0 + i * MR) * kp + p0..];
                #[cfg(target_arch = "x86_64")]
                // SAFETY: the CPU has the features (asserted); `a` starts MR rows of kp words
                // (the block's len words of each read, inside xp by the assert) and `b` holds
                // len pairs of NR columns.
                unsafe {
                    tile_avx512(a.as_ptr(), kp, b.as_ptr(), len, tile, p0 > 0)
                };
                #[cfg(not(target_arch = "x86_64"))]
                unreachable!("packed bf16 weights off x86-64 ({a:?}, {b:?}, {tile:?})");
            }
        }
        for (i, tile) in tiles.iter().enumerate() {
            let r0 = g0 + i * MR;
            for (rr, row) in tile.iter().enumerate().take(g1.saturating_sub(r0).min(MR)) {
                // SAFETY: row r0 + rr < r.end and columns c0..c0 + cols <= n, ours by the contract.
                let dst = unsafe { std::slice::from_raw_parts_mut(y.0.add((r0 + rr) * n + c0), cols) };
                if accumulate {
                    dst.iter_mut().zip(row).for_each(|(d, v)| *d += v);
                } else {
                    dst.copy_from_slice(&row[..cols]);
                }
            }
        }
    }
}

/// `v` rounded to bf16, as f32.
#[inline(always)]
pub(crate) fn round(v: f32) -> f32 {
    f32::from_bits((bf16_bits(v) as u32) << 16)
}

/// Every value of `x` rounded to bf16, as f32 (on rayon).
pub(crate) fn rounded(x: &[f32]) -> Vec<f32> {
    let mut out = vec![0.0f32; x.len()];
    out.par_chunks_mut(4096)
        .zip(x.par_chunks(4096))
        .for_each(|(d, s)| super::with_avx2(|| d.iter_mut().zip(s).for_each(|(d, &v)| *d = round(v))));
    out
}

/// One tile on `VDPBF16PS`: `a` points at MR rows of `a_rs` words (the block's pairs first),
/// `b` at `len` rows of NR pair words; adds to `tile` when `load`, else overwrites it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn tile_avx512(a: *const u32, a_rs: usize, b: *const u32, len: usize, tile: &mut [[f32; NR]; MR], load: bool) {
    use std::arch::x86_64::*;
    use std::mem::transmute;
    let mut acc = [[_mm512_setzero_ps(); NR / 16]; MR];
    if load {
        for (r, acc_r) in acc.iter_mut().enumerate() {
            for (q, v) in acc_r.iter_mut().enumerate() {
                *v = _mm512_loadu_ps(tile[r].as_ptr().add(16 * q));
            }
        }
    }
    for p in 0..len {
        let bp = b.add(p * NR) as *const f32;
        let mut bv: [__m512bh; NR / 16] = [transmute::<__m512, __m512bh>(_mm512_setzero_ps()); NR / 16];
        for (q, v) in bv.iter_mut().enumerate() {
            *v = transmute::<__m512, __m512bh>(_mm512_loadu_ps(bp.add(16 * q)));
        }
        for (r, acc_r) in acc.iter_mut().enumerate() {
            let av = transmute::<__m512i, __m512bh>(_mm512_set1_epi32(*a.add(r * a_rs + p) as i32));
            for (q, acc_rq) in acc_r.iter_mut().enumerate() {
                *acc_rq = _mm512_dpbf16_ps(*acc_rq, av, bv[q]);
            }
        }
    }
    for (r, acc_r) in acc.iter().enumerate() {
        for (q, v) in acc_r.iter().enumerate() {
            _mm512_storeu_ps(tile[r].as_mut_ptr().add(16 * q), *v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `x W` in f64 over the bf16-rounded operands (independent of the packing and kernels).
    fn reference(x: &[f32], w: &[f32], rows: usize, k: usize, n: usize) -> Vec<f64> {
        let r16 = |v: f32| half::bf16::from_f32(v).to_f32() as f64;
        let mut y = vec![0.0f64; rows * n];
        for r in 0..rows {
            for i in 0..k {
                let a = r16(x[r * k + i]);
                for j in 0..n {
                    y[r * n + j] += a * r16(w[i * n + j]);
                }
            }
        }
        y
    }

    #[test]
    fn products_of_the_rounded_operands() {
        // Odd sizes: a tail of rows (not whole tiles), of columns (not whole panels) and an odd
        // input width (an unpaired last feature).
        for &(rows, k, n) in &[(1, 1, 1), (7, 5, 3), (13, 64, 70), (100, 257, 130), (6, 1024, 64), (0, 4, 3), (3, 0, 5)]
        {
            let x = crate::cpu::test_values(rows * k, 11 + k as u64, 1.0);
            let w = crate::cpu::test_values(k * n, 23 + n as u64, 1.0);
            let bias = crate::cpu::test_values(n, 5, 1.0);
            let want = reference(&x, &w, rows, k, n);
            let stores: &[bool] = if native() { &[false, true] } else { &[false] };
            for &fast in stores {
                let weight = Bf16Weight::stored(&w, k, n, fast);
                let mut y = vec![f32::NAN; rows * n];
                weight.matmul(&x, rows, &mut y, false);
                let mut yb: Vec<f32> = (0..rows).flat_map(|_| bias.iter().copied()).collect();
                weight.matmul(&x, rows, &mut yb, true);
                for r in 0..rows {
                    for j in 0..n {
                        // f32 sums of k exact products of magnitude <= 1.
                        let tol = 1e-6 * (k as f64).max(8.0);
                        let (g, gb, e) = (y[r * n + j] as f64, yb[r * n + j] as f64, want[r * n + j]);
                        assert!((g - e).abs() < tol, "({rows},{k},{n}) fast {fast} [{r},{j}]: {g} vs {e}");
                        assert!((gb - e - bias[j] as f64).abs() < tol, "bias ({rows},{k},{n}) [{r},{j}]");
                    }
                }
            }
            // Against the f32 product the error is bf16's: about 2^-8 relative per operand.
            let exact: Vec<f64> = (0..rows * n)
                .map(|i| (0..k).map(|t| x[i / n * k + t] as f64 * w[t * n + i % n] as f64).sum())
                .collect();
            let worst = want.iter().zip(&exact).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(worst < 0.01 * (k as f64).sqrt() + 1e-3, "({rows},{k},{n}) bf16 error {worst}");
        }
    }

    #[test]
    fn rounding_is_halfs() {
        // 1 + 2^-8 and 1 + 3 * 2^-8 lie halfway between two bf16 values: ties go to the even one.
        let halfway = [f32::from_bits(0x3f80_8000), f32::from_bits(0x3f81_8000)];
        let specials = [0.0f32, -0.0, 1.0, 3.4e38, -3.4e38, 1e-40, f32::INFINITY].into_iter().chain(halfway);
        let values = crate::cpu::test_values(10000, 9, 1e3).into_iter().chain(specials);
        for v in values.chain([f32::NAN, f32::from_bits(0x7f80_0001), f32::from_bits(0xffc0_0001)]) {
            let got = bf16_bits(v);
            let want = half::bf16::from_f32(v);
            if v.is_nan() {
                assert!(half::bf16::from_bits(got).is_nan(), "{:#x} -> {got:#x}", v.to_bits());
            } else {
                assert_eq!(got, want.to_bits(), "{v}");
            }
        }
    }

    #[test]
    fn packing_keeps_the_rounded_weight() {
        let (k, n) = (9, 70);
        let w = crate::cpu::test_values(k * n, 3, 2.0);
        for packed in [false, true] {
            let back = Bf16Weight::stored(&w, k, n, packed).to_f32();
            for (a, b) in w.iter().zip(&back) {
                assert_eq!(half::bf16::from_f32(*a).to_f32(), *b);
                assert!((a - b).abs() <= a.abs() / 256.0, "{a} -> {b}");
            }
        }
    }
}
