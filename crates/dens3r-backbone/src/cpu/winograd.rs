//! 3x3, stride 1, padding 1 convolution by Winograd F(2x2, 3x3) on raw `f32` buffers.
//!
//! Each 2x2 output tile is computed from a 4x4 input patch with 16 multiplies per
//! (input, output) channel pair instead of 36: the input patches and the kernels are
//! transformed once (`B^T d B`, `G g G^T`), the 16 transformed planes are multiplied as 16
//! independent matrix products on the `gemm` crate, and the products are transformed back
//! (`A^T m A`). F(2x2, 3x3) has small, exact-in-binary transform coefficients, so the result
//! matches direct convolution to float rounding (tested against a direct loop).
//!
//! Work is split into bands of tile rows so memory stays bounded (two bands per thread in
//! flight) and the bands run in parallel on rayon.

use gemm::Parallelism;
use rayon::prelude::*;

/// Kernels of a 3x3 convolution in the Winograd domain: 16 matrices `(out, in)`.
#[derive(Debug, Clone)]
pub struct WinogradKernel {
    /// `[16][out][in]`, plane `xi = 4 * row + col` of `G g G^T`.
    u: Vec<f32>,
    /// Output channels.
    pub out_ch: usize,
    /// Input channels.
    pub in_ch: usize,
}

impl WinogradKernel {
    /// Transforms PyTorch-layout `(out, in, 3, 3)` weights.
    pub fn new(weight: &[f32], out_ch: usize, in_ch: usize) -> Self {
        assert_eq!(weight.len(), out_ch * in_ch * 9, "3x3 kernel size mismatch");
        let plane = out_ch * in_ch;
        let mut u = vec![0.0f32; 16 * plane];
        for o in 0..out_ch {
            for i in 0..in_ch {
                let g = &weight[(o * in_ch + i) * 9..][..9];
                // G g: (4 x 3); G = [[1,0,0],[.5,.5,.5],[.5,-.5,.5],[0,0,1]].
                let mut t = [[0.0f32; 3]; 4];
                for c in 0..3 {
                    let (g0, g1, g2) = (g[c], g[3 + c], g[6 + c]);
                    t[0][c] = g0;
                    t[1][c] = 0.5 * (g0 + g1 + g2);
                    t[2][c] = 0.5 * (g0 - g1 + g2);
                    t[3][c] = g2;
                }
                // (G g) G^T: (4 x 4).
                for (r, row) in t.iter().enumerate() {
                    let (a, b, c) = (row[0], row[1], row[2]);
                    let vals = [a, 0.5 * (a + b + c), 0.5 * (a - b + c), c];
                    for (col, v) in vals.into_iter().enumerate() {
                        u[(4 * r + col) * plane + o * in_ch + i] = v;
                    }
                }
            }
        }
        Self { u, out_ch, in_ch }
    }

    /// Convolves one image `(in, h, w)` into `(out, h, w)`, zero padding 1, adding `bias`.
    pub fn forward(&self, x: &[f32], h: usize, w: usize, bias: Option<&[f32]>) -> Vec<f32> {
        let (cin, cout) = (self.in_ch, self.out_ch);
        assert_eq!(x.len(), cin * h * w, "input size mismatch");
        let th = h.div_ceil(2);
        // Tiles per row, padded to whole SIMD groups (the padding tiles are computed, unused).
        let tw = w.div_ceil(2).next_multiple_of(LANES);
        // Bands of tile rows with ~512 tiles each: large enough for an efficient product.
        let rows_per_band = (512 / tw).clamp(1, th);
        let bands: Vec<(usize, usize)> =
            (0..th).step_by(rows_per_band).map(|r0| (r0, rows_per_band.min(th - r0))).collect();
        let threads = rayon::current_num_threads();
        let inner = if bands.len() >= threads { Parallelism::None } else { Parallelism::Rayon(0) };
        let outs: Vec<Vec<f32>> = bands
            .par_iter()
            .map(|&(r0, nr)| {
                let nt = nr * tw;
                let mut v = vec![0.0f32; 16 * cin * nt];
                let band = Band { h, w, r0, nr, tw };
                super::with_avx2(|| input_transform(x, cin, &band, &mut v));
                let mut m = vec![0.0f32; 16 * cout * nt];
                for xi in 0..16 {
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
                let rows = (2 * (r0 + nr)).min(h) - 2 * r0;
                let mut y = vec![0.0f32; cout * rows * w];
                super::with_avx2(|| output_transform(&m, cout, &band, bias, &mut y));
                y
            })
            .collect();
        // Stitch the bands' rows into (out, h, w).
        let mut y = vec![0.0f32; cout * h * w];
        for (&(r0, _), band) in bands.iter().zip(&outs) {
            let y0 = 2 * r0;
            let rows = band.len() / (cout * w);
            for o in 0..cout {
                y[(o * h + y0) * w..][..rows * w].copy_from_slice(&band[o * rows * w..][..rows * w]);
            }
        }
        y
    }
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

/// `B^T d B` for every channel and tile of a band, into `v[16][cin][nr * tw]`.
#[inline(always)]
fn input_transform(x: &[f32], cin: usize, b: &Band, v: &mut [f32]) {
    let (h, w, tw) = (b.h, b.w, b.tw);
    let nt = b.nr * tw;
    let plane = cin * nt;
    // Four zero-padded source rows: prow[r][j] = image[y0 + r][j - 1].
    let plen = 2 * tw + 2;
    let mut prow = vec![0.0f32; 4 * plen];
    for c in 0..cin {
        let img = &x[c * h * w..][..h * w];
        for tr in 0..b.nr {
            let y0 = 2 * (b.r0 + tr) as isize - 1;
            for r in 0..4 {
                let dst = &mut prow[r * plen..][..plen];
                let yy = y0 + r as isize;
                if yy < 0 || yy >= h as isize {
                    dst.fill(0.0);
                } else {
                    dst[1..=w].copy_from_slice(&img[yy as usize * w..][..w]);
                }
            }
            for g in (0..tw).step_by(LANES) {
                // d[r][cc][lane] = prow[r][2 * (g + lane) + cc]
                let mut d = [[[0.0f32; LANES]; 4]; 4];
                for (r, dr) in d.iter_mut().enumerate() {
                    let src = &prow[r * plen + 2 * g..][..2 * LANES + 2];
                    for (cc, dc) in dr.iter_mut().enumerate() {
                        for (l, dv) in dc.iter_mut().enumerate() {
                            *dv = src[2 * l + cc];
                        }
                    }
                }
                // Rows: B^T = [[1,0,-1,0],[0,1,1,0],[0,-1,1,0],[0,1,0,-1]].
                let mut t = [[[0.0f32; LANES]; 4]; 4];
                for cc in 0..4 {
                    for l in 0..LANES {
                        t[0][cc][l] = d[0][cc][l] - d[2][cc][l];
                        t[1][cc][l] = d[1][cc][l] + d[2][cc][l];
                        t[2][cc][l] = d[2][cc][l] - d[1][cc][l];
                        t[3][cc][l] = d[1][cc][l] - d[3][cc][l];
                    }
                }
                let base = c * nt + tr * tw + g;
                for (r, tr_) in t.iter().enumerate() {
                    for col in 0..4 {
                        let out = &mut v[(4 * r + col) * plane + base..][..LANES];
                        for l in 0..LANES {
                            out[l] = match col {
                                0 => tr_[0][l] - tr_[2][l],
                                1 => tr_[1][l] + tr_[2][l],
                                2 => tr_[2][l] - tr_[1][l],
                                _ => tr_[1][l] - tr_[3][l],
                            };
                        }
                    }
                }
            }
        }
    }
}

/// `A^T m A` plus bias for every output channel and tile of a band, into `y (cout, rows, w)`.
#[inline(always)]
fn output_transform(m: &[f32], cout: usize, b: &Band, bias: Option<&[f32]>, y: &mut [f32]) {
    let (w, tw) = (b.w, b.tw);
    let nt = b.nr * tw;
    let plane = cout * nt;
    let rows = y.len() / (cout * w);
    let mut orow = vec![0.0f32; 2 * 2 * tw];
    for o in 0..cout {
        let bv = bias.map_or(0.0, |b| b[o]);
        let out = &mut y[o * rows * w..][..rows * w];
        for tr in 0..b.nr {
            for g in (0..tw).step_by(LANES) {
                let base = o * nt + tr * tw + g;
                let mut q = [[[0.0f32; LANES]; 4]; 4];
                for (r, qr) in q.iter_mut().enumerate() {
                    for (c, qc) in qr.iter_mut().enumerate() {
                        qc.copy_from_slice(&m[(4 * r + c) * plane + base..][..LANES]);
                    }
                }
                // A^T = [[1,1,1,0],[0,1,-1,-1]] on rows, then columns.
                let mut s = [[[0.0f32; LANES]; 4]; 2];
                for c in 0..4 {
                    for l in 0..LANES {
                        s[0][c][l] = q[0][c][l] + q[1][c][l] + q[2][c][l];
                        s[1][c][l] = q[1][c][l] - q[2][c][l] - q[3][c][l];
                    }
                }
                for (a, sa) in s.iter().enumerate() {
                    let dst = &mut orow[a * 2 * tw + 2 * g..][..2 * LANES];
                    for l in 0..LANES {
                        dst[2 * l] = sa[0][l] + sa[1][l] + sa[2][l] + bv;
                        dst[2 * l + 1] = sa[1][l] - sa[2][l] - sa[3][l] + bv;
                    }
                }
            }
            for a in 0..2 {
                let yy = 2 * tr + a;
                if yy < rows {
                    out[yy * w..][..w].copy_from_slice(&orow[a * 2 * tw..][..w]);
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
        // Odd sizes exercise partial tiles; 600 columns exercise several bands.
        for &(cin, cout, h, w) in &[(3, 5, 7, 9), (8, 4, 6, 8), (2, 3, 1, 1), (4, 2, 5, 600), (16, 16, 33, 17)] {
            let x = lcg(cin * h * w, 1 + h as u64);
            let wt = lcg(cout * cin * 9, 7 + w as u64);
            let bias = lcg(cout, 3);
            let got = WinogradKernel::new(&wt, cout, cin).forward(&x, h, w, Some(&bias));
            let want = crate::cpu::direct_conv3x3(&x, &wt, cin, cout, h, w, &bias);
            let err = got.iter().zip(&want).map(|(&a, &b)| (a as f64 - b).abs()).fold(0.0, f64::max);
            assert!(err < 1e-5 * (cin as f64).sqrt() * 3.0, "{cin}x{cout}x{h}x{w}: max err {err}");
        }
    }
}
