//! Convolutions as plain matrix products on raw buffers: 1x1 (one product) and, for layers
//! with few output channels where Winograd's transforms dominate, 3x3 as nine products over
//! shifted views of the zero-padded input. Output columns are split across rayon workers.

use rayon::prelude::*;

/// `y (cout x n) [+]= w (cout x cin) * x (cin x n)` with row strides `x_rs` / `y_rs`.
#[allow(clippy::too_many_arguments)]
fn product(
    w: &[f32],
    x: &[f32],
    x_rs: usize,
    y: &mut [f32],
    y_rs: usize,
    cout: usize,
    cin: usize,
    n: usize,
    acc: bool,
) {
    super::gemm_by_columns(w, x, (x_rs, 1), y, y_rs, (cout, cin, n), acc, 256);
}

fn fill_bias(y: &mut [f32], bias: Option<&[f32]>, plane: usize) {
    if let Some(b) = bias {
        y.chunks_exact_mut(plane).zip(b).for_each(|(row, &v)| row.fill(v));
    }
}

/// 1x1 convolution of one image `(cin, hw)` with `(cout, cin)` weights.
pub fn conv1x1(x: &[f32], w: &[f32], bias: Option<&[f32]>, cin: usize, cout: usize, hw: usize) -> Vec<f32> {
    assert_eq!(x.len(), cin * hw, "conv1x1 input size mismatch");
    assert_eq!(w.len(), cout * cin, "conv1x1 weight size mismatch");
    let mut y = vec![0.0f32; cout * hw];
    fill_bias(&mut y, bias, hw);
    product(w, x, hw, &mut y, hw, cout, cin, hw, bias.is_some());
    y
}

/// 3x3, stride 1, padding 1 convolution of one image `(cin, h, w)` with weights given as
/// nine `(cout, cin)` matrices (`taps[ky * 3 + kx]`).
pub fn conv3x3_shifted(
    x: &[f32],
    taps: &[f32],
    bias: Option<&[f32]>,
    cin: usize,
    cout: usize,
    h: usize,
    w: usize,
) -> Vec<f32> {
    assert_eq!(x.len(), cin * h * w, "conv3x3 input size mismatch");
    assert_eq!(taps.len(), 9 * cout * cin, "conv3x3 weight size mismatch");
    let (xp, plane) = padded_planes(x, cin, h, w);
    let wp = w + 2;
    let n = h * wp; // output rows 0..h on the padded-width grid (two junk columns per row)
    let mut yp = vec![0.0f32; cout * n];
    fill_bias(&mut yp, bias, n);
    for (t, tap) in taps.chunks_exact(cout * cin).enumerate() {
        let off = (t / 3) * wp + t % 3;
        product(tap, &xp[off..], plane, &mut yp, n, cout, cin, n, bias.is_some() || t > 0);
    }
    let mut y = vec![0.0f32; cout * h * w];
    y.par_chunks_mut(h * w).zip(yp.par_chunks(n)).for_each(|(dst, src)| {
        for r in 0..h {
            dst[r * w..][..w].copy_from_slice(&src[r * wp..][..w]);
        }
    });
    y
}

/// The zero-padded input of the shifted products and its per-channel plane length: (h + 2) x
/// (w + 2) per channel plus 2 spare elements so the last shifted view stays in bounds. Output
/// pixel (r, c) lives at padded index (r+1)(w+2)+c+1; computing all padded positions from 0 to
/// h*(w+2) with tap offset (ky, kx) reads x_pad[i + ky*(w+2) + kx], a contiguous column range.
fn padded_planes(x: &[f32], cin: usize, h: usize, w: usize) -> (Vec<f32>, usize) {
    let wp = w + 2;
    let plane = (h + 2) * wp + 2;
    let mut xp = vec![0.0f32; cin * plane];
    xp.par_chunks_mut(plane).zip(x.par_chunks(h * w)).for_each(|(dst, src)| {
        for r in 0..h {
            dst[(r + 1) * wp + 1..][..w].copy_from_slice(&src[r * w..][..w]);
        }
    });
    (xp, plane)
}

/// PyTorch `(cout, cin, 3, 3)` weights as nine `(cout, cin)` tap matrices.
pub fn taps_from_weight(weight: &[f32], cout: usize, cin: usize) -> Vec<f32> {
    let mut taps = vec![0.0f32; 9 * cout * cin];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..9 {
                taps[(t * cout + o) * cin + i] = weight[(o * cin + i) * 9 + t];
            }
        }
    }
    taps
}

/// `(cout, cin, 3, 3)` weights as the `(cin, cout, 3, 3)` weights of the convolution that
/// gives a 3x3 / stride 1 / pad 1 convolution's input gradient from its output gradient
/// (channels swapped, taps turned by 180 degrees).
pub fn flip_transpose3x3(weight: &[f32], cout: usize, cin: usize) -> Vec<f32> {
    assert_eq!(weight.len(), cout * cin * 9, "conv3x3 weight size mismatch");
    let mut out = vec![0.0f32; cin * cout * 9];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..9 {
                out[(i * cout + o) * 9 + 8 - t] = weight[(o * cin + i) * 9 + t];
            }
        }
    }
    out
}

/// `(cout, cin)` as `(cin, cout)`: the 1x1 convolution that gives a 1x1 convolution's input
/// gradient.
pub fn transpose(weight: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    assert_eq!(weight.len(), rows * cols, "matrix size mismatch");
    let mut out = vec![0.0f32; rows * cols];
    for r in 0..rows {
        for c in 0..cols {
            out[c * rows + r] = weight[r * cols + c];
        }
    }
    out
}

/// Nine `(cout, cin)` tap matrices as PyTorch `(cout, cin, 3, 3)` weights: the inverse of
/// [`taps_from_weight`].
pub fn weight_from_taps(taps: &[f32], cout: usize, cin: usize) -> Vec<f32> {
    assert_eq!(taps.len(), 9 * cout * cin, "conv3x3 taps size mismatch");
    let mut weight = vec![0.0f32; cout * cin * 9];
    for (t, tap) in taps.chunks_exact(cout * cin).enumerate() {
        for (oi, &v) in tap.iter().enumerate() {
            weight[oi * 9 + t] = v;
        }
    }
    weight
}

/// Adds one image's contribution to a 3x3 / stride 1 / pad 1 convolution's weight gradient,
/// kept as nine `(cout, cin)` tap matrices (`taps[ky * 3 + kx]`, as [`taps_from_weight`] lays
/// them out; [`weight_from_taps`] turns the sum into PyTorch's layout):
/// `dtaps[t][o, i] += sum_p dy[o, p] x[i, p + (ky - 1, kx - 1)]` (zero outside the image), for
/// `x (cin, h, w)` and `dy (cout, h, w)`. Nine products over the padded input's shifted views,
/// the transposes of [`conv3x3_shifted`]'s, side by side on rayon.
pub fn conv3x3_weight_grad(x: &[f32], dy: &[f32], cin: usize, cout: usize, h: usize, w: usize, dtaps: &mut [f32]) {
    assert_eq!(x.len(), cin * h * w, "conv3x3 input size mismatch");
    assert_eq!(dy.len(), cout * h * w, "conv3x3 output gradient size mismatch");
    assert_eq!(dtaps.len(), 9 * cout * cin, "conv3x3 weight gradient size mismatch");
    let (xp, plane) = padded_planes(x, cin, h, w);
    // The output gradient on the padded-width grid, its two junk columns per row zero.
    let wp = w + 2;
    let n = h * wp;
    let mut dyp = vec![0.0f32; cout * n];
    dyp.par_chunks_mut(n).zip(dy.par_chunks(h * w)).for_each(|(dst, src)| {
        for r in 0..h {
            dst[r * wp..][..w].copy_from_slice(&src[r * w..][..w]);
        }
    });
    // The nine taps side by side, each one product (thin as the matrices are, splitting their
    // columns as well was 5% slower on dens3r-s's training step).
    dtaps.par_chunks_mut(cout * cin).enumerate().for_each(|(t, g)| {
        let off = (t / 3) * wp + t % 3;
        // rhs (n x cin): the input's shifted view read transposed.
        super::gemm_by_columns(&dyp, &xp[off..], (1, plane), g, cin, (cout, n, cin), true, cin.max(1));
    });
}

/// Adds one image's contribution to a 1x1 convolution's weight gradient:
/// `dw (cout, cin) += dy (cout, hw) x (cin, hw)^T`.
pub fn conv1x1_weight_grad(x: &[f32], dy: &[f32], cin: usize, cout: usize, hw: usize, dw: &mut [f32]) {
    assert_eq!(x.len(), cin * hw, "conv1x1 input size mismatch");
    assert_eq!(dy.len(), cout * hw, "conv1x1 output gradient size mismatch");
    assert_eq!(dw.len(), cout * cin, "conv1x1 weight gradient size mismatch");
    super::gemm_by_columns(dy, x, (1, hw), dw, cin, (cout, hw, cin), true, 16);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rnd(n: usize, seed: u64) -> Vec<f32> {
        crate::cpu::test_values(n, seed, 1.0)
    }

    #[test]
    fn shifted_3x3_matches_direct_loop() {
        for &(cin, cout, h, w) in &[(3, 2, 5, 7), (8, 4, 1, 1), (5, 3, 17, 600)] {
            let (x, wt, b) = (rnd(cin * h * w, 1), rnd(cout * cin * 9, 2), rnd(cout, 3));
            let got = conv3x3_shifted(&x, &taps_from_weight(&wt, cout, cin), Some(&b), cin, cout, h, w);
            let want = crate::cpu::direct_conv3x3(&x, &wt, cin, cout, h, w, &b);
            for (i, (g, acc)) in got.iter().zip(&want).enumerate() {
                assert!((*g as f64 - acc).abs() < 1e-5, "({cin},{cout},{h},{w}) [{i}]: {g} vs {acc}");
            }
        }
    }

    #[test]
    fn conv1x1_matches_direct_loop() {
        let (cin, cout, hw) = (7, 5, 1000);
        let (x, wt) = (rnd(cin * hw, 4), rnd(cout * cin, 5));
        let got = conv1x1(&x, &wt, None, cin, cout, hw);
        for o in 0..cout {
            for p in 0..hw {
                let want: f64 = (0..cin).map(|i| wt[o * cin + i] as f64 * x[i * hw + p] as f64).sum();
                assert!((got[o * hw + p] as f64 - want).abs() < 1e-5);
            }
        }
    }

    /// The weight gradient of one image, in f64 from the definition.
    fn direct_weight_grad(x: &[f32], dy: &[f32], cin: usize, cout: usize, h: usize, w: usize, k: usize) -> Vec<f64> {
        let r = (k / 2) as isize;
        let mut g = vec![0.0f64; cout * cin * k * k];
        for o in 0..cout {
            for i in 0..cin {
                for ky in 0..k {
                    for kx in 0..k {
                        let mut acc = 0.0;
                        for yy in 0..h as isize {
                            for xx in 0..w as isize {
                                let (sy, sx) = (yy + ky as isize - r, xx + kx as isize - r);
                                if sy < 0 || sx < 0 || sy >= h as isize || sx >= w as isize {
                                    continue;
                                }
                                acc += dy[(o * h + yy as usize) * w + xx as usize] as f64
                                    * x[(i * h + sy as usize) * w + sx as usize] as f64;
                            }
                        }
                        g[((o * cin + i) * k + ky) * k + kx] = acc;
                    }
                }
            }
        }
        g
    }

    #[test]
    fn weight_gradients_match_the_definition_and_accumulate() {
        for &(cin, cout, h, w) in &[(3, 2, 5, 7), (1, 1, 1, 1), (6, 17, 9, 40)] {
            let (x, dy) = (rnd(cin * h * w, 7), rnd(cout * h * w, 8));
            let start = rnd(cout * cin * 9, 9);
            let mut g3 = taps_from_weight(&start, cout, cin);
            conv3x3_weight_grad(&x, &dy, cin, cout, h, w, &mut g3);
            let g3 = weight_from_taps(&g3, cout, cin);
            for (j, (g, want)) in g3.iter().zip(direct_weight_grad(&x, &dy, cin, cout, h, w, 3)).enumerate() {
                assert!((*g as f64 - start[j] as f64 - want).abs() < 1e-4, "3x3 ({cin},{cout},{h},{w}) [{j}]");
            }
            let mut g1 = start[..cout * cin].to_vec();
            conv1x1_weight_grad(&x, &dy, cin, cout, h * w, &mut g1);
            for (j, (g, want)) in g1.iter().zip(direct_weight_grad(&x, &dy, cin, cout, h, w, 1)).enumerate() {
                assert!((*g as f64 - start[j] as f64 - want).abs() < 1e-4, "1x1 ({cin},{cout},{h},{w}) [{j}]");
            }
        }
    }

    /// The input gradient is the adjoint of the convolution: <conv(x), dy> = <x, conv'(dy)>.
    #[test]
    fn flipped_transposed_weights_give_the_adjoint() {
        let (cin, cout, h, w) = (5, 4, 6, 9);
        let (x, dy, wt) = (rnd(cin * h * w, 10), rnd(cout * h * w, 11), rnd(cout * cin * 9, 12));
        let y = conv3x3_shifted(&x, &taps_from_weight(&wt, cout, cin), None, cin, cout, h, w);
        let back = flip_transpose3x3(&wt, cout, cin);
        let dx = conv3x3_shifted(&dy, &taps_from_weight(&back, cin, cout), None, cout, cin, h, w);
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(p, q)| *p as f64 * *q as f64).sum::<f64>();
        let (lhs, rhs) = (dot(&y, &dy), dot(&x, &dx));
        assert!((lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
        let t = transpose(&wt[..cout * cin], cout, cin);
        let y1 = conv1x1(&x, &wt[..cout * cin], None, cin, cout, h * w);
        let dx1 = conv1x1(&dy, &t, None, cout, cin, h * w);
        let (lhs, rhs) = (dot(&y1, &dy), dot(&x, &dx1));
        assert!((lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
    }
}
