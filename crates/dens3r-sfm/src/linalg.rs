//! Dense symmetric positive-definite solves for the small reduced systems of the stages
//! (one 3x3 or 6x6 block per camera).

/// Solves `a x = b` for a symmetric positive-definite `a` (`n x n`, row-major) by Cholesky
/// decomposition, in place of `b`. `None` when `a` is not positive definite.
pub fn cholesky_solve(a: &mut [f64], b: &mut [f64], n: usize) -> Option<()> {
    use rayon::prelude::*;
    // Row-oriented Cholesky: column j of L is row j's dot products with the rows below it,
    // each row's independent of the others (split over threads for large systems).
    for j in 0..n {
        let (done, rest) = a.split_at_mut((j + 1) * n);
        let row_j = &mut done[j * n..];
        let d = row_j[j] - dot(&row_j[..j], &row_j[..j]);
        if d.is_nan() || d <= 0.0 || !d.is_finite() {
            return None;
        }
        let d = d.sqrt();
        row_j[j] = d;
        let row_j = &row_j[..j];
        let update = |row_i: &mut [f64]| row_i[j] = (row_i[j] - dot(&row_i[..j], row_j)) / d;
        if (n - j) * j > 1 << 16 {
            rest.par_chunks_mut(n).for_each(update);
        } else {
            rest.chunks_mut(n).for_each(update);
        }
    }
    for i in 0..n {
        b[i] = (b[i] - dot(&a[i * n..i * n + i], &b[..i])) / a[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= a[k * n + i] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
    Some(())
}

/// Dot product in eight independent sums (so the compiler may use vector registers).
fn dot(x: &[f64], y: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (xc, yc) = (x.chunks_exact(8), y.chunks_exact(8));
    let tail: f64 = xc.remainder().iter().zip(yc.remainder()).map(|(a, b)| a * b).sum();
    for (a, b) in xc.zip(yc) {
        for k in 0..8 {
            acc[k] += a[k] * b[k];
        }
    }
    acc.iter().sum::<f64>() + tail
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A known 3x3 system: the solution multiplies back to the right-hand side.
    #[test]
    fn solves_a_known_system() {
        let a0 = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let x = [1.0, -2.0, 0.5];
        let mut b: Vec<f64> = (0..3).map(|i| (0..3).map(|k| a0[i * 3 + k] * x[k]).sum()).collect();
        let mut a = a0;
        cholesky_solve(&mut a, &mut b, 3).unwrap();
        for k in 0..3 {
            assert!((b[k] - x[k]).abs() < 1e-12, "{b:?}");
        }
        // A larger system (threads, eight-way sums): against the product it solves.
        let n = 300;
        let m: Vec<f64> = (0..n * n).map(|k| ((k * 7919 % 1000) as f64 / 1000.0) - 0.5).collect();
        let mut a: Vec<f64> = (0..n * n)
            .map(|k| {
                (0..n).map(|l| m[(k / n) * n + l] * m[(k % n) * n + l]).sum::<f64>()
                    + if k / n == k % n { 1.0 } else { 0.0 }
            })
            .collect();
        let a0 = a.clone();
        let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
        let mut b: Vec<f64> = (0..n).map(|i| (0..n).map(|k| a0[i * n + k] * x[k]).sum()).collect();
        cholesky_solve(&mut a, &mut b, n).unwrap();
        let worst = b.iter().zip(&x).map(|(p, q)| (p - q).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-8, "{worst}");
        let mut singular = [1.0, 1.0, 1.0, 1.0];
        assert!(cholesky_solve(&mut singular, &mut [1.0, 2.0], 2).is_none());
    }
}
