//! MASt3R fast reciprocal nearest neighbours on dense descriptors (spec 6.4) with Dens3R's
//! filters (spec 3.5: confidence >= 1.001, 3 px border), and tracks across pairs by union-find.

use crate::union_find::UnionFind;
use rayon::prelude::*;

/// A dense descriptor map: `dim` floats per pixel, row-major.
#[derive(Debug, Clone, Copy)]
pub struct Descriptors<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Floats per pixel (24 for Dens3R).
    pub dim: usize,
    /// `width * height * dim` values.
    pub data: &'a [f32],
}

impl Descriptors<'_> {
    fn len(&self) -> usize {
        self.width * self.height
    }
    fn at(&self, i: usize) -> &[f32] {
        &self.data[i * self.dim..(i + 1) * self.dim]
    }
    fn xy(&self, i: usize) -> (usize, usize) {
        (i % self.width, i / self.width)
    }
}

/// Matching options (Dens3R's defaults).
#[derive(Debug, Clone, PartialEq)]
pub struct MatchOptions {
    /// Seed grid step in pixels (8).
    pub subsample: usize,
    /// A seed is kept when its round trip lands within this many pixels of it (5).
    pub pixel_tol: f32,
    /// Minimum of the two descriptor confidences (1.001).
    pub min_conf: f32,
    /// Matches within this many pixels of either image's border are dropped (3).
    pub border: usize,
}

impl Default for MatchOptions {
    fn default() -> Self {
        Self { subsample: 8, pixel_tol: 5.0, min_conf: 1.001, border: 3 }
    }
}

/// One correspondence: pixel `(x, y)` in each image and its confidence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    /// Pixel in image A.
    pub a: (usize, usize),
    /// Pixel in image B.
    pub b: (usize, usize),
    /// `min(confA, confB)`.
    pub conf: f32,
}

/// The largest value of `row` (NaN ignored; -inf when empty or all NaN), in 16 lanes so the
/// compiler emits vector max instructions.
fn row_max(row: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; 16];
    let chunks = row.chunks_exact(16);
    let rest = chunks.remainder();
    for c in chunks {
        for (l, &v) in lanes.iter_mut().zip(c) {
            *l = if v > *l { v } else { *l };
        }
    }
    let mut m = f32::NEG_INFINITY;
    for &v in lanes.iter().chain(rest) {
        if v > m {
            m = v;
        }
    }
    m
}

/// `out[r * n + c] = lhs[r] . rhs[c]` for row-major `lhs` (`out.len() / n` rows) and `rhs`
/// (`n` rows), both `dim` wide: one `gemm` call.
pub(crate) fn dots_abt(lhs: &[f32], rhs: &[f32], dim: usize, out: &mut [f32]) {
    let (rows, n) = (lhs.len() / dim.max(1), rhs.len() / dim.max(1));
    assert!(lhs.len() == rows * dim && rhs.len() == n * dim && out.len() == rows * n, "dots_abt shapes");
    // SAFETY: dst is rows x n, row stride n, inside `out`; lhs is rows x dim row-major; rhs is
    // read as dim x n (element (k, j) at rhs[j * dim + k]); the shapes are checked above.
    unsafe {
        gemm::gemm(
            rows,
            n,
            dim,
            out.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs.as_ptr(),
            1,
            dim as isize,
            rhs.as_ptr(),
            dim as isize,
            1,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// For each query (flat pixel index into `q`), the pixel of `db` whose descriptor has the
/// largest dot product with it (the first on ties). Blocks of queries run in parallel; each
/// block's scores against a tile of `db` come from one `gemm` call, followed by a running
/// arg-max, so no full score matrix is ever held.
fn nearest_many(queries: &[usize], q: &Descriptors, db: &Descriptors) -> Vec<usize> {
    const QB: usize = 256; // queries per block
    const TB: usize = 1024; // database pixels per tile
    let dim = q.dim;
    queries
        .par_chunks(QB)
        .flat_map_iter(|block| {
            let rows = block.len();
            let lhs: Vec<f32> = block.iter().flat_map(|&i| q.at(i).iter().copied()).collect();
            let mut scores = vec![0f32; rows * TB];
            let mut best = vec![(f32::NEG_INFINITY, 0usize); rows];
            for t0 in (0..db.len()).step_by(TB) {
                let n = TB.min(db.len() - t0);
                let rhs = &db.data[t0 * dim..(t0 + n) * dim];
                dots_abt(&lhs, rhs, dim, &mut scores[..rows * n]);
                for (r, b) in best.iter_mut().enumerate() {
                    let row = &scores[r * n..(r + 1) * n];
                    // The row's maximum first (branch-free, vectorised), its index only when
                    // it beats the best so far: the same first-on-ties arg-max, NaN ignored.
                    let m = row_max(row);
                    if m > b.0 {
                        let j = row.iter().position(|&v| v == m).expect("the maximum is in the row");
                        *b = (m, t0 + j);
                    }
                }
            }
            best.into_iter().map(|b| b.1)
        })
        .collect()
}

/// Seeds on a `subsample` grid of `from`; a seed `x` matches `y = NN(x)` in `to` when
/// `NN(y)` back in `from` lies within `tol` pixels of `x`. Returns `(x, y)` flat indices.
/// Seeds of `from` and hits in `to` for which `usable_from` / `usable_to` is false are left
/// out before searching (their matches would be dropped anyway).
fn one_way(
    from: &Descriptors,
    to: &Descriptors,
    sub: usize,
    tol: f32,
    usable_from: impl Fn(usize) -> bool,
    usable_to: impl Fn(usize) -> bool,
) -> Vec<(usize, usize)> {
    let mut seeds = Vec::new();
    let mut y = sub / 2;
    while y < from.height {
        let mut x = sub / 2;
        while x < from.width {
            let s = y * from.width + x;
            if usable_from(s) {
                seeds.push(s);
            }
            x += sub;
        }
        y += sub;
    }
    let fwd = nearest_many(&seeds, from, to);
    // Seeds often land on the same pixel: each distinct usable one is searched back once.
    let mut hits: Vec<usize> = fwd.iter().copied().filter(|&t| usable_to(t)).collect();
    hits.sort_unstable();
    hits.dedup();
    let hit_back = nearest_many(&hits, to, from);
    seeds
        .into_iter()
        .zip(fwd)
        .filter_map(|(s, t)| {
            let b = hit_back[hits.binary_search(&t).ok()?];
            let ((x0, y0), (x1, y1)) = (from.xy(s), from.xy(b));
            let d = ((x0 as f32 - x1 as f32).powi(2) + (y0 as f32 - y1 as f32).powi(2)).sqrt();
            (d < tol).then_some((s, t))
        })
        .collect()
}

/// Non-symmetric reciprocal matching (`extract_correspondences_nonsym`): A->B and B->A seeds,
/// merged and de-duplicated (sorted by A index, then B index), filtered by confidence and
/// border. `conf_a` / `conf_b` are per-pixel descriptor confidences.
pub fn reciprocal_matches(
    a: &Descriptors,
    b: &Descriptors,
    conf_a: &[f32],
    conf_b: &[f32],
    opts: &MatchOptions,
) -> Result<Vec<Match>, String> {
    for (name, d, c) in [("A", a, conf_a), ("B", b, conf_b)] {
        if d.data.len() != d.len() * d.dim || c.len() != d.len() || d.dim == 0 {
            return Err(format!(
                "matching: image {name} has {} descriptor values and {} confidences for {}x{}x{}",
                d.data.len(),
                c.len(),
                d.width,
                d.height,
                d.dim
            ));
        }
    }
    if a.dim != b.dim {
        return Err(format!("matching: descriptor sizes differ ({} vs {})", a.dim, b.dim));
    }
    let sub = opts.subsample.max(1);
    let inside = |d: &Descriptors, (x, y): (usize, usize)| {
        x >= opts.border && y >= opts.border && x + opts.border < d.width && y + opts.border < d.height
    };
    // A pixel below the confidence floor or on the border cannot be in a kept match, so only
    // usable pixels are searched (NaN confidences stay: `min` below passes the other one
    // through), and every pair found lies inside both images.
    let ua = |i: usize| (conf_a[i].is_nan() || conf_a[i] >= opts.min_conf) && inside(a, a.xy(i));
    let ub = |i: usize| (conf_b[i].is_nan() || conf_b[i] >= opts.min_conf) && inside(b, b.xy(i));
    let mut pairs = one_way(a, b, sub, opts.pixel_tol, ua, ub);
    pairs.extend(one_way(b, a, sub, opts.pixel_tol, ub, ua).into_iter().map(|(y, x)| (x, y)));
    pairs.sort_unstable();
    pairs.dedup();
    Ok(pairs
        .into_iter()
        .filter_map(|(i, j)| {
            let m = Match { a: a.xy(i), b: b.xy(j), conf: conf_a[i].min(conf_b[j]) };
            (m.conf >= opts.min_conf).then_some(m)
        })
        .collect())
}

/// A keypoint: image index and pixel `(x, y)`.
pub type Keypoint = (usize, (usize, usize));

/// Keypoint tracks across images: matches of every pair joined by union-find over
/// `(image, pixel)`; tracks seen in fewer than `min_len` keypoints are dropped (Dens3R: 3).
/// Each track lists its `(image, (x, y))` keypoints, sorted.
pub fn tracks(matches: &[(usize, usize, Vec<Match>)], min_len: usize) -> Vec<Vec<Keypoint>> {
    use std::collections::HashMap;
    let mut id: HashMap<Keypoint, usize> = HashMap::new();
    let mut sets = UnionFind::new(0);
    for (ia, ib, ms) in matches {
        for m in ms {
            let u = *id.entry((*ia, m.a)).or_insert_with(|| sets.push());
            let v = *id.entry((*ib, m.b)).or_insert_with(|| sets.push());
            sets.union(u, v);
        }
    }
    let mut groups: HashMap<usize, Vec<Keypoint>> = HashMap::new();
    for (k, i) in id {
        groups.entry(sets.find(i)).or_default().push(k);
    }
    let mut out: Vec<_> = groups
        .into_values()
        .filter(|g| g.len() >= min_len)
        .map(|mut g| {
            g.sort_unstable();
            g
        })
        .collect();
    out.sort_unstable();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The tiled, vectorised arg-max equals a plain first-on-ties scan over every pixel, on
    /// random descriptors with duplicated pixels (ties) and sizes off the tile and lane widths.
    #[test]
    fn nearest_many_is_the_plain_arg_max() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let (w, h, dim) = (53, 41, 24);
        let mut db: Vec<f32> = (0..w * h * dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
        // Pixel 700 repeats pixel 100: queries near them tie, and the first must win.
        let copy = db[100 * dim..101 * dim].to_vec();
        db[700 * dim..701 * dim].copy_from_slice(&copy);
        let q: Vec<f32> = (0..w * h * dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let (qd, dd) =
            (Descriptors { width: w, height: h, dim, data: &q }, Descriptors { width: w, height: h, dim, data: &db });
        let queries: Vec<usize> = (0..w * h).step_by(7).chain([100]).collect();
        let got = nearest_many(&queries, &qd, &dd);
        for (&i, &g) in queries.iter().zip(&got) {
            let dot = |j: usize| (0..dim).map(|k| q[i * dim + k] * db[j * dim + k]).sum::<f32>();
            let mut best = (f32::NEG_INFINITY, 0);
            for j in 0..w * h {
                if dot(j) > best.0 {
                    best = (dot(j), j);
                }
            }
            // The GEMM sums in another order: equal up to rounding, so compare the scores.
            assert!((dot(g) - best.0).abs() < 1e-5, "query {i}: {g} ({}) vs {} ({})", dot(g), best.1, best.0);
            assert_ne!(g, 700, "a tie goes to the first pixel");
        }
        assert_eq!(row_max(&[1.0, f32::NAN, 3.0, 2.0]), 3.0);
        assert_eq!(row_max(&[]), f32::NEG_INFINITY);
        let long: Vec<f32> = (0..37).map(|i| ((i * 7) % 37) as f32).collect();
        assert_eq!(row_max(&long), 36.0);
    }

    /// Descriptors that are a known function of a scene coordinate: unit-norm random Fourier
    /// features, so the dot product peaks where the coordinates agree.
    fn features(coords: &[(f32, f32)], dim: usize, seed: u64) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let freqs: Vec<(f32, f32, f32)> = (0..dim / 2)
            .map(|_| (rng.gen_range(-0.3..0.3), rng.gen_range(-0.3..0.3), rng.gen_range(0.0..std::f32::consts::TAU)))
            .collect();
        let mut out = Vec::with_capacity(coords.len() * dim);
        for &(x, y) in coords {
            for &(fx, fy, ph) in &freqs {
                let a = fx * x + fy * y + ph;
                out.push(a.cos());
                out.push(a.sin());
            }
        }
        let norm = ((dim / 2) as f32).sqrt();
        out.iter_mut().for_each(|v| *v /= norm);
        out
    }

    #[test]
    fn reciprocal_matches_find_true_correspondences() {
        // Image B sees the scene shifted by (+11, -6) pixels and scaled by 1.1 about the origin:
        // B pixel (x, y) shows scene point ((x + 11) / 1.1, (y - 6) / 1.1), image A pixel (x, y)
        // shows scene point (x, y).
        let (w, h, dim) = (96, 72, 24);
        let to_scene_b = |x: f32, y: f32| ((x + 11.0) / 1.1, (y - 6.0) / 1.1);
        let ca: Vec<(f32, f32)> = (0..w * h).map(|i| ((i % w) as f32, (i / w) as f32)).collect();
        let cb: Vec<(f32, f32)> = (0..w * h).map(|i| to_scene_b((i % w) as f32, (i / w) as f32)).collect();
        let (da, db) = (features(&ca, dim, 5), features(&cb, dim, 5));
        let a = Descriptors { width: w, height: h, dim, data: &da };
        let b = Descriptors { width: w, height: h, dim, data: &db };
        let conf = vec![2.0f32; w * h];
        let ms = reciprocal_matches(&a, &b, &conf, &conf, &MatchOptions::default()).unwrap();
        assert!(ms.len() > 60, "{} matches", ms.len());
        for m in &ms {
            let (sx, sy) = to_scene_b(m.b.0 as f32, m.b.1 as f32);
            let err = ((sx - m.a.0 as f32).powi(2) + (sy - m.a.1 as f32).powi(2)).sqrt();
            assert!(err <= 1.0, "match {m:?} is {err} px off the true correspondence");
            assert!(m.a.0 >= 3 && m.a.1 >= 3 && m.a.0 + 3 < w && m.a.1 + 3 < h);
        }
        // Sorted by A, de-duplicated.
        assert!(ms.windows(2).all(|p| (p[0].a.1, p[0].a.0) <= (p[1].a.1, p[1].a.0)));
        // Low confidence removes matches.
        let low = vec![1.0f32; w * h];
        assert!(reciprocal_matches(&a, &b, &low, &conf, &MatchOptions::default()).unwrap().is_empty());
        // Wrong sizes are errors, not panics.
        assert!(reciprocal_matches(&a, &b, &conf[1..], &conf, &MatchOptions::default()).is_err());
    }

    #[test]
    fn tracks_join_matches_across_pairs() {
        let m = |a: (usize, usize), b: (usize, usize)| Match { a, b, conf: 2.0 };
        let matches = vec![
            (0, 1, vec![m((1, 1), (2, 2)), m((5, 5), (6, 6))]),
            (1, 2, vec![m((2, 2), (3, 3))]),
            (2, 3, vec![m((3, 3), (4, 4)), m((9, 9), (8, 8))]),
        ];
        let t = tracks(&matches, 3);
        assert_eq!(t, vec![vec![(0, (1, 1)), (1, (2, 2)), (2, (3, 3)), (3, (4, 4))]]);
        assert_eq!(tracks(&matches, 2).len(), 3);
    }

    /// The blocked gemm search equals a direct f64 scan (sizes that leave partial blocks and
    /// tiles).
    #[test]
    fn blocked_search_equals_a_direct_scan() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let (w, h, dim) = (67, 41, 24);
        let mut data = |n: usize| -> Vec<f32> { (0..n * dim).map(|_| rng.gen_range(-1.0..1.0)).collect() };
        let (a, b) = (data(w * h), data(w * h));
        let (da, db) =
            (Descriptors { width: w, height: h, dim, data: &a }, Descriptors { width: w, height: h, dim, data: &b });
        let queries: Vec<usize> = (0..w * h).step_by(7).collect();
        let got = nearest_many(&queries, &da, &db);
        for (&q, &g) in queries.iter().zip(&got) {
            let dot = |j: usize| (0..dim).map(|k| a[q * dim + k] as f64 * b[j * dim + k] as f64).sum::<f64>();
            let best = (0..w * h).map(dot).fold(f64::NEG_INFINITY, f64::max);
            assert!(dot(g) >= best - 1e-5, "query {q}: {} vs {best}", dot(g));
        }
    }

    /// `one_way` (each distinct forward hit searched back once) keeps exactly the seeds a plain
    /// per-seed round trip keeps, on descriptors drawn from a few prototypes (many seeds share a
    /// hit, ties abound); `reciprocal_matches`, which skips unusable pixels before searching,
    /// keeps exactly the plain round trips that pass its confidence and border filters.
    #[test]
    fn matching_equals_plain_round_trips() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let (w, h, dim) = (53, 37, 8);
        let protos: Vec<f32> = (0..12 * dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let mut draw =
            || -> Vec<f32> { (0..w * h).flat_map(|_| protos[rng.gen_range(0..12) * dim..][..dim].to_vec()).collect() };
        let (a, b) = (draw(), draw());
        let (da, db) =
            (Descriptors { width: w, height: h, dim, data: &a }, Descriptors { width: w, height: h, dim, data: &b });
        let nn = |q: &Descriptors, i: usize, d: &Descriptors| {
            let dot = |j: usize| (0..q.dim).map(|k| q.at(i)[k] * d.at(j)[k]).sum::<f32>();
            (0..d.len()).fold((f32::NEG_INFINITY, 0), |best, j| if dot(j) > best.0 { (dot(j), j) } else { best }).1
        };
        // Plain round trips from every 4th pixel of `f`: (seed, hit) when back within `tol`.
        let round = |f: &Descriptors, t: &Descriptors, tol: f32| {
            let mut out = Vec::new();
            for y in (2..h).step_by(4) {
                for x in (2..w).step_by(4) {
                    let hit = nn(f, y * w + x, t);
                    let (bx, by) = f.xy(nn(t, hit, f));
                    if ((bx as f32 - x as f32).powi(2) + (by as f32 - y as f32).powi(2)).sqrt() < tol {
                        out.push((y * w + x, hit));
                    }
                }
            }
            out
        };
        for tol in [0.5, 5.0, 30.0] {
            assert_eq!(one_way(&da, &db, 4, tol, |_| true, |_| true), round(&da, &db, tol), "tol {tol}");
        }
        // Matching with confidences (some under the floor, some NaN) and a border keeps exactly
        // the plain round trips of both directions whose pixels pass the filters.
        let mut conf = || -> Vec<f32> {
            (0..w * h)
                .map(|_| match rng.gen_range(0..10) {
                    0 => f32::NAN,
                    1..=3 => 1.0,
                    _ => 2.0,
                })
                .collect()
        };
        let (ca, cb) = (conf(), conf());
        // Descriptors of a scene seen shifted and scaled (as in the test above): true matches.
        let pa: Vec<(f32, f32)> = (0..w * h).map(|i| ((i % w) as f32, (i / w) as f32)).collect();
        let pb: Vec<(f32, f32)> = pa.iter().map(|&(x, y)| ((x + 5.0) / 1.1, (y - 3.0) / 1.1)).collect();
        let (a, b) = (features(&pa, 24, 2), features(&pb, 24, 2));
        let (da, db) = (
            Descriptors { width: w, height: h, dim: 24, data: &a },
            Descriptors { width: w, height: h, dim: 24, data: &b },
        );
        let opts = MatchOptions { subsample: 4, ..Default::default() };
        let got = reciprocal_matches(&da, &db, &ca, &cb, &opts).unwrap();
        let mut want = round(&da, &db, opts.pixel_tol);
        want.extend(round(&db, &da, opts.pixel_tol).into_iter().map(|(j, i)| (i, j)));
        want.sort_unstable();
        want.dedup();
        let inside = |(x, y): (usize, usize)| x >= 3 && y >= 3 && x + 3 < w && y + 3 < h;
        let want: Vec<Match> = want
            .into_iter()
            .map(|(i, j)| Match { a: da.xy(i), b: db.xy(j), conf: ca[i].min(cb[j]) })
            .filter(|m| m.conf >= opts.min_conf && inside(m.a) && inside(m.b))
            .collect();
        assert!(want.len() > 5, "{} matches", want.len());
        assert_eq!(got, want);
    }
}
