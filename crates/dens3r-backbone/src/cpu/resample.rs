//! Element-wise and resampling ops on raw buffers: bilinear x2 upsampling with
//! `align_corners=True` (separable, rayon over channels) and ReLU.

use rayon::prelude::*;

/// Bilinear x2 upsampling of `(c, h, w)` planes to `(c, 2h, 2w)`, corners aligned
/// (source coordinate `i * (n_in - 1) / (n_out - 1)`, as PyTorch computes it in f32).
pub fn upsample2x(x: &[f32], c: usize, h: usize, w: usize) -> Vec<f32> {
    upsample2x_rows(x, c, h, w, 0..2 * h)
}

/// Rows `rows` of [`upsample2x`]'s output, `(c, rows.len(), 2w)`: the same values, without
/// the rest of the image.
pub fn upsample2x_rows(x: &[f32], c: usize, h: usize, w: usize, rows: std::ops::Range<usize>) -> Vec<f32> {
    assert_eq!(x.len(), c * h * w, "upsample input size mismatch");
    let (ho, wo) = (2 * h, 2 * w);
    assert!(rows.end <= ho, "upsample rows {rows:?} beyond {ho}");
    let (ty, tx) = (taps(h, ho), taps(w, wo));
    let nr = rows.len();
    let mut y = vec![0.0f32; c * nr * wo];
    y.par_chunks_mut(nr * wo).zip(x.par_chunks(h * w)).for_each(|(dst, src)| {
        for (r, &(y0, y1, fy)) in ty[rows.clone()].iter().enumerate() {
            let (a, b) = (&src[y0 * w..][..w], &src[y1 * w..][..w]);
            for (o, &(x0, x1, fx)) in dst[r * wo..][..wo].iter_mut().zip(&tx) {
                // PyTorch's weighting: (1 - fy) * ((1 - fx) a0 + fx a1) + fy * (...).
                let top = (1.0 - fx) * a[x0] + fx * a[x1];
                let bot = (1.0 - fx) * b[x0] + fx * b[x1];
                *o = (1.0 - fy) * top + fy * bot;
            }
        }
    });
    y
}

/// For each of `n_out` samples upsampled from `n_in`, corners aligned: the two source
/// samples it reads and the second one's weight.
fn taps(n_in: usize, n_out: usize) -> Vec<(usize, usize, f32)> {
    let scale = if n_out > 1 { (n_in - 1) as f32 / (n_out - 1) as f32 } else { 0.0 };
    (0..n_out)
        .map(|i| {
            let src = scale * i as f32;
            let i0 = (src as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            (i0, i1, src - i0 as f32)
        })
        .collect()
}

/// The gradient of [`upsample2x`]: `dy (c, 2h, 2w)` carried back to `(c, h, w)` (each output's
/// gradient shared among the inputs it read, by their weights), rayon over channels.
pub fn upsample2x_backward(dy: &[f32], c: usize, h: usize, w: usize) -> Vec<f32> {
    let (ho, wo) = (2 * h, 2 * w);
    assert_eq!(dy.len(), c * ho * wo, "upsample gradient size mismatch");
    let (ty, tx) = (taps(h, ho), taps(w, wo));
    let mut dx = vec![0.0f32; c * h * w];
    dx.par_chunks_mut(h * w).zip(dy.par_chunks(ho * wo)).for_each(|(dst, src)| {
        let mut row = vec![0.0f32; w];
        for (r, &(y0, y1, fy)) in ty.iter().enumerate() {
            row.fill(0.0);
            for (g, &(x0, x1, fx)) in src[r * wo..][..wo].iter().zip(&tx) {
                row[x0] += (1.0 - fx) * g;
                row[x1] += fx * g;
            }
            for (j, v) in row.iter().enumerate() {
                dst[y0 * w + j] += (1.0 - fy) * v;
                dst[y1 * w + j] += fy * v;
            }
        }
    });
    dx
}

/// `max(x, 0)` in place.
pub fn relu_in_place(x: &mut [f32]) {
    x.par_chunks_mut(1 << 16).for_each(|c| c.iter_mut().for_each(|v| *v = v.max(0.0)));
}
