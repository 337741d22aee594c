//! PatchMatch on one reference view at one pyramid level: every pixel holds a plane (depth and
//! normal in the reference camera's OpenCV frame); planes spread by red-black (checkerboard)
//! propagation from the best-scoring neighbours in eight directions (ACMH's adaptive
//! sampling), then are refined by random and perturbed hypotheses (Gipuma). A plane is scored
//! by the bilaterally weighted NCC of the window it induces in each source view (homography
//! `K_s (R + t n^T / c) K_r^-1`), the mean over the best views, plus, when asked, ACMM's
//! forward-backward reprojection error against the sources' depth maps and the network's
//! prior (depth and normal, weighted by its confidence) so texture-less surfaces follow it.

use crate::image::Grey;
use crate::options::PatchMatchOptions;
use crate::simd::{window_sums, LANES};
use dens3r_geom::{Intrinsics, Raster};
use glam::{Mat3, Vec3};
use rayon::prelude::*;

/// Most window samples (radius 7 at step 2 is 64; radius 5 at step 1 is 121).
pub const MAX_SAMPLES: usize = 128;
/// Most source views one reference is matched against.
pub const MAX_SOURCES: usize = 16;
/// Cost of a view the hypothesis does not project into.
const INVALID_VIEW_COST: f32 = 2.0;
/// Photometric cost of a texture-less window (no evidence either way).
const FLAT_COST: f32 = 1.0;
/// Reference windows whose weighted grey standard deviation is below this are texture-less.
const FLAT_STD: f32 = 0.006;

/// Pixel intrinsics in f32.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct K {
    /// Focal length x.
    pub fx: f32,
    /// Focal length y.
    pub fy: f32,
    /// Principal point x.
    pub cx: f32,
    /// Principal point y.
    pub cy: f32,
}

impl K {
    /// From the f64 intrinsics.
    pub fn from(k: &Intrinsics) -> Self {
        Self { fx: k.fx as f32, fy: k.fy as f32, cx: k.cx as f32, cy: k.cy as f32 }
    }

    /// The ray through pixel `(u, v)` with z = 1.
    #[inline]
    pub fn ray(&self, u: f32, v: f32) -> Vec3 {
        Vec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// The pixel of a camera-frame point (z > 0).
    #[inline]
    pub fn project(&self, p: Vec3) -> (f32, f32) {
        (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }

    fn matrix(&self) -> Mat3 {
        Mat3::from_cols(Vec3::new(self.fx, 0.0, 0.0), Vec3::new(0.0, self.fy, 0.0), Vec3::new(self.cx, self.cy, 1.0))
    }

    fn inverse(&self) -> Mat3 {
        self.matrix().inverse()
    }
}

/// A depth map with its camera intrinsics, for the geometric-consistency term.
#[derive(Debug, Clone, Copy)]
pub struct DepthView<'a> {
    /// Depth (0 = none).
    pub depth: &'a Raster<f32>,
    /// Its intrinsics.
    pub k: K,
}

/// One source view of a reference: its image at the level, intrinsics, and the rigid motion
/// from the reference camera's frame to its own (`X_s = R X_r + t`).
#[derive(Debug, Clone, Copy)]
pub struct Source<'a> {
    /// Grey image at this level.
    pub image: &'a Grey,
    /// Its intrinsics at this level.
    pub k: K,
    /// Rotation reference -> source camera.
    pub r: Mat3,
    /// Translation reference -> source camera.
    pub t: Vec3,
    /// The source's own depth map, for the geometric-consistency term.
    pub depth: Option<DepthView<'a>>,
}

/// The network's prediction for the reference at this level.
#[derive(Debug, Clone, Copy)]
pub struct Prior<'a> {
    /// Depth (0 or non-finite = none).
    pub depth: &'a Raster<f32>,
    /// Camera-frame normals facing the camera (zero = none).
    pub normals: &'a Raster<Vec3>,
    /// Per-pixel weight in 0..1 (the network's confidence).
    pub weight: &'a Raster<f32>,
}

/// One reference view's problem at one level.
#[derive(Debug, Clone)]
pub struct Problem<'a> {
    /// Reference grey image.
    pub image: &'a Grey,
    /// Reference intrinsics at this level.
    pub k: K,
    /// Source views (at most [`MAX_SOURCES`]).
    pub sources: Vec<Source<'a>>,
    /// The network's depth and normals, if any.
    pub prior: Option<Prior<'a>>,
    /// Depths random hypotheses are drawn from (near, far).
    pub depth_range: (f32, f32),
    /// Whether the geometric-consistency term is in the cost.
    pub geometric: bool,
}

/// A plane hypothesis and its cost.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hyp {
    /// Depth along the optical axis at the pixel.
    pub depth: f32,
    /// Camera-frame unit normal facing the camera.
    pub normal: Vec3,
    /// Cost (lower is better).
    pub cost: f32,
}

/// Depth, normal and cost of every pixel of a reference view.
#[derive(Debug, Clone)]
pub struct PlaneMap {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Row-major hypotheses.
    pub hyps: Vec<Hyp>,
}

impl PlaneMap {
    /// The depth map.
    pub fn depth(&self) -> Raster<f32> {
        Raster::from_vec(self.width, self.height, self.hyps.iter().map(|h| h.depth).collect()).expect("sized")
    }

    /// The normal map.
    pub fn normals(&self) -> Raster<Vec3> {
        Raster::from_vec(self.width, self.height, self.hyps.iter().map(|h| h.normal).collect()).expect("sized")
    }

    /// The cost map.
    pub fn costs(&self) -> Raster<f32> {
        Raster::from_vec(self.width, self.height, self.hyps.iter().map(|h| h.cost).collect()).expect("sized")
    }

    /// This map on a grid twice as fine (`width` x `height`), each pixel taking its coarse
    /// pixel's plane (depth re-intersected along its own ray); costs are recomputed by
    /// [`solve`].
    pub fn upsample(&self, coarse: K, fine: K, width: usize, height: usize) -> PlaneMap {
        let mut hyps = Vec::with_capacity(width * height);
        for y in 0..height {
            let cy = (((y as f32 + 0.5) * 0.5 - 0.5).round().max(0.0) as usize).min(self.height - 1);
            for x in 0..width {
                let cx = (((x as f32 + 0.5) * 0.5 - 0.5).round().max(0.0) as usize).min(self.width - 1);
                let h = self.hyps[cy * self.width + cx];
                let c = h.normal.dot(coarse.ray(cx as f32, cy as f32) * h.depth);
                let ray = fine.ray(x as f32, y as f32);
                let den = h.normal.dot(ray);
                let d = if den < -1e-3 { c / den } else { h.depth };
                let depth = if d.is_finite() && d > 0.0 && (d / h.depth - 1.0).abs() < 0.5 { d } else { h.depth };
                hyps.push(Hyp { depth, normal: h.normal, cost: f32::INFINITY });
            }
        }
        PlaneMap { width, height, hyps }
    }
}

/// A small counter-based random generator: every draw is a hash of (seed, pixel, step), so
/// results do not depend on the threads' order.
#[derive(Debug, Clone, Copy)]
struct Rng(u64);

impl Rng {
    fn new(seed: u64, a: u64, b: u64) -> Self {
        let mut r = Rng(seed ^ a.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ b.wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
        r.next();
        r
    }

    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in [-1, 1).
    fn signed(&mut self) -> f32 {
        2.0 * self.unit() - 1.0
    }
}

/// The reference window around one pixel: offsets, bilateral weights and the centred,
/// weighted grey values, computed once per visit and shared by every hypothesis.
struct RefWindow {
    n: usize,
    w: [f32; MAX_SAMPLES],
    /// `w * (r - mean)`.
    wr: [f32; MAX_SAMPLES],
    wsum: f32,
    /// Weighted variance times `wsum`.
    var: f32,
    flat: bool,
}

/// The fixed part of a level: window offsets and their spatial weights.
struct Window {
    offsets: Vec<(i32, i32)>,
    du: Vec<f32>,
    dv: Vec<f32>,
    spatial: Vec<f32>,
    inv_two_sigma_c2: f32,
}

impl Window {
    fn new(o: &PatchMatchOptions) -> Self {
        let r = o.window_radius as i32;
        let step = o.window_step.max(1) as i32;
        let mut offsets = Vec::new();
        // Symmetric about the centre: -r, -r + step, ..., r (r = 5, step 2: six samples a side).
        let mut ks = Vec::new();
        let mut k = -r;
        while k <= r {
            ks.push(k);
            k += step;
        }
        for &dy in &ks {
            for &dx in &ks {
                offsets.push((dx, dy));
            }
        }
        offsets.truncate(MAX_SAMPLES);
        let s2 = 2.0 * o.sigma_spatial * o.sigma_spatial;
        let spatial = offsets.iter().map(|&(dx, dy)| (-((dx * dx + dy * dy) as f32) / s2).exp()).collect();
        // Padded to whole vectors; the padding's weights stay 0.
        let padded = offsets.len().div_ceil(LANES) * LANES;
        let mut du: Vec<f32> = offsets.iter().map(|o| o.0 as f32).collect();
        let mut dv: Vec<f32> = offsets.iter().map(|o| o.1 as f32).collect();
        du.resize(padded, 0.0);
        dv.resize(padded, 0.0);
        Self { offsets, du, dv, spatial, inv_two_sigma_c2: 1.0 / (2.0 * o.sigma_color * o.sigma_color) }
    }

    fn at(&self, img: &Grey, x: usize, y: usize) -> RefWindow {
        let mut win = RefWindow {
            n: self.du.len(),
            w: [0.0; MAX_SAMPLES],
            wr: [0.0; MAX_SAMPLES],
            wsum: 0.0,
            var: 0.0,
            flat: false,
        };
        let (w, h) = (img.width() as i32, img.height() as i32);
        let centre = img.at(x, y);
        let (mut sw, mut swr, mut swrr) = (0.0f32, 0.0f32, 0.0f32);
        let mut vals = [0.0f32; MAX_SAMPLES];
        for (i, &(dx, dy)) in self.offsets.iter().enumerate() {
            let xx = (x as i32 + dx).clamp(0, w - 1) as usize;
            let yy = (y as i32 + dy).clamp(0, h - 1) as usize;
            let r = img.at(xx, yy);
            let dc = r - centre;
            let wt = self.spatial[i] * (-dc * dc * self.inv_two_sigma_c2).exp();
            win.w[i] = wt;
            vals[i] = r;
            sw += wt;
            swr += wt * r;
            swrr += wt * r * r;
        }
        let mean = swr / sw;
        for ((wr, w), v) in win.wr.iter_mut().zip(&win.w).zip(&vals).take(win.n) {
            *wr = w * (v - mean);
        }
        win.wsum = sw;
        win.var = (swrr - swr * mean).max(0.0);
        win.flat = win.var / sw < FLAT_STD * FLAT_STD;
        win
    }
}

/// What one level's solve needs besides the problem.
struct Solver<'a, 'p> {
    p: &'p Problem<'a>,
    o: &'p PatchMatchOptions,
    win: Window,
    kinv: Mat3,
    ksrc: Vec<Mat3>,
    width: usize,
    height: usize,
    seed: u64,
    prior_cos_tol: f32,
}

impl<'a, 'p> Solver<'a, 'p> {
    /// The cost of plane (depth `d`, normal `n`) at pixel `(x, y)` with window `win`.
    fn cost(&self, x: usize, y: usize, win: &RefWindow, d: f32, n: Vec3) -> f32 {
        let (xf, yf) = (x as f32, y as f32);
        let point = self.p.k.ray(xf, yf) * d;
        let c = n.dot(point);
        if c > -1e-6 * d || d.is_nan() || d <= 0.0 {
            return 2.0 * INVALID_VIEW_COST;
        }
        let mut view_costs = [INVALID_VIEW_COST; MAX_SOURCES];
        let nsrc = self.p.sources.len().min(MAX_SOURCES);
        for (s, src) in self.p.sources.iter().take(nsrc).enumerate() {
            let m = src.r + Mat3::from_cols(src.t * (n.x / c), src.t * (n.y / c), src.t * (n.z / c));
            let hmat = self.ksrc[s] * m * self.kinv;
            let h0 = hmat * Vec3::new(xf, yf, 1.0);
            if h0.z <= 1e-6 {
                continue;
            }
            let (uc, vc) = (h0.x / h0.z, h0.y / h0.z);
            let (sw, sh) = (src.image.width() as f32, src.image.height() as f32);
            if !(uc >= 0.0 && vc >= 0.0 && uc <= sw - 1.0 && vc <= sh - 1.0) {
                continue;
            }
            let mut cost = if win.flat {
                FLAT_COST
            } else {
                let (c0, c1) = (hmat.x_axis, hmat.y_axis);
                let n = win.n;
                let [s_ws, s_wss, s_wrs] =
                    window_sums(src.image, h0, c0, c1, &self.win.du[..n], &self.win.dv[..n], &win.w[..n], &win.wr[..n]);
                let var_s = (s_wss - s_ws * s_ws / win.wsum).max(0.0);
                let den = (win.var * var_s).sqrt();
                if den > 1e-10 {
                    (1.0 - s_wrs / den).clamp(0.0, 2.0)
                } else {
                    FLAT_COST
                }
            };
            if self.p.geometric {
                if let Some(dv) = &src.depth {
                    cost += self.o.geom_weight * self.reprojection_error(xf, yf, point, src, dv);
                }
            }
            view_costs[s] = cost;
        }
        let costs = &mut view_costs[..nsrc.max(1)];
        let k = self.o.best_views.clamp(1, costs.len());
        // Partial selection of the k smallest (k and the view count are small).
        for i in 0..k {
            let mut m = i;
            for j in i + 1..costs.len() {
                if costs[j] < costs[m] {
                    m = j;
                }
            }
            costs.swap(i, m);
        }
        let mut total = costs[..k].iter().sum::<f32>() / k as f32;
        if let Some(prior) = &self.p.prior {
            total += self.prior_cost(prior, x, y, d, n);
        }
        total
    }

    /// ACMM's forward-backward reprojection error (pixels, capped) of `point` through `src`.
    fn reprojection_error(&self, xf: f32, yf: f32, point: Vec3, src: &Source, dv: &DepthView) -> f32 {
        let cap = self.o.geom_max_error;
        let ps = src.r * point + src.t;
        if ps.z <= 0.0 {
            return cap;
        }
        let (u, v) = dv.k.project(ps);
        let (ui, vi) = (u.round(), v.round());
        if !(ui >= 0.0 && vi >= 0.0 && (ui as usize) < dv.depth.width() && (vi as usize) < dv.depth.height()) {
            return cap;
        }
        let ds = *dv.depth.get(ui as usize, vi as usize);
        if ds.is_nan() || ds <= 0.0 {
            return cap;
        }
        let back = dv.k.ray(ui, vi) * ds;
        let pr = src.r.transpose() * (back - src.t);
        if pr.z <= 0.0 {
            return cap;
        }
        let (ur, vr) = self.p.k.project(pr);
        ((ur - xf).powi(2) + (vr - yf).powi(2)).sqrt().min(cap)
    }

    fn prior_cost(&self, prior: &Prior, x: usize, y: usize, d: f32, n: Vec3) -> f32 {
        let w = *prior.weight.get(x, y) * self.o.prior_weight;
        let dp = *prior.depth.get(x, y);
        if !(w > 0.0 && dp > 0.0 && dp.is_finite()) {
            return 0.0;
        }
        let rel = (d - dp) / (dp * self.o.prior_depth_tolerance);
        let depth_term = (rel * rel).min(1.0);
        let np = *prior.normals.get(x, y);
        let normal_term =
            if np.length_squared() > 0.5 { ((1.0 - n.dot(np)) / (1.0 - self.prior_cos_tol)).min(1.0) } else { 0.0 };
        0.5 * w * (depth_term + normal_term)
    }

    /// A random depth (uniform in inverse depth over the range).
    fn random_depth(&self, rng: &mut Rng) -> f32 {
        let (near, far) = self.p.depth_range;
        let (a, b) = (1.0 / near, 1.0 / far);
        1.0 / (b + (a - b) * rng.unit())
    }

    /// A random normal facing the camera at pixel `(x, y)`.
    fn random_normal(&self, rng: &mut Rng, x: usize, y: usize) -> Vec3 {
        let ray = self.p.k.ray(x as f32, y as f32).normalize();
        loop {
            let v = Vec3::new(rng.signed(), rng.signed(), rng.signed());
            let l = v.length_squared();
            if l > 1e-4 && l <= 1.0 {
                let n = v / l.sqrt();
                let n = if n.dot(ray) > 0.0 { -n } else { n };
                // Planes seen nearly edge-on induce degenerate windows.
                if n.dot(ray) < -0.1 {
                    return n;
                }
            }
        }
    }

    /// `n` tilted by a random amount up to `amount` (radians-ish), kept facing the camera.
    fn perturb_normal(&self, rng: &mut Rng, n: Vec3, amount: f32, x: usize, y: usize) -> Vec3 {
        let ray = self.p.k.ray(x as f32, y as f32).normalize();
        for _ in 0..4 {
            let m = (n + Vec3::new(rng.signed(), rng.signed(), rng.signed()) * amount).normalize();
            if m.dot(ray) < -0.1 {
                return m;
            }
        }
        n
    }

    fn clamp_depth(&self, d: f32) -> f32 {
        let (near, far) = self.p.depth_range;
        d.clamp(near, far)
    }

    /// One pixel's update: propagation from the other colour's best neighbours, then refinement.
    #[allow(clippy::too_many_arguments)]
    fn update(&self, x: usize, y: usize, cur: Hyp, other: &[Hyp], pw: usize, iter: usize, explore: bool) -> Hyp {
        let win = self.win.at(self.p.image, x, y);
        let mut best = cur;
        if !best.cost.is_finite() {
            best.cost = self.cost(x, y, &win, best.depth, best.normal);
        }
        // Propagation: in each of 4 directions the best of the near (1, 3, 5 px) and of the
        // far (7 .. 23 px) candidates, all of the other colour.
        const NEAR: [i32; 3] = [1, 3, 5];
        const FAR: [i32; 5] = [7, 11, 15, 19, 23];
        let (w, h) = (self.width as i32, self.height as i32);
        let at = |xx: i32, yy: i32| -> Option<Hyp> {
            (xx >= 0 && yy >= 0 && xx < w && yy < h).then(|| other[yy as usize * pw + xx as usize / 2])
        };
        for (dx, dy) in [(1i32, 0i32), (-1, 0), (0, 1), (0, -1)] {
            for group in [&NEAR[..], &FAR[..]] {
                let mut cand: Option<(Hyp, i32, i32)> = None;
                for &k in group {
                    let (xx, yy) = (x as i32 + dx * k, y as i32 + dy * k);
                    if let Some(hn) = at(xx, yy) {
                        if cand.is_none_or(|(c, _, _)| hn.cost < c.cost) {
                            cand = Some((hn, xx, yy));
                        }
                    }
                }
                if let Some((c, xx, yy)) = cand {
                    // The neighbour's plane, intersected with this pixel's ray.
                    let offset = c.normal.dot(self.p.k.ray(xx as f32, yy as f32) * c.depth);
                    let den = c.normal.dot(self.p.k.ray(x as f32, y as f32));
                    let d = if den < -1e-6 { offset / den } else { c.depth };
                    if d.is_finite() && d > 0.0 && (d != best.depth || c.normal != best.normal) {
                        let cost = self.cost(x, y, &win, d, c.normal);
                        if cost < best.cost {
                            best = Hyp { depth: d, normal: c.normal, cost };
                        }
                    }
                }
            }
        }
        // Refinement: random and perturbed depths and normals, alone and together.
        let mut rng = Rng::new(self.seed, (y * self.width + x) as u64, iter as u64);
        let scale = 0.5f32.powi(iter as i32);
        let d_pert = self.clamp_depth(best.depth * (1.0 + 0.05 * scale * rng.signed()));
        let n_pert = self.perturb_normal(&mut rng, best.normal, 0.3 * scale, x, y);
        let mut tries: [(f32, Vec3); 6] = [(best.depth, best.normal); 6];
        let mut count = 0;
        if explore {
            let d_rand = self.random_depth(&mut rng);
            let n_rand = self.random_normal(&mut rng, x, y);
            tries[0] = (d_rand, best.normal);
            tries[1] = (best.depth, n_rand);
            tries[2] = (d_rand, n_rand);
            count = 3;
        }
        tries[count] = (d_pert, best.normal);
        tries[count + 1] = (best.depth, n_pert);
        tries[count + 2] = (d_pert, n_pert);
        count += 3;
        for &(d, n) in &tries[..count] {
            let cost = self.cost(x, y, &win, d, n);
            if cost < best.cost {
                best = Hyp { depth: d, normal: n, cost };
            }
        }
        if let Some(prior) = self.p.prior.as_ref().filter(|_| self.o.prior_weight > 0.0) {
            let dp = *prior.depth.get(x, y);
            let np = *prior.normals.get(x, y);
            if dp > 0.0 && dp.is_finite() && np.length_squared() > 0.5 && (dp != best.depth || np != best.normal) {
                let cost = self.cost(x, y, &win, dp, np);
                if cost < best.cost {
                    best = Hyp { depth: dp, normal: np, cost };
                }
            }
        }
        best
    }
}

/// Splits a map into its two checkerboard colours: colour `c` holds the pixels with
/// `(x + y) % 2 == c` at `y * pw + x / 2`.
fn split(map: &PlaneMap) -> [Vec<Hyp>; 2] {
    let pw = map.width.div_ceil(2);
    let blank = Hyp { depth: 0.0, normal: Vec3::ZERO, cost: f32::INFINITY };
    let mut out = [vec![blank; pw * map.height], vec![blank; pw * map.height]];
    for y in 0..map.height {
        for x in 0..map.width {
            out[(x + y) & 1][y * pw + x / 2] = map.hyps[y * map.width + x];
        }
    }
    out
}

fn join(planes: &[Vec<Hyp>; 2], width: usize, height: usize) -> PlaneMap {
    let pw = width.div_ceil(2);
    let mut hyps = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            hyps.push(planes[(x + y) & 1][y * pw + x / 2]);
        }
    }
    PlaneMap { width, height, hyps }
}

/// A random start: the prior where it has depth and normal, else random planes.
pub fn initial(problem: &Problem, o: &PatchMatchOptions, level_seed: u64) -> PlaneMap {
    let (width, height) = (problem.image.width(), problem.image.height());
    let solver = Solver::new(problem, o, level_seed);
    let mut hyps = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            let mut rng = Rng::new(level_seed ^ 0x5EED, (y * width + x) as u64, u64::MAX);
            let from_prior = problem.prior.as_ref().and_then(|p| {
                let (d, n) = (*p.depth.get(x, y), *p.normals.get(x, y));
                (o.prior_weight > 0.0 && d > 0.0 && d.is_finite() && n.length_squared() > 0.5).then_some((d, n))
            });
            let (depth, normal) =
                from_prior.unwrap_or_else(|| (solver.random_depth(&mut rng), solver.random_normal(&mut rng, x, y)));
            hyps.push(Hyp { depth, normal, cost: f32::INFINITY });
        }
    }
    PlaneMap { width, height, hyps }
}

impl<'a, 'p> Solver<'a, 'p> {
    fn new(p: &'p Problem<'a>, o: &'p PatchMatchOptions, seed: u64) -> Self {
        Self {
            p,
            o,
            win: Window::new(o),
            kinv: p.k.inverse(),
            ksrc: p.sources.iter().map(|s| s.k.matrix()).collect(),
            width: p.image.width(),
            height: p.image.height(),
            seed,
            prior_cos_tol: o.prior_normal_tolerance_deg.to_radians().cos(),
        }
    }
}

/// Runs `iterations` red-black sweeps from `start` (costs not finite are computed first);
/// `explore` adds random hypotheses to the refinement (the coarsest level).
pub fn solve(
    problem: &Problem,
    o: &PatchMatchOptions,
    start: PlaneMap,
    iterations: usize,
    explore: bool,
    level_seed: u64,
) -> PlaneMap {
    let solver = Solver::new(problem, o, level_seed);
    let (width, height) = (start.width, start.height);
    assert_eq!((width, height), (problem.image.width(), problem.image.height()), "start map of the level's size");
    let pw = width.div_ceil(2);
    let mut planes = split(&start);
    // Every start hypothesis scored before any propagation reads its cost.
    for (c, plane) in planes.iter_mut().enumerate() {
        plane.par_chunks_mut(pw).enumerate().for_each(|(y, row)| {
            for (i, hyp) in row.iter_mut().enumerate() {
                let x = 2 * i + ((y + c) & 1);
                if x < width && !hyp.cost.is_finite() {
                    let win = solver.win.at(problem.image, x, y);
                    hyp.cost = solver.cost(x, y, &win, hyp.depth, hyp.normal);
                }
            }
        });
    }
    for iter in 0..iterations {
        for c in 0..2 {
            let (a, b) = planes.split_at_mut(1);
            let (mine, other) = if c == 0 { (&mut a[0], &b[0]) } else { (&mut b[0], &a[0]) };
            mine.par_chunks_mut(pw).enumerate().for_each(|(y, row)| {
                for (i, hyp) in row.iter_mut().enumerate() {
                    let x = 2 * i + ((y + c) & 1);
                    if x < width {
                        *hyp = solver.update(x, y, *hyp, other, pw, iter, explore);
                    }
                }
            });
        }
    }
    join(&planes, width, height)
}
