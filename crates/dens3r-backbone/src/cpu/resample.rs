//! Element-wise and resampling ops on raw buffers: bilinear x2 upsampling with
//! `align_corners=True` (separable, rayon over channels) and ReLU.

use rayon::prelude::*;

/// Bilinear x2 upsampling of `(c, h, w)` planes to `(c, 2h, 2w)`, corners aligned
/// (source coordinate `i * (n_in - 1) / (n_out - 1)`, as PyTorch computes it in f32).
pub fn upsample2x(x: &[f32], c: usize, h: usize, w: usize) -> Vec<f32> {
    assert_eq!(x.len(), c * h * w, "upsample input size mismatch");
    let (ho, wo) = (2 * h, 2 * w);
    let taps = |n_in: usize, n_out: usize| -> Vec<(usize, usize, f32)> {
        let scale = if n_out > 1 { (n_in - 1) as f32 / (n_out - 1) as f32 } else { 0.0 };
        (0..n_out)
            .map(|i| {
                let src = scale * i as f32;
                let i0 = (src as usize).min(n_in - 1);
                let i1 = (i0 + 1).min(n_in - 1);
                (i0, i1, src - i0 as f32)
            })
            .collect()
    };
    let (ty, tx) = (taps(h, ho), taps(w, wo));
    let mut y = vec![0.0f32; c * ho * wo];
    y.par_chunks_mut(ho * wo).zip(x.par_chunks(h * w)).for_each(|(dst, src)| {
        let mut row = vec![0.0f32; wo];
        for (r, &(y0, y1, fy)) in ty.iter().enumerate() {
            let (a, b) = (&src[y0 * w..][..w], &src[y1 * w..][..w]);
            for (o, &(x0, x1, fx)) in row.iter_mut().zip(&tx) {
                // PyTorch's weighting: (1 - fy) * ((1 - fx) a0 + fx a1) + fy * (...).
                let top = (1.0 - fx) * a[x0] + fx * a[x1];
                let bot = (1.0 - fx) * b[x0] + fx * b[x1];
                *o = (1.0 - fy) * top + fy * bot;
            }
            dst[r * wo..][..wo].copy_from_slice(&row);
        }
    });
    y
}

/// `max(x, 0)` in place.
pub fn relu_in_place(x: &mut [f32]) {
    x.par_chunks_mut(1 << 16).for_each(|c| c.iter_mut().for_each(|v| *v = v.max(0.0)));
}
