//! The RANSAC loop the two-view models share (essential matrix, homography): minimal-sample
//! hypotheses scored by their inliers, each new best refitted on its inliers while they grow,
//! and an adaptive stop.

use crate::resection::SplitMix;
use glam::DVec2;

/// Best model for correspondences `(a[k], b[k])`: `fit` builds a model from the
/// correspondences it is given (a `sample`-sized random draw, or a hypothesis' inliers),
/// `score` counts a model's inliers and marks them. Each new best is refitted on its inliers
/// (kept when it loses none: a fit to every inlier beats the sample it grew from) until the
/// set stops growing (10 times at most). Draws stop after `iterations`, or once 99.9%
/// sure that one all-inlier sample was drawn (at least 50). Returns the inlier count, the
/// model and its inliers; `None` when no draw gave a model.
pub(crate) fn ransac<M>(
    a: &[DVec2],
    b: &[DVec2],
    sample: usize,
    iterations: usize,
    seed: u64,
    fit: impl Fn(&[DVec2], &[DVec2]) -> Option<M>,
    score: impl Fn(&M) -> (usize, Vec<bool>),
) -> Option<(usize, M, Vec<bool>)> {
    let n = a.len();
    let refit = |mask: &[bool]| {
        let (pa, pb): (Vec<DVec2>, Vec<DVec2>) =
            a.iter().zip(b).zip(mask).filter(|(_, &m)| m).map(|((p, q), _)| (*p, *q)).unzip();
        fit(&pa, &pb)
    };
    let mut rng = SplitMix(seed);
    let mut best: Option<(usize, M, Vec<bool>)> = None;
    let mut pick = Vec::with_capacity(sample);
    let (mut it, mut needed) = (0, iterations);
    while it < needed {
        it += 1;
        rng.distinct(n, sample, &mut pick);
        let sa: Vec<DVec2> = pick.iter().map(|&k| a[k]).collect();
        let sb: Vec<DVec2> = pick.iter().map(|&k| b[k]).collect();
        let Some(mut m) = fit(&sa, &sb) else { continue };
        let (mut c, mut mask) = score(&m);
        if best.as_ref().is_some_and(|x| c <= x.0) {
            continue;
        }
        for _ in 0..10 {
            let Some(m2) = refit(&mask) else { break };
            let (c2, mask2) = score(&m2);
            if c2 < c {
                break;
            }
            let grew = c2 > c;
            (m, c, mask) = (m2, c2, mask2);
            if !grew {
                break;
            }
        }
        // Stop once 99.9% sure of one all-inlier sample.
        let p_good = (c as f64 / n as f64).powi(sample as i32);
        if p_good > 1e-9 {
            let k = ((1.0 - 0.999f64).ln() / (1.0 - p_good).max(1e-12).ln()).ceil();
            needed = needed.min(k.max(50.0) as usize);
        }
        best = Some((c, m, mask));
    }
    best
}
