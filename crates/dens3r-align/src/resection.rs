//! Camera resection from a dense pointmap: the pose (and focal) of the camera that saw pixel
//! `(x, y)` at 3-D point `X` in an arbitrary frame, by the normalised DLT with the principal
//! point known and square pixels. Global alignment uses it so pair predictions may come in any
//! similarity frame, not only their first camera's.

use dens3r_geom::transform::nearest_rotation;
use glam::{DMat3, DVec3};

/// A resected camera: `x_cam = rotation * X + translation` (world-to-camera, in the pointmap's
/// units) and the focal in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Resection {
    /// World-to-camera rotation.
    pub rotation: DMat3,
    /// World-to-camera translation.
    pub translation: DVec3,
    /// Focal length (pixels), `fx = fy`.
    pub focal: f64,
}

/// Eigen-decomposition of a symmetric matrix by cyclic Jacobi rotations: eigenvalues and
/// eigenvectors (columns of the returned row-major `n x n` matrix).
pub(crate) fn jacobi_eigen(mut a: Vec<f64>, n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j].powi(2))
            .sum();
        let diag: f64 = (0..n).map(|i| a[i * n + i].powi(2)).sum();
        if off <= 1e-30 * diag.max(1e-300) {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq.abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| a[i * n + i]).collect(), v)
}

/// Resects a camera from `(pixel offset from the principal point, 3-D point, weight)` samples.
/// `None` when fewer than 6 samples or the configuration is degenerate.
pub fn resect(samples: &[((f64, f64), DVec3, f64)]) -> Option<Resection> {
    if samples.len() < 6 {
        return None;
    }
    // Hartley normalisation: 3-D centred, unit mean distance; 2-D unit mean radius (the
    // principal point stays at the origin).
    let wsum: f64 = samples.iter().map(|s| s.2).sum();
    if wsum.is_nan() || wsum <= 0.0 {
        return None;
    }
    let c = samples.iter().map(|s| s.1 * s.2).sum::<DVec3>() / wsum;
    let s3 = samples.iter().map(|s| (s.1 - c).length() * s.2).sum::<f64>() / wsum;
    let s2 = samples.iter().map(|s| (s.0 .0.hypot(s.0 .1)) * s.2).sum::<f64>() / wsum;
    if !(s3 > 0.0 && s2 > 0.0) {
        return None;
    }
    let mut m = vec![0.0f64; 144];
    for &((u, v), x, w) in samples {
        let p = (x - c) / s3;
        let (u, v) = (u / s2, v / s2);
        let rows = [
            [p.x, p.y, p.z, 1.0, 0.0, 0.0, 0.0, 0.0, -u * p.x, -u * p.y, -u * p.z, -u],
            [0.0, 0.0, 0.0, 0.0, p.x, p.y, p.z, 1.0, -v * p.x, -v * p.y, -v * p.z, -v],
        ];
        for r in &rows {
            for i in 0..12 {
                for j in 0..12 {
                    m[i * 12 + j] += w * r[i] * r[j];
                }
            }
        }
    }
    let (vals, vecs) = jacobi_eigen(m, 12);
    let k = (0..12).min_by(|&a, &b| vals[a].total_cmp(&vals[b]))?;
    let p: Vec<f64> = (0..12).map(|i| vecs[i * 12 + k]).collect();
    // Undo the normalisation: P = diag(s2, s2, 1) * P~ * [I/s3, -c/s3; 0, 1].
    let row = |r: usize, sc: f64| {
        let a = DVec3::new(p[4 * r], p[4 * r + 1], p[4 * r + 2]) * (sc / s3);
        let b = (p[4 * r + 3] - DVec3::new(p[4 * r], p[4 * r + 1], p[4 * r + 2]).dot(c) / s3) * sc;
        (a, b)
    };
    let (mut r0, mut r1, mut r2) = (row(0, s2), row(1, s2), row(2, 1.0));
    let norm = r2.0.length();
    if norm.is_nan() || norm <= 0.0 {
        return None;
    }
    // Points must lie in front of the camera.
    let sign = if r2.0.dot(c) + r2.1 < 0.0 { -1.0 } else { 1.0 } / norm;
    for r in [&mut r0, &mut r1, &mut r2] {
        r.0 *= sign;
        r.1 *= sign;
    }
    let (f0, f1) = (r0.0.length(), r1.0.length());
    let focal = 0.5 * (f0 + f1);
    if !(focal.is_finite() && focal > 0.0) {
        return None;
    }
    // Nearest rotation to the rows (r0 / f, r1 / f, r2).
    let rot = nearest_rotation(DMat3::from_cols(r0.0 / f0, r1.0 / f1, r2.0).transpose());
    let translation = DVec3::new(r0.1 / focal, r1.1 / focal, r2.1);
    Some(Resection { rotation: rot, translation, focal })
}

/// Reprojection error (pixels) of a `(pixel offset, point)` sample under `r`; infinite behind
/// the camera.
pub fn reprojection_error(r: &Resection, (u, v): (f64, f64), x: DVec3) -> f64 {
    let c = r.rotation * x + r.translation;
    if c.z <= 0.0 {
        return f64::INFINITY;
    }
    (r.focal * c.x / c.z - u).hypot(r.focal * c.y / c.z - v)
}

/// PnP-RANSAC settings.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacOptions {
    /// Minimal-sample hypotheses tried.
    pub iterations: usize,
    /// Inlier reprojection error, pixels.
    pub threshold: f64,
    /// Sampling seed (results are reproducible).
    pub seed: u64,
}

impl Default for RansacOptions {
    fn default() -> Self {
        Self { iterations: 512, threshold: 5.0, seed: 0 }
    }
}

impl RansacOptions {
    /// Defaults with the threshold scaled to the image: 5 px, or 1% of the long side for
    /// images over 500 px.
    pub fn for_image(width: usize, height: usize) -> Self {
        Self { threshold: (0.01 * width.max(height) as f64).max(5.0), ..Default::default() }
    }
}

/// Resection samples of a `w x h` pointmap (pixel `(x, y)` sees `pts(x, y)`): about `max`
/// pixels on a regular grid, those with positive `weight(flat index)` and a finite point,
/// as (offset from the centre `(w/2, h/2)`, point, weight).
pub fn pointmap_samples(
    pts: &dens3r_geom::Raster<dens3r_geom::Vec3>,
    weight: impl Fn(usize) -> f64,
    max: usize,
) -> Vec<((f64, f64), DVec3, f64)> {
    let (w, h) = (pts.width(), pts.height());
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let step = ((w * h) as f64 / max.max(1) as f64).sqrt().ceil().max(1.0) as usize;
    let mut out = Vec::new();
    for y in (0..h).step_by(step) {
        for x in (0..w).step_by(step) {
            let q = *pts.get(x, y);
            let wq = weight(y * w + x);
            if wq > 0.0 && q.is_finite() {
                out.push(((x as f64 - cx, y as f64 - cy), q.as_dvec3(), wq));
            }
        }
    }
    out
}

/// The camera of a `pts` pointmap in its own frame (`x_cam = R X + t`), from its
/// [`pointmap_samples`]: the frame itself (what Dens3R outputs for a pair's first view) unless
/// PnP-RANSAC finds a camera that explains clearly more of the points (on imperfect
/// predictions RANSAC otherwise finds degenerate cameras, focal near 0). `None` when no camera
/// explains them.
pub fn pointmap_camera(
    pts: &dens3r_geom::Raster<dens3r_geom::Vec3>,
    samples: &[((f64, f64), DVec3, f64)],
) -> Option<(DMat3, DVec3)> {
    let (w, h) = (pts.width(), pts.height());
    let ransac = RansacOptions::for_image(w, h);
    let inlier_weight = |r: &Resection| inliers(samples, r, ransac.threshold).0;
    let own = dens3r_geom::focal::focal_from_pointmap(
        pts,
        (w as f64 / 2.0, h as f64 / 2.0),
        dens3r_geom::focal::FocalMode::Weiszfeld,
    )
    .filter(|f| f.is_finite() && *f > 0.0)
    .map(|focal| Resection { rotation: DMat3::IDENTITY, translation: DVec3::ZERO, focal });
    let (r, _) = resect_ransac(samples, &ransac)?;
    if own.as_ref().is_some_and(|o| inlier_weight(o) >= 0.9 * inlier_weight(&r)) {
        Some((DMat3::IDENTITY, DVec3::ZERO))
    } else {
        Some((r.rotation, r.translation))
    }
}

/// The samples `r` reprojects within `threshold` pixels: their total weight and the mask.
pub fn inliers(samples: &[((f64, f64), DVec3, f64)], r: &Resection, threshold: f64) -> (f64, Vec<bool>) {
    let mask: Vec<bool> = samples.iter().map(|s| reprojection_error(r, s.0, s.1) < threshold).collect();
    (samples.iter().zip(&mask).filter(|(_, &m)| m).map(|(s, _)| s.2).sum(), mask)
}

/// SplitMix64: a small reproducible generator for sampling.
pub(crate) struct SplitMix(pub(crate) u64);

impl SplitMix {
    /// A draw in `0..n`.
    pub(crate) fn below(&mut self, n: usize) -> usize {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) % n as u64) as usize
    }

    /// `k` distinct draws in `0..n` (all of `0..n` in some order when `k >= n`) into `out`.
    pub(crate) fn distinct(&mut self, n: usize, k: usize, out: &mut Vec<usize>) {
        out.clear();
        while out.len() < k.min(n) {
            let i = self.below(n);
            if !out.contains(&i) {
                out.push(i);
            }
        }
    }
}

/// Robust resection (PnP-RANSAC with unknown focal, locally optimised): DLT hypotheses from
/// random 8-point samples (6 is the minimum, but noisy 6-point DLTs are poor), scored by the
/// weight of their inliers (reprojection error below the threshold); every new best is refitted
/// on its inliers at shrinking thresholds, then until the inlier set stops growing. Returns the camera and its
/// inlier mask. `None` with fewer than 6 samples or no hypothesis.
pub fn resect_ransac(samples: &[((f64, f64), DVec3, f64)], opts: &RansacOptions) -> Option<(Resection, Vec<bool>)> {
    let n = samples.len();
    if n < 6 {
        return None;
    }
    let mut rng = SplitMix(opts.seed);
    let score_at = |r: &Resection, thr: f64| -> (f64, Vec<bool>) { inliers(samples, r, thr) };
    let score = |r: &Resection| score_at(r, opts.threshold);
    let fit = |mask: &[bool]| {
        let inliers: Vec<_> = samples.iter().zip(mask).filter(|(_, &m)| m).map(|(s, _)| *s).collect();
        resect(&inliers)
    };
    // Local optimisation: refit on the inliers at 4x, 2x, then 1x the threshold (a loose set
    // first, so a rough hypothesis from a near-degenerate sample reaches the true camera),
    // then while refitting gains inlier weight.
    let refine = |(mut sc, mut r, mut mask): (f64, Resection, Vec<bool>)| {
        for m in [4.0, 2.0, 1.0] {
            let Some(refit) = fit(&score_at(&r, m * opts.threshold).1) else { break };
            let (sc2, mask2) = score(&refit);
            if sc2 > sc {
                (sc, r, mask) = (sc2, refit, mask2);
            }
        }
        for _ in 0..5 {
            let Some(refit) = fit(&mask) else { break };
            let (sc2, mask2) = score(&refit);
            if sc2 <= sc {
                break;
            }
            (sc, r, mask) = (sc2, refit, mask2);
        }
        (sc, r, mask)
    };
    const SAMPLE: usize = 8;
    let mut best: Option<(f64, Resection, Vec<bool>)> = None;
    let mut pick = Vec::with_capacity(SAMPLE);
    for _ in 0..opts.iterations {
        rng.distinct(n, SAMPLE, &mut pick);
        let minimal: Vec<_> = pick.iter().map(|&k| samples[k]).collect();
        if let Some(r) = resect(&minimal) {
            let (sc, mask) = score(&r);
            if best.as_ref().is_none_or(|b| sc > b.0) {
                best = Some(refine((sc, r, mask)));
            }
        }
    }
    let (_, mut r, _) = best?;
    // Polish at a tighter threshold: outliers that happen to land within the search threshold
    // (points smeared along the surface) otherwise bias the focal.
    for _ in 0..3 {
        let tight = score_at(&r, 0.4 * opts.threshold).1;
        if tight.iter().filter(|&&m| m).count() < 6 {
            break;
        }
        let Some(refit) = fit(&tight) else { break };
        r = refit;
    }
    let mask = score(&r).1;
    Some((r, mask))
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::transform::axis_angle;
    use rand::{Rng, SeedableRng};

    #[test]
    fn recovers_a_random_camera() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let rot = axis_angle(DVec3::new(rng.gen(), rng.gen(), rng.gen::<f64>() + 0.1), rng.gen_range(0.0..3.0));
            let t = DVec3::new(rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0));
            let f = rng.gen_range(100.0..800.0);
            // Points in front of the camera, expressed in the world frame.
            let samples: Vec<_> = (0..500)
                .map(|_| {
                    let pc = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(1.0..4.0));
                    let pw = rot.transpose() * (pc - t);
                    ((f * pc.x / pc.z, f * pc.y / pc.z), pw, 1.0)
                })
                .collect();
            let r = resect(&samples).unwrap();
            assert!((r.focal / f - 1.0).abs() < 1e-6, "{} vs {f}", r.focal);
            assert!((r.rotation - rot).abs_diff_eq(DMat3::ZERO, 1e-6), "{:?} vs {rot:?}", r.rotation);
            assert!((r.translation - t).length() < 1e-6);
        }
        assert!(resect(&[]).is_none());
    }

    #[test]
    fn ransac_ignores_gross_outliers() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        for trial in 0..10 {
            let rot = axis_angle(DVec3::new(rng.gen(), rng.gen(), rng.gen::<f64>() + 0.1), rng.gen_range(0.0..3.0));
            let t = DVec3::new(rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0));
            let f = rng.gen_range(200.0..800.0);
            // 35% of the points are wrong (a depth-edge smear, far off the true surface).
            let samples: Vec<_> = (0..400)
                .map(|k| {
                    let pc = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(1.0..4.0));
                    let px = (f * pc.x / pc.z, f * pc.y / pc.z);
                    let pc = if k % 20 < 7 { pc * rng.gen_range(1.3..3.0) + DVec3::X * 0.5 } else { pc };
                    (px, rot.transpose() * (pc - t), 1.0)
                })
                .collect();
            let plain = resect(&samples).unwrap();
            let (r, mask) = resect_ransac(&samples, &RansacOptions { seed: trial, ..Default::default() }).unwrap();
            let inliers = mask.iter().filter(|&&m| m).count();
            assert_eq!(inliers, 260, "trial {trial}: exactly the clean points are inliers");
            assert!((r.focal / f - 1.0).abs() < 1e-6, "{} vs {f}", r.focal);
            assert!((r.rotation - rot).abs_diff_eq(DMat3::ZERO, 1e-6));
            assert!((r.translation - t).length() < 1e-6);
            // The plain least-squares DLT is pulled off by the outliers.
            assert!((plain.focal / f - 1.0).abs() > 1e-3 || (plain.translation - t).length() > 1e-3);
        }
        assert!(resect_ransac(&[], &RansacOptions::default()).is_none());
    }
}
