//! Stage 5: bundle adjustment. Camera rotations and centres, points and focals moved together
//! to minimise the reprojection error under a Huber loss, by Levenberg-Marquardt on the
//! reduced camera system: each point's 3x3 block eliminated (the Schur complement), the
//! camera-side system (6 per camera, 1 per free focal) solved densely, the points
//! back-substituted. One camera is held fixed (the gauge); the scale stays free (damping
//! keeps the step finite along it).

use crate::linalg::cholesky_solve;
use dens3r_align::keypoints::Keypoints;
use dens3r_geom::transform::{axis_angle, nearest_rotation};
use glam::{DMat3, DVec2, DVec3};

/// Bundle adjustment settings.
#[derive(Debug, Clone, PartialEq)]
pub struct BaOptions {
    /// Levenberg-Marquardt iterations at most.
    pub iterations: usize,
    /// Huber loss threshold (pixels): residuals beyond it count linearly.
    pub huber_px: f64,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub tolerance: f64,
}

impl Default for BaOptions {
    fn default() -> Self {
        Self { iterations: 40, huber_px: 0.5, tolerance: 1e-7 }
    }
}

/// A camera in the adjustment: camera-to-world rotation, centre, index of its focal, principal
/// point (fixed).
#[derive(Debug, Clone, PartialEq)]
pub struct BaCamera {
    /// Camera-to-world rotation.
    pub rotation: DMat3,
    /// Centre in the world.
    pub center: DVec3,
    /// Index into [`BaProblem::focals`].
    pub focal: usize,
    /// Principal point (pixels).
    pub principal: DVec2,
}

/// What is adjusted: cameras (`None`: not in the adjustment), focals (shared by the cameras
/// naming them; `focal_fixed` ones kept), points (`None`: left out), and per point its
/// observations `(view, keypoint)` of `keypoints`.
pub struct BaProblem<'a> {
    /// Cameras.
    pub cameras: &'a mut [Option<BaCamera>],
    /// Focals (pixels).
    pub focals: &'a mut [f64],
    /// Which focals are known.
    pub focal_fixed: &'a [bool],
    /// Per focal, a value it is drawn towards (a photo's EXIF focal): a prior residual
    /// `(f - f0) / (FOCAL_PRIOR_SIGMA f0)`, weighed as one observation.
    pub focal_prior: &'a [Option<f64>],
    /// Points.
    pub points: &'a mut [Option<DVec3>],
    /// Per point, its observations.
    pub observations: &'a [Vec<(usize, usize)>],
    /// The keypoints observed.
    pub keypoints: &'a [Keypoints],
}

/// How an adjustment went.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaReport {
    /// Root mean square reprojection error (pixels) before and after.
    pub initial_rms_px: f64,
    /// After.
    pub final_rms_px: f64,
    /// Iterations run.
    pub iterations: usize,
}

/// One observation linearised: residual (pixels), `d r / d (rotation tangent, centre)` (2x6),
/// `d r / d focal` (2), `d r / d point` (2x3).
type Linearised = (DVec2, [[f64; 6]; 2], DVec2, [[f64; 3]; 2]);

/// A point's part of the normal equations: its 3x3 block, its gradient, and per observation
/// the camera-side columns it couples to with their rows of `J_c^T J_p`.
type PointPart = (DMat3, DVec3, Vec<(Vec<usize>, [[f64; 3]; 7])>);

impl BaCamera {
    /// Point `x` in this camera's frame.
    fn to_camera(&self, x: DVec3) -> DVec3 {
        self.rotation.transpose() * (x - self.center)
    }

    /// The pixel where point `x` lands at focal `f`; `None` behind the camera.
    pub fn project(&self, f: f64, x: DVec3) -> Option<DVec2> {
        let q = self.to_camera(x);
        (q.z > 1e-9).then(|| DVec2::new(q.x / q.z, q.y / q.z) * f + self.principal)
    }
}

/// One observation's residual and Jacobians ([`Linearised`]); `None` behind the camera.
fn linearise(c: &BaCamera, f: f64, x: DVec3, uv: DVec2) -> Option<Linearised> {
    let rt = c.rotation.transpose();
    let q = c.to_camera(x);
    if q.z <= 1e-9 {
        return None;
    }
    let (u, v) = (q.x / q.z, q.y / q.z);
    let r = DVec2::new(f * u, f * v) + c.principal - uv;
    // d r / d q, then the chain: rotation R <- R Exp(w) gives d q = q x w; centre: -R^T;
    // point: R^T.
    let s = f / q.z;
    let drq = [[s, 0.0, -s * u], [0.0, s, -s * v]];
    let qx = [[0.0, -q.z, q.y], [q.z, 0.0, -q.x], [-q.y, q.x, 0.0]]; // [q]x, d q / d w
    let rtm = [rt.row(0), rt.row(1), rt.row(2)];
    let mut jc = [[0.0; 6]; 2];
    let mut jp = [[0.0; 3]; 2];
    for row in 0..2 {
        for k in 0..3 {
            let mut w = 0.0;
            let mut p = 0.0;
            for l in 0..3 {
                w += drq[row][l] * qx[l][k];
                p += drq[row][l] * rtm[l][k];
            }
            jc[row][k] = w;
            jc[row][3 + k] = -p;
            jp[row][k] = p;
        }
    }
    Some((r, jc, DVec2::new(u, v), jp))
}

/// A focal prior's standard deviation, as a share of the prior focal: weak, so that a photo
/// cropped in an editor (its EXIF focal half the truth) still finds its focal from the data.
pub const FOCAL_PRIOR_SIGMA: f64 = 0.1;

/// The prior residual of focal `f` (None without a prior) and its derivative.
fn prior_residual(p: &BaProblem, f: usize) -> Option<(f64, f64)> {
    let f0 = p.focal_prior.get(f).copied().flatten().filter(|f0| *f0 > 0.0)?;
    let s = FOCAL_PRIOR_SIGMA * f0;
    Some(((p.focals[f] - f0) / s, 1.0 / s))
}

/// The Huber weight of a residual of length `e`.
fn huber(e: f64, delta: f64) -> f64 {
    if e <= delta {
        1.0
    } else {
        delta / e
    }
}

/// The robust cost and the squared-error sum with its count.
fn cost(p: &BaProblem, delta: f64) -> (f64, f64, usize) {
    let (mut robust, mut sq, mut count) = (0.0, 0.0, 0);
    for (t, x) in p.observations.iter().zip(p.points.iter()) {
        let Some(x) = x else { continue };
        for &(v, kp) in t {
            let Some(c) = &p.cameras[v] else { continue };
            // The residual alone: the cost is evaluated at every trial step.
            let e = match c.project(p.focals[c.focal], *x) {
                Some(uv) => (uv - p.keypoints[v].xy[kp]).length(),
                None => 10.0 * delta,
            };
            robust += if e <= delta { 0.5 * e * e } else { delta * (e - 0.5 * delta) };
            sq += e * e;
            count += 1;
        }
    }
    for f in 0..p.focals.len() {
        if let Some((r, _)) = prior_residual(p, f) {
            robust += 0.5 * r * r;
        }
    }
    (robust, sq, count)
}

/// Adjusts `p` in place; the first camera is held fixed.
pub fn bundle_adjust(p: &mut BaProblem, opts: &BaOptions) -> BaReport {
    let n = p.cameras.len();
    let gauge = p.cameras.iter().position(|c| c.is_some());
    // Camera-side unknowns: 6 per free camera, then one per free focal.
    let mut cam_col = vec![usize::MAX; n];
    let mut dim = 0;
    for (v, col) in cam_col.iter_mut().enumerate() {
        if p.cameras[v].is_some() && Some(v) != gauge {
            *col = dim;
            dim += 6;
        }
    }
    let used_focals: Vec<bool> =
        (0..p.focals.len()).map(|f| p.cameras.iter().flatten().any(|c| c.focal == f) && !p.focal_fixed[f]).collect();
    let mut focal_col = vec![usize::MAX; p.focals.len()];
    for (f, &u) in used_focals.iter().enumerate() {
        if u {
            focal_col[f] = dim;
            dim += 1;
        }
    }
    let delta = opts.huber_px;
    let (c0, sq0, count) = cost(p, delta);
    let rms = |sq: f64| (sq / count.max(1) as f64).sqrt();
    let mut report = BaReport { initial_rms_px: rms(sq0), final_rms_px: rms(sq0), iterations: 0 };
    if count == 0 || dim == 0 {
        return report;
    }
    let mut current = c0;
    let mut lambda = 1e-4;
    for it in 0..opts.iterations {
        report.iterations = it + 1;
        // Normal equations, points eliminated as they are built.
        let mut s = vec![0.0; dim * dim];
        let mut g = vec![0.0; dim];
        // Per point: its V block, gradient and the camera-side columns it couples to.
        let mut point_parts: Vec<Option<PointPart>> = Vec::new();
        for (t, x) in p.observations.iter().zip(p.points.iter()) {
            let Some(x) = x else {
                point_parts.push(None);
                continue;
            };
            let mut vblk = DMat3::ZERO;
            let mut gp = DVec3::ZERO;
            let mut couplings: Vec<(Vec<usize>, [[f64; 3]; 7])> = Vec::new();
            for &(v, kp) in t {
                let Some(c) = &p.cameras[v] else { continue };
                let Some((r, jc, jf, jp)) = linearise(c, p.focals[c.focal], *x, p.keypoints[v].xy[kp]) else {
                    continue;
                };
                let w = huber(r.length(), delta);
                // Camera-side Jacobian columns of this observation.
                let mut cols: Vec<(usize, [f64; 2])> = Vec::with_capacity(7);
                if cam_col[v] != usize::MAX {
                    cols.extend((0..6).map(|k| (cam_col[v] + k, [jc[0][k], jc[1][k]])));
                }
                if focal_col[c.focal] != usize::MAX {
                    cols.push((focal_col[c.focal], [jf.x, jf.y]));
                }
                let rr = [r.x, r.y];
                for &(a, ja) in &cols {
                    g[a] -= w * (ja[0] * rr[0] + ja[1] * rr[1]);
                    for &(b, jb) in &cols {
                        s[a * dim + b] += w * (ja[0] * jb[0] + ja[1] * jb[1]);
                    }
                }
                let mut y = [[0.0; 3]; 7]; // J_c^T J_p rows
                for (k, &(_, ja)) in cols.iter().enumerate() {
                    for l in 0..3 {
                        y[k][l] = w * (ja[0] * jp[0][l] + ja[1] * jp[1][l]);
                    }
                }
                for l in 0..3 {
                    gp[l] -= w * (jp[0][l] * rr[0] + jp[1][l] * rr[1]);
                    for m in 0..3 {
                        let val = w * (jp[0][l] * jp[0][m] + jp[1][l] * jp[1][m]);
                        vblk.col_mut(m)[l] += val;
                    }
                }
                couplings.push((cols.iter().map(|c| c.0).collect(), y));
            }
            point_parts.push(Some((vblk, gp, couplings)));
        }
        // Focal priors.
        for (f, &col) in focal_col.iter().enumerate() {
            if let (true, Some((r, j))) = (col != usize::MAX, prior_residual(p, f)) {
                s[col * dim + col] += j * j;
                g[col] -= j * r;
            }
        }
        // Damping, then the Schur complement of each point.
        let diag: Vec<f64> = (0..dim).map(|k| s[k * dim + k]).collect();
        for k in 0..dim {
            s[k * dim + k] += lambda * diag[k].max(1e-9);
        }
        let mut vinv: Vec<Option<DMat3>> = Vec::with_capacity(point_parts.len());
        for part in &point_parts {
            let Some((vblk, gp, couplings)) = part else {
                vinv.push(None);
                continue;
            };
            let mut vd = *vblk;
            for k in 0..3 {
                vd.col_mut(k)[k] += lambda * vblk.col(k)[k].max(1e-12);
            }
            if vd.determinant().abs() < 1e-30 {
                vinv.push(None);
                continue;
            }
            let vi = vd.inverse();
            let vg = vi * *gp;
            for (cols_a, ya) in couplings {
                for (ka, &a) in cols_a.iter().enumerate() {
                    let ya_v = DVec3::from_array(ya[ka]);
                    g[a] -= ya_v.dot(vg);
                    let yv = vi * ya_v; // symmetric V^-1
                    for (cols_b, yb) in couplings {
                        for (kb, &b) in cols_b.iter().enumerate() {
                            s[a * dim + b] -= yv.dot(DVec3::from_array(yb[kb]));
                        }
                    }
                }
            }
            vinv.push(Some(vi));
        }
        let mut step = g.clone();
        let ok = cholesky_solve(&mut s, &mut step, dim).is_some();
        // Back-substitution and the trial parameters.
        let saved = (p.cameras.to_vec(), p.focals.to_vec(), p.points.to_vec());
        if ok {
            for (&k, cam) in cam_col.iter().zip(p.cameras.iter_mut()) {
                if k == usize::MAX {
                    continue;
                }
                let c = cam.as_mut().expect("in the adjustment");
                let w = DVec3::new(step[k], step[k + 1], step[k + 2]);
                if w.length() > 0.0 {
                    c.rotation = nearest_rotation(c.rotation * axis_angle(w / w.length(), w.length()));
                }
                c.center += DVec3::new(step[k + 3], step[k + 4], step[k + 5]);
            }
            for (f, &col) in focal_col.iter().enumerate() {
                if col != usize::MAX {
                    p.focals[f] += step[col];
                }
            }
            for ((part, vi), x) in point_parts.iter().zip(&vinv).zip(p.points.iter_mut()) {
                let (Some((_, gp, couplings)), Some(vi), Some(x)) = (part, vi, x.as_mut()) else { continue };
                let mut rhs = *gp;
                for (cols, y) in couplings {
                    for (k, &a) in cols.iter().enumerate() {
                        rhs -= DVec3::from_array(y[k]) * step[a];
                    }
                }
                *x += *vi * rhs;
            }
        }
        let trial = if ok && p.focals.iter().all(|f| *f > 0.0) { cost(p, delta).0 } else { f64::INFINITY };
        if trial < current {
            let gain = (current - trial) / current.max(1e-300);
            current = trial;
            lambda = (lambda / 3.0).max(1e-12);
            if gain < opts.tolerance {
                break;
            }
        } else {
            p.cameras.clone_from_slice(&saved.0);
            p.focals.clone_from_slice(&saved.1);
            p.points.clone_from_slice(&saved.2);
            lambda *= 4.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    report.final_rms_px = rms(cost(p, delta).1);
    report
}
