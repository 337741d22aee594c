//! DUSt3R-style global alignment (spec section 6.1), natively: pairwise pointmaps (both views
//! in the first view's camera frame, each pair in its own similarity frame) become one scene of
//! cameras (OpenCV frame, camera-to-world), focals and depth maps.
//!
//! * **Initialisation ("mst"):** the maximum spanning tree of pair scores
//!   `mean(conf_i) * mean(conf_j)`, from the strongest pair (which fixes the world frame at its
//!   first camera), propagated with confidence-weighted Procrustes including scale. Focal by
//!   Weiszfeld on each image's own-frame pointmap, pose and depth scale by Procrustes of that
//!   pointmap onto the propagated points.
//! * **Optimisation:** Adam over per-image log-depth (on a pixel grid), rotation, translation
//!   and log-focal, and per-pair similarity (rotation, translation, log-scale with geometric mean
//!   fixed), minimising `sum w |X_k(p) - T_e(X^e_k(p))|` with `w = log(conf)`; gradients are
//!   analytic, rotations are updated on the manifold (`R <- exp(d) R`).
//! * **Output:** each image's depth at full resolution is the confidence-weighted average of
//!   every aligned pair prediction of it, seen from its optimised camera.

use crate::resection;
use crate::union_find::UnionFind;
use dens3r_geom::align::umeyama;
use dens3r_geom::focal::{focal_or_fallback, FALLBACK_HFOV_DEG};
use dens3r_geom::transform::{axis_angle, nearest_rotation, Sim3};
use dens3r_geom::{Intrinsics, PinholeCamera, Raster, Vec3};
use dens3r_optim::{AdamW, At, Decay, Schedule};
use glam::{DMat3, DMat4, DVec3};
use rayon::prelude::*;

/// One network run on the pair `(i, j)`: both pointmaps in camera `i`'s frame (up to the pair's
/// own scale), with their confidences. `pts_i` / `conf_i` have image `i`'s size, `pts_j` /
/// `conf_j` image `j`'s.
#[derive(Debug, Clone)]
pub struct PairPrediction {
    /// First view.
    pub i: usize,
    /// Second view.
    pub j: usize,
    /// View `i`'s points, camera-`i` frame.
    pub pts_i: Raster<Vec3>,
    /// View `j`'s points, camera-`i` frame.
    pub pts_j: Raster<Vec3>,
    /// View `i`'s confidence (>= 1 for Dens3R / DUSt3R).
    pub conf_i: Raster<f32>,
    /// View `j`'s confidence.
    pub conf_j: Raster<f32>,
}

/// How confidences become loss weights (DUSt3R `conf_trf`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfTransform {
    /// `log(c)` (the default; 0 for `c <= 1`).
    Log,
    /// `sqrt(c)`.
    Sqrt,
    /// `c - 1`.
    Minus1,
    /// `c`.
    Identity,
}

impl ConfTransform {
    /// The loss weight of confidence `c` (0 for non-finite `c`).
    pub fn weight(self, c: f32) -> f64 {
        let c = c as f64;
        if !c.is_finite() {
            return 0.0;
        }
        match self {
            ConfTransform::Log => c.max(1.0).ln(),
            ConfTransform::Sqrt => c.max(0.0).sqrt(),
            ConfTransform::Minus1 => (c - 1.0).max(0.0),
            ConfTransform::Identity => c.max(0.0),
        }
    }
}

/// Options of [`global_align`].
#[derive(Debug, Clone, PartialEq)]
pub struct AlignOptions {
    /// Adam iterations (DUSt3R: 300).
    pub iterations: usize,
    /// Initial learning rate (0.01).
    pub lr: f64,
    /// Final learning rate (1e-6), reached linearly or along a cosine.
    pub lr_min: f64,
    /// Cosine instead of linear decay.
    pub cosine: bool,
    /// Confidence to weight.
    pub conf: ConfTransform,
    /// Pixels per image optimised (a regular grid); full-resolution depth comes from the
    /// aligned pair predictions.
    pub grid_points: usize,
    /// Optimise focals (otherwise the Weiszfeld estimates are kept).
    pub optimize_focal: bool,
    /// Known focal lengths per image (pixels at its size; from EXIF or the user), used as they
    /// are and never optimised; images without an entry, or with `None`, are estimated.
    pub focals: Vec<Option<f64>>,
    /// Known camera-to-world rotations per image, in one common frame of their own (e.g.
    /// averaged from keypoint-matched pairs, [`crate::average_rotations`]): turned as one into
    /// the initial cameras' frame and then kept, never optimised; images without an entry, or
    /// with `None`, are estimated.
    pub rotations: Vec<Option<DMat3>>,
    /// Images of one size whose focal is not known share one focal (one camera's photos, as
    /// COLMAP's single camera): it starts at the median of their own estimates and is optimised
    /// as one parameter. Off estimates a focal per image, as DUSt3R does.
    pub shared_focal: bool,
}

impl Default for AlignOptions {
    fn default() -> Self {
        Self {
            iterations: 300,
            lr: 0.01,
            lr_min: 1e-6,
            cosine: false,
            conf: ConfTransform::Log,
            grid_points: 4096,
            optimize_focal: true,
            focals: Vec::new(),
            rotations: Vec::new(),
            shared_focal: false,
        }
    }
}

impl AlignOptions {
    /// Image `k`'s known focal ([`Self::focals`]), when it is a usable one (finite, positive):
    /// the alignment keeps it; the others it estimates.
    pub fn known_focal(&self, k: usize) -> Option<f64> {
        self.focals.get(k).copied().flatten().filter(|f| f.is_finite() && *f > 0.0)
    }

    /// The group of images that share one focal with image `k` (in order; `k` alone where its
    /// focal is known or [`Self::shared_focal`] is off): the images of its size with no known
    /// focal.
    fn focal_group(&self, sizes: &[(usize, usize)], k: usize) -> Vec<usize> {
        if !self.shared_focal || self.known_focal(k).is_some() {
            return vec![k];
        }
        (0..sizes.len()).filter(|&m| sizes[m] == sizes[k] && self.known_focal(m).is_none()).collect()
    }

    /// Image `k`'s known rotation ([`Self::rotations`]).
    fn known_rotation(&self, k: usize) -> Option<DMat3> {
        self.rotations.get(k).copied().flatten().filter(|r| r.is_finite())
    }
}

/// Why alignment could not run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GlobalAlignError {
    /// A pair or image list is malformed.
    #[error("global alignment: {0}")]
    Input(String),
    /// The pairs do not connect every image.
    #[error("global alignment: images {0:?} share no pair with the rest; add pairs that connect them")]
    Disconnected(Vec<usize>),
    /// A Procrustes or focal step had too few valid points.
    #[error("global alignment: {0}")]
    Degenerate(String),
}

/// One aligned image.
#[derive(Debug, Clone)]
pub struct AlignedView {
    /// Intrinsics (principal point at the centre) and camera-to-world pose, OpenCV frame.
    pub camera: PinholeCamera,
    /// Full-resolution z-depth in this camera (0 = invalid).
    pub depth: Raster<f32>,
    /// Largest confidence any pair gave the pixel.
    pub conf: Raster<f32>,
}

/// The aligned scene.
#[derive(Debug, Clone)]
pub struct Alignment {
    /// One per input image, in input order.
    pub views: Vec<AlignedView>,
    /// Per pair (input order): the similarity taking its frame into the world.
    pub pair_transforms: Vec<Sim3>,
    /// Weighted mean 3-D residual before and after optimisation (world units).
    pub loss: (f64, f64),
    /// Fallbacks taken (a camera or focal no pointmap supported), for the user to see.
    pub warnings: Vec<String>,
}

type Grad = (DVec3, DVec3); // (rotation tangent, translation)

/// Adam as DUSt3R's global alignment runs it (betas 0.9 and 0.9), in f64.
const ADAM: AdamW<f64> = AdamW { beta1: 0.9, beta2: 0.9, eps: 1e-8, weight_decay: 0.0 };

/// Adam moments of one parameter vector.
#[derive(Clone)]
struct Adam {
    m: Vec<f64>,
    v: Vec<f64>,
}

impl Adam {
    fn new(n: usize) -> Self {
        Self { m: vec![0.0; n], v: vec![0.0; n] }
    }
    /// Returns the steps (to subtract) for gradient `g` at iteration `t` (1-based).
    fn step(&mut self, g: &[f64], lr: f64, t: i32) -> Vec<f64> {
        let mut out = vec![0.0; g.len()];
        ADAM.steps(At::new(t as usize - 1, lr), &mut self.m, &mut self.v, g, &mut out);
        out
    }
}

/// A similarity `s R x + t` with Adam state for (rotation, translation, log-scale).
#[derive(Clone)]
struct Pose {
    r: DMat3,
    t: DVec3,
    adam: Adam,
}

impl Pose {
    fn new(r: DMat3, t: DVec3) -> Self {
        Self { r, t, adam: Adam::new(6) }
    }
    fn update(&mut self, g: Grad, lr: f64, it: i32) {
        let s = self.adam.step(&[g.0.x, g.0.y, g.0.z, g.1.x, g.1.y, g.1.z], lr, it);
        let d = DVec3::new(-s[0], -s[1], -s[2]);
        if d.length() > 0.0 {
            self.r = nearest_rotation(axis_angle(d, d.length()) * self.r);
        }
        self.t -= DVec3::new(s[3], s[4], s[5]);
    }
}

/// The grid pixels optimised in a `w x h` image.
fn grid(w: usize, h: usize, points: usize) -> Vec<(usize, usize)> {
    let stride = (((w * h) as f64 / points.max(1) as f64).sqrt().ceil() as usize).max(1);
    let mut px = Vec::new();
    let mut y = stride / 2;
    while y < h {
        let mut x = stride / 2;
        while x < w {
            px.push((x, y));
            x += stride;
        }
        y += stride;
    }
    px
}

fn dv(p: Vec3) -> DVec3 {
    p.as_dvec3()
}

/// A usable pair-frame point (pair frames are arbitrary, so only finiteness is required).
fn valid(p: Vec3) -> bool {
    p.is_finite()
}

/// Aligns pairwise predictions over `sizes.len()` images (`sizes[k]` = (width, height)).
/// `progress(iteration, loss)` is called during optimisation.
pub fn global_align(
    sizes: &[(usize, usize)],
    pairs: &[PairPrediction],
    opts: &AlignOptions,
    progress: impl FnMut(usize, f64),
) -> Result<Alignment, GlobalAlignError> {
    check_inputs(sizes, pairs)?;
    let n = sizes.len();
    // Loss weights per pair side, and pair scores.
    let weights = |pts: &Raster<Vec3>, conf: &Raster<f32>| -> Vec<f64> {
        pts.data().iter().zip(conf.data()).map(|(&p, &c)| if valid(p) { opts.conf.weight(c) } else { 0.0 }).collect()
    };
    let w: Vec<[Vec<f64>; 2]> =
        pairs.iter().map(|p| [weights(&p.pts_i, &p.conf_i), weights(&p.pts_j, &p.conf_j)]).collect();
    let mean_conf = |c: &Raster<f32>| {
        let v: Vec<f64> = c.data().iter().filter(|c| c.is_finite()).map(|&c| c as f64).collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    let score: Vec<f64> = pairs.iter().map(|p| mean_conf(&p.conf_i) * mean_conf(&p.conf_j)).collect();

    let world = spanning_tree_points(n, pairs, &w, &score)?;
    let mut init = initial_cameras(sizes, pairs, &w, &score, world)?;
    let groups: Vec<Vec<usize>> = (0..n).map(|k| opts.focal_group(sizes, k)).collect();
    let estimates = init.focal.clone();
    for (k, f) in init.focal.iter_mut().enumerate() {
        if let Some(known) = opts.known_focal(k) {
            *f = known;
        } else {
            let mut own: Vec<f64> = groups[k].iter().map(|&m| estimates[m]).collect();
            *f = dens3r_geom::focal::median(&mut own).unwrap_or(estimates[k]);
        }
    }
    // Known rotations: the one rotation `g` taking their frame into the initial cameras' frame
    // (least squares over the images that have one), then kept.
    let known: Vec<(usize, DMat3)> = (0..n).filter_map(|k| opts.known_rotation(k).map(|r| (k, r))).collect();
    if !known.is_empty() {
        let sum = known.iter().fold(DMat3::ZERO, |acc, &(k, r)| acc + init.poses[k].r * r.transpose());
        let g = nearest_rotation(sum);
        for &(k, r) in &known {
            init.poses[k].r = g * r;
        }
    }
    let grids: Vec<Vec<(usize, usize)>> = sizes.iter().map(|&(wk, hk)| grid(wk, hk, opts.grid_points)).collect();
    let (problem, mut state, g) = Problem::new(sizes, pairs, &w, grids, &init)?;
    let (loss0, last) = problem.optimise(&mut state, opts, &groups, progress);
    let (views, pair_transforms) = outputs(sizes, pairs, &w, &problem, &state, g);
    Ok(Alignment { views, pair_transforms, loss: (loss0 / g, last / g), warnings: init.warnings })
}

/// Refuses pair lists that do not fit the images.
fn check_inputs(sizes: &[(usize, usize)], pairs: &[PairPrediction]) -> Result<(), GlobalAlignError> {
    let n = sizes.len();
    let bad = |m: String| Err(GlobalAlignError::Input(m));
    if n < 2 {
        return bad(format!("needs at least 2 images, got {n}"));
    }
    for (e, p) in pairs.iter().enumerate() {
        if p.i >= n || p.j >= n || p.i == p.j {
            return bad(format!("pair {e} is ({}, {}) over {n} images", p.i, p.j));
        }
        let dims = |r: (usize, usize), k: usize, what: &str| -> Result<(), GlobalAlignError> {
            if r != sizes[k] {
                return Err(GlobalAlignError::Input(format!(
                    "pair {e} ({}, {}): {what} is {}x{}, image {k} is {}x{}",
                    p.i, p.j, r.0, r.1, sizes[k].0, sizes[k].1
                )));
            }
            Ok(())
        };
        dims((p.pts_i.width(), p.pts_i.height()), p.i, "pts_i")?;
        dims((p.conf_i.width(), p.conf_i.height()), p.i, "conf_i")?;
        dims((p.pts_j.width(), p.pts_j.height()), p.j, "pts_j")?;
        dims((p.conf_j.width(), p.conf_j.height()), p.j, "conf_j")?;
    }
    if let Some(k) = (0..n).find(|&k| !pairs.iter().any(|p| p.i == k)) {
        return bad(format!(
            "image {k} is never the first view of a pair, so no pointmap is in its own frame: add ({k}, j) pairs (symmetrize the pair graph)"
        ));
    }
    Ok(())
}

/// `r`'s valid points through `t` (NaN elsewhere).
fn to_world(r: &Raster<Vec3>, t: &Sim3) -> Vec<DVec3> {
    r.data().iter().map(|&p| if valid(p) { t.apply(dv(p)) } else { DVec3::NAN }).collect()
}

/// The weighted similarity taking `src`'s valid points onto `dst`.
fn procrustes(src: &Raster<Vec3>, dst: &[DVec3], w: &[f64]) -> Result<Sim3, GlobalAlignError> {
    let (mut s, mut d, mut ww) = (Vec::new(), Vec::new(), Vec::new());
    for ((&p, &q), &wk) in src.data().iter().zip(dst).zip(w) {
        if wk > 0.0 && valid(p) && q.is_finite() {
            s.push(dv(p));
            d.push(q);
            ww.push(wk);
        }
    }
    umeyama(&s, &d, Some(&ww), true).map_err(|e| GlobalAlignError::Degenerate(e.to_string()))
}

/// Stage 1: the maximum spanning tree of pair scores (Kruskal), propagated from the strongest pair
/// (whose frame becomes the world's): every image's points in the world.
fn spanning_tree_points(
    n: usize,
    pairs: &[PairPrediction],
    w: &[[Vec<f64>; 2]],
    score: &[f64],
) -> Result<Vec<Vec<DVec3>>, GlobalAlignError> {
    let mut order: Vec<usize> = (0..pairs.len()).collect();
    order.sort_by(|&a, &b| score[b].total_cmp(&score[a]));
    let mut uf = UnionFind::new(n);
    let tree: Vec<usize> = order.into_iter().filter(|&e| uf.union(pairs[e].i, pairs[e].j)).collect();
    let root = uf.find(0);
    let lost: Vec<usize> = (0..n).filter(|&k| uf.find(k) != root).collect();
    if !lost.is_empty() {
        return Err(GlobalAlignError::Disconnected(lost));
    }
    let mut world: Vec<Option<Vec<DVec3>>> = vec![None; n];
    let first = &pairs[tree[0]];
    world[first.i] = Some(to_world(&first.pts_i, &Sim3::IDENTITY));
    world[first.j] = Some(to_world(&first.pts_j, &Sim3::IDENTITY));
    let mut pending: Vec<usize> = tree[1..].to_vec();
    while !pending.is_empty() {
        let before = pending.len();
        let mut k = 0;
        while k < pending.len() {
            let e = pending[k];
            let p = &pairs[e];
            let (known, new) = match (world[p.i].is_some(), world[p.j].is_some()) {
                (true, false) => (0, 1),
                (false, true) => (1, 0),
                _ => {
                    k += 1;
                    continue;
                }
            };
            let sides = [(&p.pts_i, p.i), (&p.pts_j, p.j)];
            let t = procrustes(sides[known].0, world[sides[known].1].as_ref().unwrap(), &w[e][known])?;
            world[sides[new].1] = Some(to_world(sides[new].0, &t));
            pending.swap_remove(k);
        }
        if pending.len() == before {
            break; // unreachable for a spanning tree
        }
    }
    Ok(world.into_iter().map(|p| p.expect("a spanning tree reaches every image")).collect())
}

/// Each image's starting camera.
struct InitialCameras {
    focal: Vec<f64>,
    poses: Vec<Pose>,
    /// Depth scale of each camera-frame pointmap in the world.
    scale: Vec<f64>,
    /// Each image's own pointmap in its camera frame.
    cam_pts: Vec<Raster<Vec3>>,
    warnings: Vec<String>,
}

/// Stage 2: per image, from its strongest own pair (view k first): the camera in the pair's frame by
/// resection, so the pair frame need not be camera k's; the focal by Weiszfeld on the
/// camera-frame pointmap; pose and depth scale by Procrustes onto the propagated points
/// (world point = s R x_cam + t, so the depth is s z).
fn initial_cameras(
    sizes: &[(usize, usize)],
    pairs: &[PairPrediction],
    w: &[[Vec<f64>; 2]],
    score: &[f64],
    world: Vec<Vec<DVec3>>,
) -> Result<InitialCameras, GlobalAlignError> {
    let n = sizes.len();
    let mut init = InitialCameras {
        focal: vec![0.0f64; n],
        poses: Vec::with_capacity(n),
        scale: vec![1.0f64; n],
        cam_pts: Vec::with_capacity(n),
        warnings: Vec::new(),
    };
    for k in 0..n {
        let e = (0..pairs.len()).filter(|&e| pairs[e].i == k).max_by(|&a, &b| score[a].total_cmp(&score[b])).unwrap();
        let (wk, hk) = sizes[k];
        let pts = &pairs[e].pts_i;
        let samples = resection::pointmap_samples(pts, |i| w[e][0][i], 20_000);
        if samples.len() < 6 {
            return Err(GlobalAlignError::Degenerate(format!(
                "image {k}: {} confident points in its own pair frame, too few to place its camera",
                samples.len()
            )));
        }
        // A pointmap no camera explains (untrained weights) keeps the pair frame as the camera
        // frame, which is what Dens3R outputs anyway.
        let (rot, tr) = match resection::pointmap_camera(pts, &samples) {
            Some(c) => c,
            None => {
                init.warnings.push(format!(
                    "image {k}: no camera explains its pointmap; taking the pair frame as its camera frame"
                ));
                (DMat3::IDENTITY, DVec3::ZERO)
            }
        };
        let cam = pts.map(|&q| if valid(q) { (rot * dv(q) + tr).as_vec3() } else { Vec3::NAN });
        init.focal[k] = focal_or_fallback(&cam, wk, hk).unwrap_or_else(|f| {
            init.warnings.push(format!(
                "image {k}: its pointmap gives no positive focal (untrained weights?); starting from a {FALLBACK_HFOV_DEG}-degree field of view"
            ));
            f
        });
        let t = procrustes(&cam, &world[k], &w[e][0])?;
        init.scale[k] = t.scale;
        init.poses.push(Pose::new(t.rotation, t.translation));
        init.cam_pts.push(cam);
    }
    Ok(init)
}

/// What is optimised: per image log-depth on its grid, pose and log-focal; per pair its
/// similarity (rotation, translation, log-scale) with Adam state.
struct State {
    logd: Vec<Vec<f64>>,
    logf: Vec<f64>,
    poses: Vec<Pose>,
    pair_pose: Vec<Pose>,
    log_s: Vec<f64>,
}

/// The fixed parts of the problem: where each image is sampled and which pair sides see it.
struct Problem {
    sizes: Vec<(usize, usize)>,
    /// Grid pixel offsets from the principal point, per image.
    offsets: Vec<Vec<(f64, f64)>>,
    /// Grid samples of each pair side: (grid index, point, weight).
    samples: Vec<[Vec<(usize, DVec3, f64)>; 2]>,
    /// Per image: its (pair, side) occurrences.
    sides_of: Vec<Vec<(usize, usize)>>,
    total_w: f64,
    /// Initial mean log pair scale (the gauge of scale).
    mean_log_s0: f64,
}

/// One image's share of the loss and its gradients.
struct ImageGrad {
    loss: f64,
    pose: Grad,
    logd: Vec<f64>,
    logf: f64,
    pairs: Vec<(usize, Grad, f64)>, // (pair, pose grad, log-scale grad)
}

impl Problem {
    /// Stages 3 and 4: grids, initial depths, and a global scale `g` that makes the median
    /// depth 1; then pair similarities onto the initial world points.
    fn new(
        sizes: &[(usize, usize)],
        pairs: &[PairPrediction],
        w: &[[Vec<f64>; 2]],
        grids: Vec<Vec<(usize, usize)>>,
        init: &InitialCameras,
    ) -> Result<(Self, State, f64), GlobalAlignError> {
        let n = sizes.len();
        let mut logd: Vec<Vec<f64>> = (0..n)
            .map(|k| {
                let p = &init.cam_pts[k];
                grids[k]
                    .iter()
                    .map(|&(x, y)| {
                        let q = *p.get(x, y);
                        if q.is_finite() && q.z > 0.0 {
                            (init.scale[k] * q.z as f64).ln()
                        } else {
                            f64::NAN
                        }
                    })
                    .collect()
            })
            .collect();
        // Fill invalid grid depths with the image's median so every parameter is finite.
        for d in logd.iter_mut() {
            let mut v: Vec<f64> = d.iter().copied().filter(|x| x.is_finite()).collect();
            let med = dens3r_geom::focal::median(&mut v).unwrap_or(0.0);
            d.iter_mut().filter(|x| !x.is_finite()).for_each(|x| *x = med);
        }
        let mut all: Vec<f64> = logd.iter().flatten().copied().collect();
        let g = (-dens3r_geom::focal::median(&mut all).unwrap_or(0.0)).exp(); // world scale factor
        let mut poses = init.poses.clone();
        for (k, d) in logd.iter_mut().enumerate() {
            d.iter_mut().for_each(|x| *x += g.ln());
            poses[k].t *= g;
        }
        let logf: Vec<f64> = init.focal.iter().map(|f| f.ln()).collect();
        // Pixel rays at the grid, camera frame, for focal f: ((x - cx) / f, (y - cy) / f, 1).
        let offsets: Vec<Vec<(f64, f64)>> = (0..n)
            .map(|k| {
                let (wk, hk) = sizes[k];
                grids[k].iter().map(|&(x, y)| (x as f64 - wk as f64 / 2.0, y as f64 - hk as f64 / 2.0)).collect()
            })
            .collect();
        let samples: Vec<[Vec<(usize, DVec3, f64)>; 2]> = pairs
            .iter()
            .zip(w)
            .map(|(p, w)| {
                let side = |pts: &Raster<Vec3>, ws: &[f64], k: usize| {
                    grids[k]
                        .iter()
                        .enumerate()
                        .filter_map(|(gi, &(x, y))| {
                            let q = *pts.get(x, y);
                            let wk = ws[y * pts.width() + x];
                            (wk > 0.0 && valid(q)).then_some((gi, dv(q), wk))
                        })
                        .collect::<Vec<_>>()
                };
                [side(&p.pts_i, &w[0], p.i), side(&p.pts_j, &w[1], p.j)]
            })
            .collect();
        let sides_of: Vec<Vec<(usize, usize)>> = (0..n)
            .map(|k| {
                (0..pairs.len())
                    .flat_map(|e| [(e, 0), (e, 1)])
                    .filter(|&(e, s)| [pairs[e].i, pairs[e].j][s] == k)
                    .collect()
            })
            .collect();
        let total_w: f64 =
            samples.iter().flat_map(|s| s.iter()).flat_map(|s| s.iter()).map(|s| s.2).sum::<f64>().max(1e-300);
        let mut problem = Self { sizes: sizes.to_vec(), offsets, samples, sides_of, total_w, mean_log_s0: 0.0 };
        let mut state = State { logd, logf, poses, pair_pose: Vec::with_capacity(pairs.len()), log_s: Vec::new() };
        problem.initial_pair_poses(pairs, &mut state)?;
        // Pair scales with their geometric mean held at the initial one.
        problem.mean_log_s0 = state.log_s.iter().sum::<f64>() / state.log_s.len() as f64;
        Ok((problem, state, g))
    }

    /// Each pair's similarity onto the initial world points of both its views.
    fn initial_pair_poses(&self, pairs: &[PairPrediction], state: &mut State) -> Result<(), GlobalAlignError> {
        let cam: Vec<Vec<DVec3>> = (0..self.sizes.len()).map(|k| self.camera_points(k, state)).collect();
        for (e, p) in pairs.iter().enumerate() {
            let (mut s, mut d, mut ww) = (Vec::new(), Vec::new(), Vec::new());
            for (side, k) in [(0, p.i), (1, p.j)] {
                for &(gi, q, wk) in &self.samples[e][side] {
                    s.push(q);
                    d.push(state.poses[k].r * cam[k][gi] + state.poses[k].t);
                    ww.push(wk);
                }
            }
            let t = umeyama(&s, &d, Some(&ww), true)
                .map_err(|err| GlobalAlignError::Degenerate(format!("pair ({}, {}): {err}", p.i, p.j)))?;
            state.pair_pose.push(Pose::new(t.rotation, t.translation));
            state.log_s.push(t.scale.ln());
        }
        Ok(())
    }

    /// Image `k`'s grid points in its camera frame.
    fn camera_points(&self, k: usize, st: &State) -> Vec<DVec3> {
        let f = st.logf[k].exp();
        self.offsets[k].iter().zip(&st.logd[k]).map(|(&(u, v), &ld)| DVec3::new(u / f, v / f, 1.0) * ld.exp()).collect()
    }

    /// Pair scales with their geometric mean held at the initial one (the gauge of scale).
    fn pair_scales(&self, log_s: &[f64]) -> Vec<f64> {
        let mean = log_s.iter().sum::<f64>() / log_s.len() as f64;
        log_s.iter().map(|l| (l - mean + self.mean_log_s0).exp()).collect()
    }

    /// Loss and analytic gradients, per image (in parallel): its sides of every pair.
    fn gradients(&self, st: &State) -> Vec<ImageGrad> {
        let s = self.pair_scales(&st.log_s);
        (0..self.sizes.len())
            .into_par_iter()
            .map(|k| {
                let f = st.logf[k].exp();
                let (rk, tk) = (st.poses[k].r, st.poses[k].t);
                let mut out = ImageGrad {
                    loss: 0.0,
                    pose: (DVec3::ZERO, DVec3::ZERO),
                    logd: vec![0.0; st.logd[k].len()],
                    logf: 0.0,
                    pairs: Vec::new(),
                };
                for &(e, side) in &self.sides_of[k] {
                    let (re, te, se) = (st.pair_pose[e].r, st.pair_pose[e].t, s[e]);
                    let mut pg: Grad = (DVec3::ZERO, DVec3::ZERO);
                    let mut sg = 0.0;
                    for &(gi, q, wq) in &self.samples[e][side] {
                        let (u, v) = self.offsets[k][gi];
                        let d = st.logd[k][gi].exp();
                        let cam = DVec3::new(u / f, v / f, 1.0) * d;
                        let rc = rk * cam;
                        let x = rc + tk;
                        let sy = re * q * se;
                        let r = x - (sy + te);
                        let len = r.length();
                        out.loss += wq * len;
                        if len < 1e-12 {
                            continue;
                        }
                        let g = r * (wq / (len * self.total_w));
                        out.pose.0 += rc.cross(g);
                        out.pose.1 += g;
                        out.logd[gi] += g.dot(rc);
                        out.logf += g.dot(rk * DVec3::new(-u / f * d, -v / f * d, 0.0));
                        pg.0 += sy.cross(-g);
                        pg.1 -= g;
                        sg -= g.dot(sy);
                    }
                    out.pairs.push((e, pg, sg));
                }
                out.loss /= self.total_w;
                out
            })
            .collect()
    }

    /// Adam over every parameter for `opts.iterations` steps, each image's focal shared with its
    /// `groups` entry ([`AlignOptions::focal_group`]); the loss before and after.
    fn optimise(
        &self,
        st: &mut State,
        opts: &AlignOptions,
        groups: &[Vec<usize>],
        mut progress: impl FnMut(usize, f64),
    ) -> (f64, f64) {
        let (n, pairs) = (self.sizes.len(), self.samples.len());
        let mut adam_s = Adam::new(pairs);
        let mut adam_d: Vec<Adam> = st.logd.iter().map(|d| Adam::new(d.len())).collect();
        let mut adam_f = Adam::new(n);
        let mut loss0 = f64::NAN;
        let mut last = f64::NAN;
        let iters = opts.iterations;
        let decay = if opts.cosine { Decay::Cosine } else { Decay::Linear };
        let schedule = Schedule { peak: opts.lr, end: opts.lr_min, warmup_steps: 0, total: iters, decay };
        for it in 0..=iters {
            let grads = self.gradients(st);
            let loss: f64 = grads.iter().map(|g| g.loss).sum();
            if it == 0 {
                loss0 = loss;
            }
            last = loss;
            if it == iters {
                break;
            }
            progress(it, loss);
            let lr = schedule.at(it);
            let t = it as i32 + 1;
            let mut pg: Vec<Grad> = vec![(DVec3::ZERO, DVec3::ZERO); pairs];
            let mut sg = vec![0.0; pairs];
            let mut fg = vec![0.0; n];
            for (k, g) in grads.into_iter().enumerate() {
                let turn = if opts.known_rotation(k).is_some() { DVec3::ZERO } else { g.pose.0 };
                st.poses[k].update((turn, g.pose.1), lr, t);
                let step = adam_d[k].step(&g.logd, lr, t);
                st.logd[k].iter_mut().zip(step).for_each(|(d, s)| *d -= s);
                fg[k] = g.logf;
                for (e, gp, gs) in g.pairs {
                    pg[e].0 += gp.0;
                    pg[e].1 += gp.1;
                    sg[e] += gs;
                }
            }
            if opts.optimize_focal {
                // A shared focal's images each take the group's summed gradient: started equal,
                // they take equal Adam steps and stay one focal.
                let fg: Vec<f64> = groups.iter().map(|g| g.iter().map(|&m| fg[m]).sum()).collect();
                // DUSt3R optimises 20 log f: the same Adam step moves log f 20 times less.
                let step = adam_f.step(&fg, lr / 20.0, t);
                // Fields of view between about 1 and 168 degrees: a bound that only untrained
                // or broken predictions reach (they otherwise drive the focal to 0).
                for (k, (l, s)) in st.logf.iter_mut().zip(step).enumerate() {
                    if opts.known_focal(k).is_some() {
                        continue;
                    }
                    let side = self.sizes[k].0.max(self.sizes[k].1) as f64;
                    *l = (*l - s).clamp((0.05 * side).ln(), (50.0 * side).ln());
                }
            }
            // The mean log-scale is fixed: only deviations from it carry gradient.
            let mean_g = sg.iter().sum::<f64>() / sg.len() as f64;
            let sg: Vec<f64> = sg.iter().map(|g| g - mean_g).collect();
            let step = adam_s.step(&sg, lr, t);
            st.log_s.iter_mut().zip(step).for_each(|(l, s)| *l -= s);
            for (e, g) in pg.into_iter().enumerate() {
                st.pair_pose[e].update(g, lr, t);
            }
        }
        (loss0, last)
    }
}

/// Stage 5, the outputs: cameras in the input scale (undo `g`), full-resolution depth from every aligned
/// pair prediction of each image, and the pair similarities.
fn outputs(
    sizes: &[(usize, usize)],
    pairs: &[PairPrediction],
    w: &[[Vec<f64>; 2]],
    problem: &Problem,
    st: &State,
    g: f64,
) -> (Vec<AlignedView>, Vec<Sim3>) {
    let pair_transforms: Vec<Sim3> = st
        .pair_pose
        .iter()
        .zip(problem.pair_scales(&st.log_s))
        .map(|(p, s)| Sim3 { scale: s / g, rotation: p.r, translation: p.t / g })
        .collect();
    let views = (0..sizes.len())
        .into_par_iter()
        .map(|k| {
            let (wk, hk) = sizes[k];
            let f = st.logf[k].exp();
            let c2w = DMat4::from_mat3_translation(st.poses[k].r, st.poses[k].t / g);
            let w2c = dens3r_geom::camera::rigid_inverse(&c2w);
            let mut num = vec![0.0f64; wk * hk];
            let mut den = vec![0.0f64; wk * hk];
            let mut conf = Raster::filled(wk, hk, 0.0f32);
            let cc = conf.data_mut();
            for &(e, side) in &problem.sides_of[k] {
                let p = &pairs[e];
                let (pts, cf) = if side == 0 { (&p.pts_i, &p.conf_i) } else { (&p.pts_j, &p.conf_j) };
                for (idx, (&q, &c)) in pts.data().iter().zip(cf.data()).enumerate() {
                    let wq = w[e][side][idx];
                    if wq > 0.0 {
                        let z = w2c.transform_point3(pair_transforms[e].apply(dv(q))).z;
                        if z > 0.0 {
                            num[idx] += wq * z;
                            den[idx] += wq;
                        }
                    }
                    if c.is_finite() && c > cc[idx] {
                        cc[idx] = c;
                    }
                }
            }
            let depth = Raster::from_fn(wk, hk, |x, y| {
                let i = y * wk + x;
                if den[i] > 0.0 {
                    (num[i] / den[i]) as f32
                } else {
                    0.0
                }
            });
            let intrinsics = Intrinsics { fx: f, fy: f, cx: wk as f64 / 2.0, cy: hk as f64 / 2.0 };
            AlignedView { camera: PinholeCamera { intrinsics, width: wk, height: hk, cam_to_world: c2w }, depth, conf }
        })
        .collect();
    (views, pair_transforms)
}
