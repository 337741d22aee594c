//! 3x3, stride 1, padding 1 convolution by Winograd F(4x4, 3x3) on raw `f32` buffers.
//!
//! Each 4x4 output tile is computed from a 6x6 input patch with 36 multiplies per
//! (input, output) channel pair instead of 144: the input patches and the kernels are
//! transformed once (`B^T d B`, `G g G^T`), the 36 transformed planes are multiplied as 36
//! independent matrix products on the `gemm` crate, and the products are transformed back
//! (`A^T m A`). The transforms are Lavin and Gray's (interpolation points 0, +-1, +-2, inf);
//! their coefficients are small, so fp32 stays within a few ulps of direct convolution times
//! the input's scale (tested against a direct loop). Kernels wider than 256x256 channels use
//! F(2x2, 3x3) (16 products per 4 outputs; [`WinogradKernel::new`] says why).
//!
//! Work is split into bands of tile rows so memory stays bounded and the bands run in
//! parallel on rayon, each writing its rows of the output in place; the transformed inputs and
//! products live in per-thread scratch buffers reused from band to band.

use gemm::Parallelism;
use rayon::prelude::*;

/// The transforms of F(M x M, 3 x 3): `N = M + 2` input rows per tile.
#[derive(Debug)]
struct Transforms<const M: usize, const N: usize> {
    /// `B^T` (N x N), applied to the input patch's rows, then its columns.
    bt: [[f32; N]; N],
    /// `G` (N x 3), applied to the kernel.
    g: [[f64; 3]; N],
    /// `A^T` (M x N), applied to the products.
    at: [[f32; N]; M],
}

/// F(4x4, 3x3).
const F4: Transforms<4, 6> = Transforms {
    bt: [
        [4.0, 0.0, -5.0, 0.0, 1.0, 0.0],
        [0.0, -4.0, -4.0, 1.0, 1.0, 0.0],
        [0.0, 4.0, -4.0, -1.0, 1.0, 0.0],
        [0.0, -2.0, -1.0, 2.0, 1.0, 0.0],
        [0.0, 2.0, -1.0, -2.0, 1.0, 0.0],
        [0.0, 4.0, 0.0, -5.0, 0.0, 1.0],
    ],
    g: [
        [1.0 / 4.0, 0.0, 0.0],
        [-1.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0],
        [-1.0 / 6.0, 1.0 / 6.0, -1.0 / 6.0],
        [1.0 / 24.0, 1.0 / 12.0, 1.0 / 6.0],
        [1.0 / 24.0, -1.0 / 12.0, 1.0 / 6.0],
        [0.0, 0.0, 1.0],
    ],
    at: [
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
        [0.0, 1.0, -1.0, 2.0, -2.0, 0.0],
        [0.0, 1.0, 1.0, 4.0, 4.0, 0.0],
        [0.0, 1.0, -1.0, 8.0, -8.0, 1.0],
    ],
};

/// F(2x2, 3x3).
const F2: Transforms<2, 4> = Transforms {
    bt: [[1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 1.0, 0.0], [0.0, -1.0, 1.0, 0.0], [0.0, 1.0, 0.0, -1.0]],
    g: [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]],
    at: [[1.0, 1.0, 1.0, 0.0], [0.0, 1.0, -1.0, -1.0]],
};

/// Output tile size of a [`WinogradKernel`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tiles {
    /// F(2x2, 3x3): 16 products per 4 outputs.
    F2,
    /// F(4x4, 3x3): 36 products per 16 outputs.
    F4,
}

/// Kernels of a 3x3 convolution in the Winograd domain: `N * N` matrices `(out, in)`.
#[derive(Debug, Clone)]
pub struct WinogradKernel {
    /// `[N * N][out][in]`, plane `xi = N * row + col` of `G g G^T`.
    u: Vec<f32>,
    tiles: Tiles,
    /// Output channels.
    pub out_ch: usize,
    /// Input channels.
    pub in_ch: usize,
}

impl WinogradKernel {
    /// Transforms PyTorch-layout `(out, in, 3, 3)` weights: F(4x4, 3x3) for kernels of at most
    /// 256x256 channels, F(2x2, 3x3) beyond. F(4x4) kernels take 4x the weights' memory
    /// (F(2x2): 16/9), and the wider ones, a DPT's input projections (512-1024 channels in),
    /// run at 1/8-1/32 of the image, where F(4x4) saves little time.
    pub fn new(weight: &[f32], out_ch: usize, in_ch: usize) -> Self {
        let tiles = if out_ch * in_ch <= 256 * 256 { Tiles::F4 } else { Tiles::F2 };
        Self::with_tiles(weight, out_ch, in_ch, tiles)
    }

    /// Transforms PyTorch-layout `(out, in, 3, 3)` weights for the given tile size.
    pub fn with_tiles(weight: &[f32], out_ch: usize, in_ch: usize, tiles: Tiles) -> Self {
        assert_eq!(weight.len(), out_ch * in_ch * 9, "3x3 kernel size mismatch");
        let u = match tiles {
            Tiles::F2 => kernel_transform(&F2, weight, out_ch, in_ch),
            Tiles::F4 => kernel_transform(&F4, weight, out_ch, in_ch),
        };
        Self { u, tiles, out_ch, in_ch }
    }

    /// Convolves one image `(in, h, w)` into `(out, h, w)`, zero padding 1, adding `bias`.
    pub fn forward(&self, x: &[f32], h: usize, w: usize, bias: Option<&[f32]>) -> Vec<f32> {
        assert_eq!(x.len(), self.in_ch * h * w, "input size mismatch");
        match self.tiles {
            Tiles::F2 => self.run(&F2, x, h, w, bias),
            Tiles::F4 => self.run(&F4, x, h, w, bias),
        }
    }

    fn run<const M: usize, const N: usize>(
        &self,
        tf: &Transforms<M, N>,
        x: &[f32],
        h: usize,
        w: usize,
        bias: Option<&[f32]>,
    ) -> Vec<f32> {
        let (cin, cout) = (self.in_ch, self.out_ch);
        let th = h.div_ceil(M);
        // Tiles per row, padded to whole SIMD groups (the padding tiles are computed, unused).
        let tw = w.div_ceil(M).next_multiple_of(LANES);
        // Bands of tile rows with ~2048 output pixels each (512 tiles of F(2x2), 128 of
        // F(4x4)): products large enough to run efficiently, transformed planes small enough
        // to stay in cache.
        let rows_per_band = (2048 / (M * M) / tw).clamp(1, th);
        let bands: Vec<(usize, usize)> =
            (0..th).step_by(rows_per_band).map(|r0| (r0, rows_per_band.min(th - r0))).collect();
        let threads = rayon::current_num_threads();
        let inner = if bands.len() >= threads { Parallelism::None } else { Parallelism::Rayon(0) };
        let mut y = vec![0.0f32; cout * h * w];
        // Each band writes only its own rows `M * r0 ..` of every channel: disjoint ranges.
        let out = super::SendPtr(y.as_mut_ptr());
        bands.par_iter().for_each(|&(r0, nr)| {
            let nt = nr * tw;
            let band = Band { h, w, r0, nr, tw };
            with_scratch(N * N * cin * nt, N * N * cout * nt, |v, m| {
                super::with_avx2(|| input_transform(tf, x, cin, &band, v));
                for xi in 0..N * N {
                    let lhs = &self.u[xi * cout * cin..][..cout * cin];
                    let rhs = &v[xi * cin * nt..][..cin * nt];
                    let dst = &mut m[xi * cout * nt..][..cout * nt];
                    // SAFETY: the three slices hold exactly (cout x cin), (cin x nt) and
                    // (cout x nt) row-major matrices as described by the strides below.
                    unsafe {
                        gemm::gemm(
                            cout,
                            nt,
                            cin,
                            dst.as_mut_ptr(),
                            1,
                            nt as isize,
                            false,
                            lhs.as_ptr(),
                            1,
                            cin as isize,
                            rhs.as_ptr(),
                            1,
                            nt as isize,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            inner,
                        );
                    }
                }
                super::with_avx2(|| output_transform(tf, m, cout, &band, bias, &out));
            });
        });
        y
    }
}

thread_local! {
    /// Per-thread transformed inputs and products, reused across bands and convolutions (every
    /// element is written before it is read), so they are not zeroed and faulted in anew.
    static SCRATCH: std::cell::RefCell<(Vec<f32>, Vec<f32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// Runs `f` on scratch buffers of `nv` and `nm` values: the thread's own, or fresh ones when
/// they are in use (a band's nested product can steal another band onto the same thread).
fn with_scratch(nv: usize, nm: usize, f: impl FnOnce(&mut [f32], &mut [f32])) {
    SCRATCH.with(|s| match s.try_borrow_mut() {
        Ok(mut s) => {
            let (v, m) = &mut *s;
            for (buf, n) in [(&mut *v, nv), (&mut *m, nm)] {
                if buf.len() < n {
                    buf.resize(n, 0.0);
                }
            }
            f(&mut v[..nv], &mut m[..nm]);
        }
        Err(_) => f(&mut vec![0.0; nv], &mut vec![0.0; nm]),
    })
}

/// `G g G^T` of every `(out, in)` kernel, in f64 (the F(4x4) coefficients are not exact in
/// binary), into `[N * N][out][in]`.
fn kernel_transform<const M: usize, const N: usize>(
    tf: &Transforms<M, N>,
    weight: &[f32],
    out_ch: usize,
    in_ch: usize,
) -> Vec<f32> {
    let plane = out_ch * in_ch;
    let mut u = vec![0.0f32; N * N * plane];
    for o in 0..out_ch {
        for i in 0..in_ch {
            let k = &weight[(o * in_ch + i) * 9..][..9];
            // G g: (N x 3).
            let mut t = [[0.0f64; 3]; N];
            for (tr, gr) in t.iter_mut().zip(&tf.g) {
                for (c, tv) in tr.iter_mut().enumerate() {
                    *tv = (0..3).map(|r| gr[r] * k[3 * r + c] as f64).sum();
                }
            }
            // (G g) G^T: (N x N).
            for (r, tr) in t.iter().enumerate() {
                for (c, gc) in tf.g.iter().enumerate() {
                    let v: f64 = (0..3).map(|k| tr[k] * gc[k]).sum();
                    u[(N * r + c) * plane + o * in_ch + i] = v as f32;
                }
            }
        }
    }
    u
}

/// Tiles handled together as SIMD lanes.
const LANES: usize = 8;

/// A band of tile rows `r0 .. r0 + nr` of an `h x w` image, `tw` (padded) tiles per row.
struct Band {
    h: usize,
    w: usize,
    r0: usize,
    nr: usize,
    tw: usize,
}

/// `rows x N` lane vectors times the transposed `out x N` matrix `t` (`dst[i][j] = sum_k
/// src[i][k] t[j][k]`); zero coefficients fold away once the constants are inlined.
#[inline(always)]
fn times_t<const R: usize, const N: usize, const O: usize>(
    src: &[[[f32; LANES]; N]; R],
    t: &[[f32; N]; O],
) -> [[[f32; LANES]; O]; R] {
    let mut dst = [[[0.0f32; LANES]; O]; R];
    for (d, s) in dst.iter_mut().zip(src) {
        for (dj, tj) in d.iter_mut().zip(t) {
            for (k, &c) in tj.iter().enumerate() {
                if c != 0.0 {
                    for l in 0..LANES {
                        dj[l] += c * s[k][l];
                    }
                }
            }
        }
    }
    dst
}

/// The transpose of an `R x C` array of lane vectors.
#[inline(always)]
fn transpose<const R: usize, const C: usize>(a: &[[[f32; LANES]; C]; R]) -> [[[f32; LANES]; R]; C] {
    let mut t = [[[0.0f32; LANES]; R]; C];
    for (r, ar) in a.iter().enumerate() {
        for (c, v) in ar.iter().enumerate() {
            t[c][r] = *v;
        }
    }
    t
}

/// `B^T d B` for every channel and tile of a band, into `v[N * N][cin][nr * tw]`.
#[inline(always)]
fn input_transform<const M: usize, const N: usize>(
    tf: &Transforms<M, N>,
    x: &[f32],
    cin: usize,
    b: &Band,
    v: &mut [f32],
) {
    let (h, w, tw) = (b.h, b.w, b.tw);
    let nt = b.nr * tw;
    let plane = cin * nt;
    // N zero-padded source rows: prow[r][j] = image[y0 + r][j - 1].
    let plen = M * tw + 2;
    let mut prow = vec![0.0f32; N * plen];
    for c in 0..cin {
        let img = &x[c * h * w..][..h * w];
        for tr in 0..b.nr {
            let y0 = (M * (b.r0 + tr)) as isize - 1;
            for r in 0..N {
                let dst = &mut prow[r * plen..][..plen];
                let yy = y0 + r as isize;
                if yy < 0 || yy >= h as isize {
                    dst.fill(0.0);
                } else {
                    dst[1..=w].copy_from_slice(&img[yy as usize * w..][..w]);
                }
            }
            for g in (0..tw).step_by(LANES) {
                // d[r][cc][lane] = prow[r][M * (g + lane) + cc]
                let mut d = [[[0.0f32; LANES]; N]; N];
                for (r, dr) in d.iter_mut().enumerate() {
                    let src = &prow[r * plen + M * g..][..M * (LANES - 1) + N];
                    for (cc, dc) in dr.iter_mut().enumerate() {
                        for (l, dv) in dc.iter_mut().enumerate() {
                            *dv = src[M * l + cc];
                        }
                    }
                }
                // (d B) then B^T (d B): columns first, then rows through the transpose.
                let db = times_t(&d, &tf.bt); // [r][j]
                let out = times_t(&transpose(&db), &tf.bt); // [j][i] = (B^T d B)[i][j]
                let base = c * nt + tr * tw + g;
                for (j, oj) in out.iter().enumerate() {
                    for (i, oij) in oj.iter().enumerate() {
                        v[(N * i + j) * plane + base..][..LANES].copy_from_slice(oij);
                    }
                }
            }
        }
    }
}

/// `A^T m A` plus bias for every output channel and tile of a band, into its rows of `y`.
#[inline(always)]
fn output_transform<const M: usize, const N: usize>(
    tf: &Transforms<M, N>,
    m: &[f32],
    cout: usize,
    b: &Band,
    bias: Option<&[f32]>,
    y: &super::SendPtr,
) {
    let (h, w, tw) = (b.h, b.w, b.tw);
    let nt = b.nr * tw;
    let plane = cout * nt;
    let rows = (M * (b.r0 + b.nr)).min(h) - M * b.r0;
    let mut orow = vec![0.0f32; M * M * tw];
    for o in 0..cout {
        let bv = bias.map_or(0.0, |b| b[o]);
        // SAFETY: rows M * r0 .. M * r0 + rows of channel o lie inside the (cout, h, w)
        // buffer, and no other band writes them.
        let out = unsafe { std::slice::from_raw_parts_mut(y.0.add((o * h + M * b.r0) * w), rows * w) };
        for tr in 0..b.nr {
            for g in (0..tw).step_by(LANES) {
                let base = o * nt + tr * tw + g;
                let mut q = [[[0.0f32; LANES]; N]; N];
                for (r, qr) in q.iter_mut().enumerate() {
                    for (c, qc) in qr.iter_mut().enumerate() {
                        qc.copy_from_slice(&m[(N * r + c) * plane + base..][..LANES]);
                    }
                }
                let qa = times_t(&q, &tf.at); // [r][b] = (q A)[r][b]
                let s = times_t(&transpose(&qa), &tf.at); // [b][a] = (A^T q A)[a][b]
                for (bb, sb) in s.iter().enumerate() {
                    for (a, sab) in sb.iter().enumerate() {
                        let dst = &mut orow[a * M * tw + M * g..][..M * LANES];
                        for l in 0..LANES {
                            dst[M * l + bb] = sab[l] + bv;
                        }
                    }
                }
            }
            for a in 0..M {
                let yy = M * tr + a;
                if yy < rows {
                    out[yy * w..][..w].copy_from_slice(&orow[a * M * tw..][..w]);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(n: usize, seed: u64) -> Vec<f32> {
        crate::cpu::test_values(n, seed, 1.0)
    }

    #[test]
    fn matches_direct_convolution_on_odd_and_even_sizes() {
        // Odd sizes exercise partial tiles; 600 columns exercise several bands; 256 channels
        // are the DPT's width. The bound is fp32 rounding of a sum of 9 * cin products of
        // values up to 1, with room for the F(4x4) transforms' coefficients (up to 8).
        let shapes = [(3, 5, 7, 9), (8, 4, 6, 8), (2, 3, 1, 1), (4, 2, 5, 600), (16, 16, 33, 17), (256, 32, 13, 21)];
        for tiles in [Tiles::F2, Tiles::F4] {
            for &(cin, cout, h, w) in &shapes {
                let x = lcg(cin * h * w, 1 + h as u64);
                let wt = lcg(cout * cin * 9, 7 + w as u64);
                let bias = lcg(cout, 3);
                let got = WinogradKernel::with_tiles(&wt, cout, cin, tiles).forward(&x, h, w, Some(&bias));
                let want = crate::cpu::direct_conv3x3(&x, &wt, cin, cout, h, w, &bias);
                let err = got.iter().zip(&want).map(|(&a, &b)| (a as f64 - b).abs()).fold(0.0, f64::max);
                let bound = match tiles {
                    Tiles::F2 => 1e-5 * (cin as f64).sqrt() * 3.0,
                    Tiles::F4 => 1e-5 * (cin as f64).sqrt() * 10.0,
                };
                assert!(err < bound, "{tiles:?} {cin}x{cout}x{h}x{w}: max err {err} (bound {bound})");
            }
        }
    }
}
