//! The dense stage over a set of views: working sizes, source views, PatchMatch coarse to
//! fine per reference (photometric, then geometric-consistency passes), fusion. Views are read
//! through [`ViewSource`] when needed (a few grey pyramids are cached), never all at once;
//! what is held for every view is its depth, normal and cost maps at the working size.

use crate::fusion::{fuse_view, fusion_partners, DepthNormalMap, FusedPoint};
use crate::image::{level_intrinsics, resize_view, working_size, Grey};
use crate::options::MvsOptions;
use crate::patch_match::{self, DepthView, Problem, Source, K};
use crate::views::{select_views, ViewSelection};
use dens3r_geom::{PinholeCamera, Raster};
use glam::{DVec3, Mat3, Vec3};
use image::RgbImage;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

/// Why the dense stage failed.
#[derive(Debug, thiserror::Error)]
pub enum MvsError {
    /// A view could not be read (the message names the file).
    #[error("{0}")]
    Input(String),
    /// The settings or the views cannot work (the message says which and what to change).
    #[error("{0}")]
    Setting(String),
}

/// The network's prediction for a view, at any size (resampled to the working size).
#[derive(Debug, Clone)]
pub struct PriorMaps {
    /// Depth on the cameras' scale (0 or NaN = none).
    pub depth: Raster<f32>,
    /// Camera-frame normals facing the camera.
    pub normals: Option<Raster<Vec3>>,
    /// The network's confidence (DUSt3R's, >= 1); none = fully trusted.
    pub conf: Option<Raster<f32>>,
}

/// Where the views come from (a scene folder, a COLMAP model, memory).
pub trait ViewSource: Sync {
    /// Number of views.
    fn len(&self) -> usize;
    /// Whether there are none.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// View `i`'s camera at its photo's full size.
    fn camera(&self, i: usize) -> PinholeCamera;
    /// View `i`'s name (for messages).
    fn name(&self, i: usize) -> String;
    /// View `i`'s photo.
    fn image(&self, i: usize) -> Result<RgbImage, MvsError>;
    /// View `i`'s network prior, if any.
    fn prior(&self, i: usize) -> Result<Option<PriorMaps>, MvsError>;
}

/// Progress of the dense stage, for a bar.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Photometric PatchMatch, view `done` of `total`.
    Photometric,
    /// Geometric-consistency pass.
    Geometric,
    /// Fusion.
    Fusion,
}

/// One view's output.
#[derive(Debug, Clone)]
pub struct ViewResult {
    /// The dense maps (all pixels PatchMatch solved, costs beside them).
    pub maps: DepthNormalMap,
    /// Pixels fusion kept.
    pub kept: Raster<bool>,
}

/// The dense stage's result.
#[derive(Debug, Clone)]
pub struct MvsResult {
    /// Per view.
    pub views: Vec<ViewResult>,
    /// Source views chosen per view.
    pub selection: Vec<ViewSelection>,
    /// Fused points (colour from their view's photo: `colors`).
    pub points: Vec<FusedPoint>,
    /// Colour of each fused point.
    pub colors: Vec<[u8; 3]>,
    /// Seconds of PatchMatch per view (photometric + geometric).
    pub seconds_per_view: Vec<f64>,
    /// Seconds of fusion.
    pub fusion_seconds: f64,
}

impl MvsResult {
    /// The filtered depth of view `i` (fusion's kept pixels only): what a TSDF should fuse.
    pub fn filtered_depth(&self, i: usize) -> Raster<f32> {
        let v = &self.views[i];
        Raster::from_fn(
            v.kept.width(),
            v.kept.height(),
            |x, y| if *v.kept.get(x, y) { *v.maps.depth.get(x, y) } else { 0.0 },
        )
    }

    /// Share of all working-size pixels fusion kept.
    pub fn kept_fraction(&self) -> f64 {
        let (k, n) = self.views.iter().fold((0usize, 0usize), |(k, n), v| {
            (k + v.kept.data().iter().filter(|b| **b).count(), n + v.kept.data().len())
        });
        k as f64 / n.max(1) as f64
    }
}

/// A view prepared for matching: its grey pyramid (level 0 = working size) and its prior there.
struct Prepared {
    pyramid: Vec<Grey>,
}

/// Views' grey pyramids, loaded on demand; at most `capacity` kept.
struct PyramidCache<'s> {
    source: &'s dyn ViewSource,
    sizes: Vec<(usize, usize)>,
    levels: usize,
    entries: HashMap<usize, Arc<Prepared>>,
    capacity: usize,
}

impl PyramidCache<'_> {
    fn get(&mut self, i: usize, keep: &[usize]) -> Result<Arc<Prepared>, MvsError> {
        if let Some(p) = self.entries.get(&i) {
            return Ok(p.clone());
        }
        if self.entries.len() >= self.capacity {
            self.entries.retain(|k, _| keep.contains(k));
        }
        let img = self.source.image(i)?;
        let cam = self.source.camera(i);
        if (img.width() as usize, img.height() as usize) != (cam.width, cam.height) {
            return Err(MvsError::Input(format!(
                "view '{}': the photo is {}x{} but its camera says {}x{}",
                self.source.name(i),
                img.width(),
                img.height(),
                cam.width,
                cam.height
            )));
        }
        let (small, _) = resize_view(&img, &cam.intrinsics, self.sizes[i]);
        let mut pyramid = vec![Grey::from_rgb(&small).smoothed()];
        for _ in 1..self.levels {
            let next = pyramid.last().expect("one level").half();
            pyramid.push(next);
        }
        let p = Arc::new(Prepared { pyramid });
        self.entries.insert(i, p.clone());
        Ok(p)
    }
}

/// The prior resampled (nearest) to `width` x `height`, and its weight from the confidence.
fn prior_at(p: &PriorMaps, width: usize, height: usize) -> (Raster<f32>, Raster<Vec3>, Raster<f32>) {
    let (pw, ph) = (p.depth.width(), p.depth.height());
    let (sx, sy) = (pw as f32 / width as f32, ph as f32 / height as f32);
    let idx = |x: usize, y: usize| -> (usize, usize) {
        let u = (((x as f32 + 0.5) * sx - 0.5).round().max(0.0) as usize).min(pw - 1);
        let v = (((y as f32 + 0.5) * sy - 0.5).round().max(0.0) as usize).min(ph - 1);
        (u, v)
    };
    let depth = Raster::from_fn(width, height, |x, y| {
        let (u, v) = idx(x, y);
        let d = *p.depth.get(u, v);
        if d > 0.0 && d.is_finite() {
            d
        } else {
            0.0
        }
    });
    let normals = Raster::from_fn(width, height, |x, y| {
        let (u, v) = idx(x, y);
        let n = p.normals.as_ref().map(|n| *n.get(u, v)).unwrap_or(Vec3::ZERO);
        if n.is_finite() && n.length_squared() > 0.5 {
            n.normalize()
        } else {
            Vec3::ZERO
        }
    });
    let weight = Raster::from_fn(width, height, |x, y| {
        let (u, v) = idx(x, y);
        match &p.conf {
            Some(c) => {
                let c = *c.get(u, v);
                if c.is_finite() && c > 1.0 {
                    1.0 - 1.0 / c
                } else {
                    0.0
                }
            }
            None => 1.0,
        }
    });
    (depth, normals, weight)
}

/// Halves a prior (nearest: the top-left pixel of each 2 x 2 block's nearest centre).
fn half_prior(p: &(Raster<f32>, Raster<Vec3>, Raster<f32>)) -> (Raster<f32>, Raster<Vec3>, Raster<f32>) {
    let (w, h) = ((p.0.width() / 2).max(1), (p.0.height() / 2).max(1));
    let at = |x: usize, y: usize| ((2 * x).min(p.0.width() - 1), (2 * y).min(p.0.height() - 1));
    (
        Raster::from_fn(w, h, |x, y| {
            let (u, v) = at(x, y);
            *p.0.get(u, v)
        }),
        Raster::from_fn(w, h, |x, y| {
            let (u, v) = at(x, y);
            *p.1.get(u, v)
        }),
        Raster::from_fn(w, h, |x, y| {
            let (u, v) = at(x, y);
            *p.2.get(u, v)
        }),
    )
}

/// World points a view sees, sampled from its prior depth on a grid of about `n` x `n`.
fn prior_points(cam: &PinholeCamera, p: &PriorMaps, n: usize) -> Vec<DVec3> {
    let (w, h) = (p.depth.width(), p.depth.height());
    let k = cam.intrinsics.scaled(w as f64 / cam.width as f64, h as f64 / cam.height as f64);
    let step = (w.max(h) / n).max(1);
    let mut out = Vec::new();
    for y in (step / 2..h).step_by(step) {
        for x in (step / 2..w).step_by(step) {
            let d = *p.depth.get(x, y) as f64;
            if d > 0.0 && d.is_finite() {
                out.push(cam.cam_to_world.transform_point3(k.unproject(x as f64, y as f64) * d));
            }
        }
    }
    out
}

/// Runs the dense stage on `source`. `points[i]`, when given, are world points view `i` sees
/// (SfM tracks); otherwise they are sampled from the priors, which then must exist.
/// `progress(stage, done, total)` is called after each view.
pub fn run_mvs(
    source: &dyn ViewSource,
    points: Option<Vec<Vec<DVec3>>>,
    o: &MvsOptions,
    mut progress: impl FnMut(Stage, usize, usize),
) -> Result<MvsResult, MvsError> {
    let n = source.len();
    if n < 2 {
        return Err(MvsError::Setting(format!("multi-view stereo needs at least 2 views; got {n}")));
    }
    let pm = &o.patch_match;
    if pm.window_radius == 0 || pm.window_step == 0 || {
        let per_side = 2 * pm.window_radius / pm.window_step + 1;
        per_side * per_side > patch_match::MAX_SAMPLES
    } {
        return Err(MvsError::Setting(format!(
            "window radius {} at step {} gives no window or more than {} samples",
            pm.window_radius,
            pm.window_step,
            patch_match::MAX_SAMPLES
        )));
    }
    let cams: Vec<PinholeCamera> = (0..n).map(|i| source.camera(i)).collect();
    let sizes: Vec<(usize, usize)> = cams.iter().map(|c| working_size(c.width, c.height, o.max_size)).collect();
    let work: Vec<PinholeCamera> = cams
        .iter()
        .zip(&sizes)
        .map(|(c, &(w, h))| PinholeCamera {
            intrinsics: c.intrinsics.scaled(w as f64 / c.width as f64, h as f64 / c.height as f64),
            width: w,
            height: h,
            cam_to_world: c.cam_to_world,
        })
        .collect();
    let points = match points {
        Some(p) => p,
        None => {
            let mut all = Vec::with_capacity(n);
            for (i, cam) in cams.iter().enumerate() {
                let Some(prior) = source.prior(i)? else {
                    return Err(MvsError::Setting(format!(
                        "view '{}' has no depth and no structure-from-motion points were given: multi-view stereo needs one of them for its depth range (run reconstruct or predict first, or pass a COLMAP model with points)",
                        source.name(i)
                    )));
                };
                all.push(prior_points(cam, &prior, 48));
            }
            all
        }
    };
    // PatchMatch matches each view against its best few; fusion checks its pixels against more
    // (a surface near one camera may be seen by views that score low over the whole image).
    let wide = select_views(&cams, &points, o.neighbours.max(o.fusion.partners));
    let fusion_lists: Vec<Vec<usize>> = wide.iter().map(|s| s.neighbours.clone()).collect();
    let selection: Vec<ViewSelection> = wide
        .into_iter()
        .map(|mut s| {
            let k = o.neighbours.min(patch_match::MAX_SOURCES);
            s.neighbours.truncate(k);
            s.scores.truncate(k);
            s
        })
        .collect();
    drop(points);
    let long = sizes.iter().map(|s| s.0.max(s.1)).max().unwrap_or(1);
    let mut levels = 1;
    while (long >> (levels - 1)) > pm.coarsest_size && levels < 6 {
        levels += 1;
    }
    let mut cache =
        PyramidCache { source, sizes: sizes.clone(), levels, entries: HashMap::new(), capacity: 2 * o.neighbours + 2 };
    let mut maps: Vec<Option<DepthNormalMap>> = vec![None; n];
    let mut seconds = vec![0.0; n];

    let rel = |i: usize, j: usize| -> (Mat3, Vec3) {
        let m = (work[j].world_to_cam() * work[i].cam_to_world).as_mat4();
        (Mat3::from_mat4(m), m.w_axis.truncate())
    };

    // Photometric pass, coarse to fine, one reference at a time. When geometric passes follow,
    // it stops one level short of the working size: the first geometric pass polishes the
    // upsampled planes at full size anyway, and the full-size photometric sweep would cost as
    // much again.
    let top = if pm.geom_iterations > 0 && levels > 1 { 1 } else { 0 };
    for i in 0..n {
        let t = Instant::now();
        let sel = &selection[i];
        let Some(range) = sel.depth_range else {
            progress(Stage::Photometric, i + 1, n);
            continue;
        };
        if sel.neighbours.is_empty() {
            progress(Stage::Photometric, i + 1, n);
            continue;
        }
        let mut keep: Vec<usize> = vec![i];
        keep.extend(&sel.neighbours);
        if let Some(next) = selection.get(i + 1) {
            keep.push(i + 1);
            keep.extend(&next.neighbours);
        }
        let refp = cache.get(i, &keep)?;
        let srcs: Vec<(usize, Arc<Prepared>)> =
            sel.neighbours.iter().map(|&j| cache.get(j, &keep).map(|p| (j, p))).collect::<Result<_, _>>()?;
        let prior0 = source.prior(i)?.map(|p| prior_at(&p, sizes[i].0, sizes[i].1));
        let mut priors = vec![prior0];
        for l in 1..levels {
            let next = priors[l - 1].as_ref().map(half_prior);
            priors.push(next);
        }
        let mut state: Option<patch_match::PlaneMap> = None;
        for l in (top..levels).rev() {
            let img = &refp.pyramid[l];
            let k = K::from(&level_intrinsics(&work[i].intrinsics, l));
            let sources: Vec<Source> = srcs
                .iter()
                .map(|(j, p)| {
                    let (r, t) = rel(i, *j);
                    Source {
                        image: &p.pyramid[l],
                        k: K::from(&level_intrinsics(&work[*j].intrinsics, l)),
                        r,
                        t,
                        depth: None,
                    }
                })
                .collect();
            let prior = priors[l].as_ref().map(|(d, nrm, w)| patch_match::Prior { depth: d, normals: nrm, weight: w });
            let problem = Problem { image: img, k, sources, prior, depth_range: range, geometric: false };
            let seed = pm.seed ^ ((i as u64) << 8) ^ l as u64;
            let (start, iters, explore) = match state.take() {
                None => (patch_match::initial(&problem, pm, seed), pm.coarse_iterations, true),
                Some(coarse) => {
                    let kc = K::from(&level_intrinsics(&work[i].intrinsics, l + 1));
                    (coarse.upsample(kc, k, img.width(), img.height()), pm.fine_iterations, false)
                }
            };
            state = Some(patch_match::solve(&problem, pm, start, iters, explore, seed));
        }
        let mut s = state.expect("at least one level");
        if top == 1 {
            let (k1, k0) = (K::from(&level_intrinsics(&work[i].intrinsics, 1)), K::from(&work[i].intrinsics));
            s = s.upsample(k1, k0, sizes[i].0, sizes[i].1);
        }
        maps[i] = Some(DepthNormalMap { camera: work[i], depth: s.depth(), normals: s.normals(), cost: s.costs() });
        seconds[i] = t.elapsed().as_secs_f64();
        progress(Stage::Photometric, i + 1, n);
    }

    // Geometric-consistency passes at the working size: each view against the others' maps of
    // the previous pass.
    for _ in 0..pm.geom_iterations {
        let depths: Vec<Option<Raster<f32>>> = maps.iter().map(|m| m.as_ref().map(|m| m.depth.clone())).collect();
        for i in 0..n {
            let t = Instant::now();
            let sel = &selection[i];
            let (Some(range), Some(current)) = (sel.depth_range, maps[i].as_ref()) else {
                progress(Stage::Geometric, i + 1, n);
                continue;
            };
            let mut keep: Vec<usize> = vec![i];
            keep.extend(&sel.neighbours);
            let refp = cache.get(i, &keep)?;
            let srcs: Vec<(usize, Arc<Prepared>)> =
                sel.neighbours.iter().map(|&j| cache.get(j, &keep).map(|p| (j, p))).collect::<Result<_, _>>()?;
            let prior = source.prior(i)?.map(|p| prior_at(&p, sizes[i].0, sizes[i].1));
            let k = K::from(&work[i].intrinsics);
            let sources: Vec<Source> = srcs
                .iter()
                .map(|(j, p)| {
                    let (r, t) = rel(i, *j);
                    let kj = K::from(&work[*j].intrinsics);
                    Source {
                        image: &p.pyramid[0],
                        k: kj,
                        r,
                        t,
                        depth: depths[*j].as_ref().map(|d| DepthView { depth: d, k: kj }),
                    }
                })
                .collect();
            let problem = Problem {
                image: &refp.pyramid[0],
                k,
                sources,
                prior: prior.as_ref().map(|(d, nrm, w)| patch_match::Prior { depth: d, normals: nrm, weight: w }),
                depth_range: range,
                geometric: true,
            };
            let start = patch_match::PlaneMap {
                width: current.depth.width(),
                height: current.depth.height(),
                hyps: current
                    .depth
                    .data()
                    .iter()
                    .zip(current.normals.data())
                    .map(|(&depth, &normal)| patch_match::Hyp { depth, normal, cost: f32::INFINITY })
                    .collect(),
            };
            let s = patch_match::solve(&problem, pm, start, pm.fine_iterations, false, pm.seed ^ 0xACC ^ i as u64);
            maps[i] = Some(DepthNormalMap { camera: work[i], depth: s.depth(), normals: s.normals(), cost: s.costs() });
            seconds[i] += t.elapsed().as_secs_f64();
            progress(Stage::Geometric, i + 1, n);
        }
    }
    drop(cache);

    // Fusion. Views PatchMatch could not solve (no depth range or partners) keep empty maps.
    let t = Instant::now();
    let maps: Vec<DepthNormalMap> = maps
        .into_iter()
        .enumerate()
        .map(|(i, m)| {
            m.unwrap_or_else(|| DepthNormalMap {
                camera: work[i],
                depth: Raster::filled(sizes[i].0, sizes[i].1, 0.0),
                normals: Raster::filled(sizes[i].0, sizes[i].1, Vec3::ZERO),
                cost: Raster::filled(sizes[i].0, sizes[i].1, f32::INFINITY),
            })
        })
        .collect();
    let partners = fusion_partners(&fusion_lists);
    let mut views = Vec::with_capacity(n);
    let mut points = Vec::new();
    let mut colors = Vec::new();
    for i in 0..n {
        let f = fuse_view(i, &maps, &partners[i], &o.fusion);
        if !f.points.is_empty() {
            let img = source.image(i)?;
            let (small, _) = resize_view(&img, &cams[i].intrinsics, sizes[i]);
            colors.extend(f.points.iter().map(|p| small.get_pixel(p.pixel.0, p.pixel.1).0));
        }
        points.extend(f.points);
        views.push(f.kept);
        progress(Stage::Fusion, i + 1, n);
    }
    let fusion_seconds = t.elapsed().as_secs_f64();
    let views = maps.into_iter().zip(views).map(|(maps, kept)| ViewResult { maps, kept }).collect();
    Ok(MvsResult { views, selection, points, colors, seconds_per_view: seconds, fusion_seconds })
}
