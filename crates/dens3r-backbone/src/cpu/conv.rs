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
    super::gemm_by_columns(w, x, x_rs, y, y_rs, (cout, cin, n), acc, 256);
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
    // Zero-padded input, (h + 2) x (w + 2) per channel plus 2 spare elements so the last
    // shifted view stays in bounds. Output pixel (r, c) lives at padded index (r+1)(w+2)+c+1;
    // computing all padded positions from 0 to h*(w+2) with tap offset (ky, kx) reads
    // x_pad[i + ky*(w+2) + kx], a contiguous column range.
    let (wp, hp) = (w + 2, h + 2);
    let plane = hp * wp + 2;
    let mut xp = vec![0.0f32; cin * plane];
    xp.par_chunks_mut(plane).zip(x.par_chunks(h * w)).for_each(|(dst, src)| {
        for r in 0..h {
            dst[(r + 1) * wp + 1..][..w].copy_from_slice(&src[r * w..][..w]);
        }
    });
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
}
