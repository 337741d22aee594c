//! One focal length for photos taken by one camera, from their keypoint-matched pairs: the
//! focal at which the pairs' relative rotations close their cycles. At a wrong focal each
//! pair's epipolar fit is nearly as good (for an object circled by the camera, whose optical
//! axes all meet, two views cannot tell the focal at all), but every pair turns by too much or
//! too little, and a loop of pairs around the object no longer comes back to where it started.

use crate::epipolar::{essential_ransac, EpipolarOptions};
use crate::rotations::{average_rotations, rotation_residuals};
use glam::{DMat3, DVec2};
use rayon::prelude::*;

/// Settings of [`focal_from_cycles`].
#[derive(Debug, Clone, PartialEq)]
pub struct CycleFocalOptions {
    /// Essential-matrix RANSAC per pair and focal.
    pub epipolar: EpipolarOptions,
    /// Fewest inliers for a pair to take part (at the starting focal).
    pub min_inliers: usize,
    /// Smallest inlier fraction of a pair's matches.
    pub min_inlier_ratio: f64,
    /// Focals searched, as factors of the starting focal.
    pub range: (f64, f64),
    /// Focals tried on a log-spaced grid over `range` before the bracket is narrowed.
    pub grid: usize,
    /// A pair's disagreement counts at most this much (degrees): a wrong pair weighs the same
    /// at every focal.
    pub cap_deg: f64,
}

impl Default for CycleFocalOptions {
    fn default() -> Self {
        Self {
            epipolar: EpipolarOptions::default(),
            min_inliers: 30,
            min_inlier_ratio: 0.3,
            range: (0.4, 2.5),
            grid: 25,
            cap_deg: 30.0,
        }
    }
}

/// A focal read from cycles, with what it was read from.
#[derive(Debug, Clone, PartialEq)]
pub struct CycleFocal {
    /// The focal (pixels).
    pub focal: f64,
    /// Mean disagreement (degrees, capped) of the pairs that close cycles, at `focal`.
    pub residual_deg: f64,
    /// The starting focal (pixels).
    pub start_focal: f64,
    /// The same at the starting focal.
    pub start_residual_deg: f64,
    /// Pairs used.
    pub pairs: usize,
    /// Independent cycles among them.
    pub cycles: usize,
}

/// The focal (pixels, shared by all `n` views) at which the relative rotations of `pairs`
/// agree best around their cycles. `pairs[k] = (i, j, a, b)`: matched keypoints of views `i`
/// (`a`) and `j` (`b`), in pixels from the principal point. Starts from `f0` (e.g. the
/// network's estimate) and searches `opts.range` times it: a grid, then golden-section search
/// around its best. `None` when the pairs close no cycle, or when the cycles do not pick a
/// focal clearly: the residual must at least halve from `f0`'s, and rise 15% to either side
/// of the focal found (by a quarter at least, by half on average).
pub fn focal_from_cycles(
    n: usize,
    pairs: &[(usize, usize, Vec<DVec2>, Vec<DVec2>)],
    f0: f64,
    opts: &CycleFocalOptions,
) -> Option<CycleFocal> {
    if !(f0.is_finite() && f0 > 0.0) {
        return None;
    }
    // Each pair's rotation at focal `f` (and its inlier count), for the pairs `which` lists.
    let rotations = |f: f64, which: &[usize]| -> Vec<Option<(DMat3, usize)>> {
        let fitted: Vec<(usize, Option<(DMat3, usize)>)> = which
            .par_iter()
            .map(|&k| {
                let (_, _, a, b) = &pairs[k];
                let na: Vec<DVec2> = a.iter().map(|q| *q / f).collect();
                let nb: Vec<DVec2> = b.iter().map(|q| *q / f).collect();
                let p = essential_ransac(&na, &nb, f, &opts.epipolar);
                // x_j = R x_i, so camera j's frame into camera i's is R^T.
                let r = p.and_then(|p| {
                    let c = p.inlier_count();
                    (c >= opts.min_inliers && c as f64 >= opts.min_inlier_ratio * a.len() as f64)
                        .then_some((p.rotation.transpose(), c))
                });
                (k, r)
            })
            .collect();
        let mut out = vec![None; pairs.len()];
        for (k, r) in fitted {
            out[k] = r;
        }
        out
    };
    // The pairs and their trust are fixed at f0, so every focal is scored on the same cycles
    // (and only those pairs are fitted again).
    let all: Vec<usize> = (0..pairs.len()).collect();
    let start = rotations(f0, &all);
    let used: Vec<usize> = (0..pairs.len()).filter(|&k| start[k].is_some()).collect();
    let weights: Vec<f64> = used.iter().map(|&k| start[k].map_or(0.0, |x| x.1 as f64)).collect();
    let mut sets = crate::union_find::UnionFind::new(n);
    let tree = used.iter().filter(|&&k| pairs[k].0 < n && pairs[k].1 < n && sets.union(pairs[k].0, pairs[k].1)).count();
    let cycles = used.len() - tree;
    if cycles == 0 {
        return None;
    }
    // Each used pair's disagreement with the others (capped; a pair that fails to fit counts
    // as the cap); their sum over the cycles is what the search minimises.
    let disagreements = |rots: &[Option<(DMat3, usize)>]| -> Vec<f64> {
        let edges: Vec<(usize, usize, DMat3, f64)> = used
            .iter()
            .zip(&weights)
            .filter_map(|(&k, &w)| rots[k].map(|(r, _)| (pairs[k].0, pairs[k].1, r, w)))
            .collect();
        let mut d = rotation_residuals(&average_rotations(n, &edges, 10), &edges).into_iter();
        used.iter()
            .map(|&k| {
                if rots[k].is_some() { d.next().flatten() } else { None }.unwrap_or(opts.cap_deg).min(opts.cap_deg)
            })
            .collect()
    };
    // A focal's cost (mean capped disagreement per cycle) with the disagreements it came from.
    let score = |f: f64| {
        let d = disagreements(&rotations(f, &used));
        (d.iter().sum::<f64>() / cycles as f64, d)
    };
    let (lo, hi) = (f0 * opts.range.0, f0 * opts.range.1);
    let steps = opts.grid.max(3);
    let grid: Vec<f64> = (0..steps).map(|k| lo * (hi / lo).powf(k as f64 / (steps - 1) as f64)).collect();
    let mut scored: Vec<(f64, Vec<f64>)> = grid.iter().map(|&f| score(f)).collect();
    let k = (0..steps).min_by(|&x, &y| scored[x].0.total_cmp(&scored[y].0))?;
    // Golden-section search (in log focal) between the grid's neighbours of its best.
    let (mut a, mut b) = (grid[k.saturating_sub(1)].ln(), grid[(k + 1).min(steps - 1)].ln());
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut sc, mut sd) = (score(c.exp()), score(d.exp()));
    for _ in 0..10 {
        if sc.0 <= sd.0 {
            (b, d, sd) = (d, c, sc);
            c = b - g * (b - a);
            sc = score(c.exp());
        } else {
            (a, c, sc) = (c, d, sd);
            d = a + g * (b - a);
            sd = score(d.exp());
        }
    }
    let (focal, (_, at_best)) = [(grid[k], scored.swap_remove(k)), (c.exp(), sc), (d.exp(), sd)]
        .into_iter()
        .min_by(|x, y| x.1 .0.total_cmp(&y.1 .0))
        .expect("three candidates");
    // Judged on the pairs that focal explains (under the cap there; matched repeated texture
    // is not): their cycles must close at least twice as well as at f0, and worse 15% to
    // either side (by a quarter at least, by half on average).
    let explained: Vec<usize> = (0..used.len()).filter(|&e| at_best[e] < opts.cap_deg).collect();
    let closing = explained.len().saturating_sub(used.len() - cycles);
    if closing == 0 {
        return None;
    }
    let mean = |d: &[f64]| explained.iter().map(|&e| d[e]).sum::<f64>() / closing as f64;
    let (residual, start_residual) = (mean(&at_best), mean(&disagreements(&start)));
    let sides: Vec<f64> = [0.85, 1.15].iter().map(|&s| mean(&disagreements(&rotations(focal * s, &used)))).collect();
    let floor = residual.max(0.5);
    let sharp = sides.iter().all(|&r| r >= 1.25 * floor) && sides.iter().sum::<f64>() >= 3.0 * floor;
    (residual <= 0.5 * start_residual && sharp).then_some(CycleFocal {
        focal,
        residual_deg: residual,
        start_focal: f0,
        start_residual_deg: start_residual,
        pairs: used.len(),
        cycles: closing,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resection::SplitMix;
    use glam::DVec3;

    /// Ten cameras circling a cloud of points (radius 4, 20 degrees above it, all looking at
    /// its centre: their optical axes meet, so no pair alone tells the focal), focal 450 px at
    /// 512x384 with 0.3 px noise; neighbours and second neighbours matched. Started 45% long
    /// (the network's error on such an orbit), the cycles give the focal within 3%.
    #[test]
    fn an_orbit_gives_its_focal() {
        let f = 450.0;
        let mut rng = SplitMix(5);
        let mut u = || rng.below(1_000_000) as f64 / 1e6 - 0.5;
        let cloud: Vec<DVec3> = (0..600).map(|_| DVec3::new(u(), u(), u()) * 1.6).collect();
        let cams: Vec<(DMat3, DVec3)> = (0..10)
            .map(|k| {
                let az = (36.0 * k as f64).to_radians();
                let el = 20f64.to_radians();
                let c = DVec3::new(az.sin() * el.cos(), -el.sin(), -az.cos() * el.cos()) * 4.0;
                // Camera-to-world rotation looking at the origin, y down.
                let z = (-c).normalize();
                let x = DVec3::Y.cross(z).normalize();
                let y = z.cross(x);
                (DMat3::from_cols(x, y, z), c)
            })
            .collect();
        let mut noise = SplitMix(9);
        let mut project = |k: usize, p: DVec3| -> Option<DVec2> {
            let (r, c) = cams[k];
            let q = r.transpose() * (p - c);
            let mut v = || (noise.below(1_000_000) as f64 / 1e6 - 0.5) * 0.6;
            let px = DVec2::new(f * q.x / q.z + v(), f * q.y / q.z + v());
            (q.z > 0.0 && px.x.abs() < 256.0 && px.y.abs() < 192.0).then_some(px)
        };
        let mut pairs = Vec::new();
        for i in 0..10 {
            for d in [1, 2] {
                let j = (i + d) % 10;
                // The near side of the cloud only: points facing both cameras.
                let dir = (cams[i].1 + cams[j].1).normalize();
                let (mut a, mut b) = (Vec::new(), Vec::new());
                for &p in cloud.iter().filter(|p| p.dot(dir) > 0.0) {
                    if let (Some(x), Some(y)) = (project(i, p), project(j, p)) {
                        a.push(x);
                        b.push(y);
                    }
                }
                pairs.push((i, j, a, b));
            }
        }
        let got = focal_from_cycles(10, &pairs, f * 1.45, &CycleFocalOptions::default()).expect("a focal");
        eprintln!("{got:?}");
        assert!((got.focal / f - 1.0).abs() < 0.03, "{got:?}");
        assert_eq!(got.cycles, 11);
        // Without a cycle (the neighbours of an open chain) nothing is claimed.
        let chain: Vec<_> = pairs.iter().filter(|p| p.1 == p.0 + 1).cloned().collect();
        assert_eq!(focal_from_cycles(10, &chain, f * 1.45, &CycleFocalOptions::default()), None);
    }
}
