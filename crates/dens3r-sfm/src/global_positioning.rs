//! Stage 4: global positioning. With every registered view's rotation fixed, camera centres
//! and track points are placed together: each observation asks that its point lie on its ray,
//! at least one unit in front of its view, `X - c = d v` with `d >= 1` for the world ray `v`
//! of a keypoint of the view centred at `c` (GLOMAP's point-to-camera constraints, with the
//! bound of least unsquared deviations (LUD) that fixes the scale and keeps the solution from
//! collapsing). The problem is convex: the depth `d` has a closed form, after which an
//! observation whose point lies beyond one unit only asks `(I - v v^T)(X - c) = 0` and one
//! nearer asks `X - c = v`. Each round solves that least-squares problem (the points
//! eliminated per track, 3x3 blocks; the centres from the reduced system, one view at the
//! origin) and reweights it (iteratively reweighted least squares): by the inverse squared
//! depth, so each residual measures the angle off the ray, and by a Cauchy weight of that
//! angle, so a wrong match barely pulls. GLOMAP optimises the same constraints from a random
//! start; this form needs no start.

use crate::linalg::cholesky_solve;
use glam::{DMat3, DVec3};

/// Global positioning settings.
#[derive(Debug, Clone, PartialEq)]
pub struct PositionOptions {
    /// Reweighting rounds.
    pub rounds: usize,
    /// Scale of the Cauchy weight on an observation's angle off its ray (degrees).
    pub cauchy_deg: f64,
}

impl Default for PositionOptions {
    fn default() -> Self {
        Self { rounds: 20, cauchy_deg: 1.0 }
    }
}

/// Camera centres and points ([`position`]).
#[derive(Debug, Clone)]
pub struct Positions {
    /// One per view; `None` for a view no observation placed.
    pub centers: Vec<Option<DVec3>>,
    /// One per track; `None` where its rays do not cross.
    pub points: Vec<Option<DVec3>>,
}

/// One observation: a view and its unit world ray.
pub type Ray = (usize, DVec3);

fn projector(v: DVec3) -> DMat3 {
    DMat3::IDENTITY - DMat3::from_cols(v * v.x, v * v.y, v * v.z)
}

/// Places the `n` views' centres and the tracks' points. `tracks[t]` lists its observations
/// (view, unit world ray); view `anchor` is put at the origin.
pub fn position(n: usize, tracks: &[Vec<Ray>], anchor: usize, opts: &PositionOptions) -> Positions {
    // Unknowns: every observed view but the anchor, 3 each.
    let mut col = vec![usize::MAX; n];
    let mut m = 0;
    for t in tracks {
        for &(v, _) in t {
            if v != anchor && col[v] == usize::MAX {
                col[v] = m;
                m += 1;
            }
        }
    }
    let mut centers = vec![None; n];
    let mut points = vec![None; tracks.len()];
    if m == 0 {
        return Positions { centers, points };
    }
    // Per observation: weight and whether its point lies beyond the unit bound (starts at it).
    let mut weights: Vec<Vec<(f64, bool)>> = tracks.iter().map(|t| vec![(1.0, false); t.len()]).collect();
    let cauchy = opts.cauchy_deg.to_radians();
    let dim = 3 * m;
    for round in 0..opts.rounds.max(1) {
        let mut s = vec![0.0; dim * dim];
        let mut rhs = vec![0.0; dim];
        let mut add = |r: usize, c: usize, blk: DMat3, sign: f64| {
            for (k, colv) in [blk.x_axis, blk.y_axis, blk.z_axis].into_iter().enumerate() {
                for (l, val) in [colv.x, colv.y, colv.z].into_iter().enumerate() {
                    s[(3 * r + l) * dim + 3 * c + k] += sign * val;
                }
            }
        };
        let mut solved = Vec::with_capacity(tracks.len());
        for (t, w) in tracks.iter().zip(&weights) {
            // B (X - c - v) for each observation: B = w P beyond the bound (P v = 0), w I at it.
            let blocks: Vec<DMat3> = w
                .iter()
                .zip(t)
                .map(|(&(w, beyond), &(_, v))| if beyond { projector(v) * w } else { DMat3::IDENTITY * w })
                .collect();
            let a = blocks.iter().fold(DMat3::ZERO, |acc, &b| acc + b);
            if t.len() < 2 || a.determinant().abs() < 1e-18 {
                solved.push(None);
                continue;
            }
            let ai = a.inverse();
            let r = t.iter().zip(&blocks).fold(DVec3::ZERO, |acc, (&(_, v), b)| acc + *b * v);
            let air = ai * r;
            for (o1, &(v1, ray1)) in t.iter().enumerate() {
                if v1 == anchor {
                    continue;
                }
                add(col[v1], col[v1], blocks[o1], 1.0);
                let g = blocks[o1] * (air - ray1);
                for k in 0..3 {
                    rhs[3 * col[v1] + k] += g[k];
                }
                for (o2, &(v2, _)) in t.iter().enumerate() {
                    if v2 != anchor {
                        add(col[v1], col[v2], blocks[o1] * ai * blocks[o2], -1.0);
                    }
                }
            }
            solved.push(Some((ai, r)));
        }
        let trace = (0..dim).map(|k| s[k * dim + k]).sum::<f64>() / dim as f64;
        for k in 0..dim {
            s[k * dim + k] += 1e-9 * trace.max(1e-12);
        }
        if cholesky_solve(&mut s, &mut rhs, dim).is_none() {
            return Positions { centers: vec![None; n], points: vec![None; tracks.len()] };
        }
        let c_of = |v: usize| -> DVec3 {
            if v == anchor {
                DVec3::ZERO
            } else {
                let k = 3 * col[v];
                DVec3::new(rhs[k], rhs[k + 1], rhs[k + 2])
            }
        };
        for (v, c) in centers.iter_mut().enumerate() {
            *c = (v == anchor || col[v] != usize::MAX).then(|| c_of(v));
        }
        for (k, (tr, sol)) in tracks.iter().zip(&solved).enumerate() {
            points[k] = sol.map(|(ai, r)| {
                let w = &weights[k];
                let bc = tr.iter().zip(w).fold(DVec3::ZERO, |acc, (&(v, ray), &(w, beyond))| {
                    let b = if beyond { projector(ray) * w } else { DMat3::IDENTITY * w };
                    acc + b * c_of(v)
                });
                ai * (bc + r)
            });
        }
        let mut changed = false;
        for (t, tr) in tracks.iter().enumerate() {
            let Some(x) = points[t] else { continue };
            for (o, &(v, ray)) in tr.iter().enumerate() {
                let d = x - c_of(v);
                let depth = d.dot(ray);
                let beyond = depth > 1.0;
                let angle = d.normalize_or_zero().dot(ray).clamp(-1.0, 1.0).acos();
                let w = 1.0 / (depth.max(1.0).powi(2) * (1.0 + (angle / cauchy).powi(2)));
                changed |= beyond != weights[t][o].1;
                weights[t][o] = (if round == 0 { 1.0 / depth.max(1.0).powi(2) } else { w }, beyond);
            }
        }
        if !changed && round >= 3 {
            break;
        }
    }
    Positions { centers, points }
}
