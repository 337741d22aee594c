//! The stages run in order: matches -> focals (known, else from the view graph's cycles) ->
//! verified edges -> rotation averaging -> tracks -> global positioning -> bundle adjustment
//! -> filtering by reprojection error and triangulation angle, rejected observations
//! re-admitted where they now fit (retriangulation) -> bundle adjustment again.

use crate::bundle_adjustment::{bundle_adjust, BaCamera, BaOptions, BaProblem};
use crate::global_positioning::{position, PositionOptions, Ray};
use crate::rotation_averaging::{average, RotationOptions};
use crate::tracks::{build_tracks, Track};
use crate::view_graph::{match_pairs, normalised, verify, Edge, PairMatches, ViewGraphOptions};
use dens3r_align::cycle_focal::{focal_from_cycles, CycleFocalOptions};
use dens3r_align::keypoints::Keypoints;
use dens3r_align::union_find::UnionFind;
use dens3r_geom::{Intrinsics, PinholeCamera};
use glam::{DMat4, DVec2, DVec3};
use std::time::Instant;

/// Structure-from-motion settings.
#[derive(Debug, Clone, PartialEq)]
pub struct SfmOptions {
    /// Matching and verification.
    pub view_graph: ViewGraphOptions,
    /// The focal at which the view graph's rotations close their cycles, for views of one size
    /// whose focal is not known; `None` starts from the guess.
    pub cycle_focal: Option<CycleFocalOptions>,
    /// Rotation averaging.
    pub rotations: RotationOptions,
    /// Global positioning.
    pub positions: PositionOptions,
    /// Bundle adjustment.
    pub ba: BaOptions,
    /// Observations reprojecting further than this (pixels) are dropped after adjustment.
    pub max_reprojection_px: f64,
    /// Points whose rays meet at under this angle (degrees) are dropped after adjustment.
    pub min_triangulation_deg: f64,
    /// A view keeping fewer observations than this is not registered.
    pub min_view_observations: usize,
}

impl Default for SfmOptions {
    fn default() -> Self {
        Self {
            view_graph: ViewGraphOptions::default(),
            cycle_focal: None,
            rotations: RotationOptions::default(),
            positions: PositionOptions::default(),
            ba: BaOptions::default(),
            max_reprojection_px: 4.0,
            min_triangulation_deg: 1.5,
            min_view_observations: 15,
        }
    }
}

/// What structure-from-motion starts from.
#[derive(Debug, Clone, Copy)]
pub struct SfmInput<'a> {
    /// Each view's keypoints (pixels, `(0, 0)` = the first pixel's centre).
    pub keypoints: &'a [Keypoints],
    /// Each view's size `(width, height)`; the principal point is its centre.
    pub sizes: &'a [(usize, usize)],
    /// Focals known (the user's): kept fixed.
    pub known_focals: &'a [Option<f64>],
    /// Focals to start from and draw towards (EXIF): refined by bundle adjustment with a weak
    /// prior ([`crate::bundle_adjustment::FOCAL_PRIOR_SIGMA`]), as COLMAP starts from EXIF
    /// focals without fixing them.
    pub prior_focals: &'a [Option<f64>],
    /// Starting focal of each view whose focal is not known (e.g. the network's estimate).
    pub focal_guess: &'a [f64],
    /// Candidate pairs to match.
    pub pairs: &'a [(usize, usize)],
}

/// Where a view's focal came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FocalSource {
    /// Given, kept.
    Known,
    /// Started from the view graph's cycles, refined by bundle adjustment.
    Cycles,
    /// Started from the guess, refined by bundle adjustment.
    Guess,
    /// Started from a prior focal (EXIF), refined by bundle adjustment with it as a prior.
    Prior,
}

/// A reconstructed point and the keypoints `(view, keypoint)` that see it.
#[derive(Debug, Clone, PartialEq)]
pub struct SfmPoint {
    /// World position.
    pub xyz: DVec3,
    /// Its observations.
    pub observations: Vec<(usize, usize)>,
    /// Mean reprojection error over them (pixels).
    pub error_px: f64,
}

/// Counts and timings.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SfmStats {
    /// Pairs with enough putative matches.
    pub matched_pairs: usize,
    /// Pairs verified by their epipolar geometry.
    pub verified_pairs: usize,
    /// Verified pairs whose rotation agrees with the averaged rotations.
    pub consistent_pairs: usize,
    /// Tracks built (at least two views each).
    pub tracks: usize,
    /// Tracks dropped as ambiguous.
    pub ambiguous_tracks: usize,
    /// Observations in the final points.
    pub observations: usize,
    /// Root mean square reprojection error (pixels) before the first and after the last
    /// bundle adjustment.
    pub rms_px: (f64, f64),
    /// Seconds per stage: matching, verification, rotations, positioning, adjustment.
    pub seconds: [f64; 5],
    /// Passes through the stages (a pass is repeated when adjustment moves a focal).
    pub passes: usize,
}

/// The result: cameras of the largest connected group of views, its points, and the groups.
#[derive(Debug, Clone)]
pub struct Sfm {
    /// One per view; `None` for a view not registered.
    pub cameras: Vec<Option<PinholeCamera>>,
    /// Where each view's focal came from.
    pub focal_sources: Vec<FocalSource>,
    /// The points.
    pub points: Vec<SfmPoint>,
    /// The verified pairs of the reconstructed group whose rotations agree, with their
    /// inlier matches.
    pub edges: Vec<Edge>,
    /// The groups of views the verified pairs connect, largest first (single views that no
    /// pair joins are groups of one). Only the first is reconstructed: groups are never merged.
    pub groups: Vec<Vec<usize>>,
    /// Counts and timings.
    pub stats: SfmStats,
}

fn principal((w, h): (usize, usize)) -> DVec2 {
    DVec2::new(w as f64 / 2.0, h as f64 / 2.0)
}

/// The starting focals: known ones; for the rest, per image size, the cycles' focal when the
/// view graph picks one clearly, else the guesses' median.
fn initial_focals(input: &SfmInput, matched: &[PairMatches], opts: &SfmOptions) -> (Vec<f64>, Vec<FocalSource>) {
    let n = input.sizes.len();
    let mut focals = vec![0.0; n];
    let mut sources = vec![FocalSource::Known; n];
    let mut sizes: Vec<(usize, usize)> = input.sizes.to_vec();
    sizes.sort_unstable();
    sizes.dedup();
    for size in sizes {
        let group: Vec<usize> = (0..n)
            .filter(|&k| input.sizes[k] == size && input.known_focals[k].is_none() && prior(input, k).is_none())
            .collect();
        if group.is_empty() {
            continue;
        }
        let mut guesses: Vec<f64> = group.iter().map(|&k| input.focal_guess[k]).filter(|f| *f > 0.0).collect();
        guesses.sort_by(f64::total_cmp);
        let guess = guesses.get(guesses.len() / 2).copied().unwrap_or(1.2 * size.0.max(size.1) as f64);
        let pp = principal(size);
        let cycle = opts.cycle_focal.as_ref().and_then(|copts| {
            let pairs: Vec<(usize, usize, Vec<DVec2>, Vec<DVec2>)> = matched
                .iter()
                .filter(|p| group.contains(&p.i) && group.contains(&p.j))
                .map(|p| {
                    let a = p.matches.iter().map(|m| input.keypoints[p.i].xy[m.0] - pp).collect();
                    let b = p.matches.iter().map(|m| input.keypoints[p.j].xy[m.1] - pp).collect();
                    (p.i, p.j, a, b)
                })
                .collect();
            focal_from_cycles(n, &pairs, guess, copts)
        });
        for &k in &group {
            focals[k] = cycle.as_ref().map_or(guess, |c| c.focal);
            sources[k] = if cycle.is_some() { FocalSource::Cycles } else { FocalSource::Guess };
        }
    }
    for k in 0..n {
        if let Some(f) = prior(input, k) {
            focals[k] = f;
            sources[k] = FocalSource::Prior;
        }
        if let Some(f) = input.known_focals[k] {
            focals[k] = f;
            sources[k] = FocalSource::Known;
        }
    }
    (focals, sources)
}

/// View `k`'s prior focal, where it has one and no known focal.
fn prior(input: &SfmInput, k: usize) -> Option<f64> {
    input.prior_focals.get(k).copied().flatten().filter(|_| input.known_focals[k].is_none())
}

/// Connected groups of `n` views under `edges`, largest first.
fn groups(n: usize, edges: &[&Edge]) -> Vec<Vec<usize>> {
    let mut sets = UnionFind::new(n);
    for e in edges {
        sets.union(e.i, e.j);
    }
    let mut by_root: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for k in 0..n {
        by_root.entry(sets.find(k)).or_default().push(k);
    }
    let mut out: Vec<Vec<usize>> = by_root.into_values().collect();
    out.sort_by_key(|g| (std::cmp::Reverse(g.len()), g[0]));
    out
}

/// Runs structure-from-motion on `input`: its pairs matched, then [`run_matched`].
pub fn run(input: &SfmInput, opts: &SfmOptions) -> Sfm {
    let clock = Instant::now();
    let matched = match_pairs(input.keypoints, input.pairs, &opts.view_graph);
    let seconds = clock.elapsed().as_secs_f64();
    let mut sfm = run_matched(input, &matched, opts);
    sfm.stats.seconds[0] = seconds;
    sfm
}

/// Runs structure-from-motion from putative matches (`input.pairs` is not read). Where bundle
/// adjustment moves a focal that was not known by more than 3%, the edges were verified and
/// the rotations averaged at a wrong focal: everything runs again from the adjusted focals
/// (twice at most).
pub fn run_matched(input: &SfmInput, matched: &[PairMatches], opts: &SfmOptions) -> Sfm {
    let (mut focals, focal_sources) = initial_focals(input, matched, opts);
    let mut seconds = [0.0; 5];
    let mut passes = 0;
    loop {
        let mut sfm = solve(input, matched, &focals, &focal_sources, opts);
        passes += 1;
        seconds.iter_mut().zip(&sfm.stats.seconds).for_each(|(a, b)| *a += b);
        sfm.stats.seconds = seconds;
        sfm.stats.passes = passes;
        let adjusted: Vec<Option<f64>> = sfm.cameras.iter().map(|c| c.map(|c| c.intrinsics.fx)).collect();
        let moved = (0..focals.len()).any(|k| {
            input.known_focals[k].is_none() && adjusted[k].is_some_and(|f| (f / focals[k] - 1.0).abs() > 0.03)
        });
        if !moved || passes == 3 {
            return sfm;
        }
        // Views left out keep the mean adjusted focal of their size.
        for k in 0..focals.len() {
            if input.known_focals[k].is_some() {
                continue;
            }
            if prior(input, k).is_some() {
                if let Some(f) = adjusted[k] {
                    focals[k] = f;
                }
                continue;
            }
            let same: Vec<f64> =
                (0..focals.len()).filter(|&j| input.sizes[j] == input.sizes[k]).filter_map(|j| adjusted[j]).collect();
            if !same.is_empty() {
                focals[k] = same.iter().sum::<f64>() / same.len() as f64;
            }
        }
    }
}

/// One pass of every stage at the given starting focals.
fn solve(
    input: &SfmInput,
    matched: &[PairMatches],
    focals: &[f64],
    focal_sources: &[FocalSource],
    opts: &SfmOptions,
) -> Sfm {
    let n = input.sizes.len();
    let mut focals = focals.to_vec();
    let focal_sources = focal_sources.to_vec();
    let mut stats = SfmStats::default();
    let mut clock = Instant::now();
    let mut lap = |stats: &mut SfmStats, k: usize| {
        stats.seconds[k] += clock.elapsed().as_secs_f64();
        clock = Instant::now();
    };
    stats.matched_pairs = matched.len();
    let pps: Vec<DVec2> = input.sizes.iter().map(|&s| principal(s)).collect();
    let edges = verify(input.keypoints, matched, &focals, &pps, &opts.view_graph);
    stats.verified_pairs = edges.len();
    lap(&mut stats, 1);
    let rot = average(n, &edges, &opts.rotations);
    let kept: Vec<&Edge> = edges.iter().zip(&rot.kept).filter(|(_, &k)| k).map(|(e, _)| e).collect();
    stats.consistent_pairs = kept.len();
    let groups = groups(n, &kept);
    lap(&mut stats, 2);
    let empty = |groups, stats| Sfm {
        cameras: vec![None; n],
        focal_sources: focal_sources.clone(),
        points: vec![],
        edges: vec![],
        groups,
        stats,
    };
    let main: Vec<usize> = groups.first().cloned().unwrap_or_default();
    let in_main = |v: usize| main.contains(&v) && rot.world[v].is_some();
    let main_edges: Vec<Edge> = kept.iter().filter(|e| in_main(e.i) && in_main(e.j)).map(|e| (*e).clone()).collect();
    let Some(strongest) = main_edges.iter().max_by(|a, b| a.weight().total_cmp(&b.weight())) else {
        return empty(groups, stats);
    };
    let (tracks, ambiguous) = build_tracks(&main_edges);
    stats.tracks = tracks.len();
    stats.ambiguous_tracks = ambiguous;
    // Each observation's world ray through its keypoint.
    let ray = |v: usize, kp: usize| -> DVec3 {
        let q = normalised(input.keypoints[v].xy[kp], pps[v], focals[v]);
        rot.world[v].expect("main group") * DVec3::new(q.x, q.y, 1.0).normalize()
    };
    let rays: Vec<Vec<Ray>> = tracks.iter().map(|t| t.iter().map(|&(v, kp)| (v, ray(v, kp))).collect()).collect();
    let pos = position(n, &rays, strongest.i, &opts.positions);
    lap(&mut stats, 3);

    // Bundle adjustment over the positioned cameras and points, twice: after each, the
    // observations that reproject badly go, and a track's others come back where they fit.
    let size_groups: Vec<usize> = {
        let mut keys: Vec<(usize, usize, bool)> = Vec::new();
        (0..n)
            .map(|k| {
                let own = input.known_focals[k].is_some() || prior(input, k).is_some();
                let key = (input.sizes[k].0, input.sizes[k].1, own);
                let key = if key.2 { (k, usize::MAX, true) } else { key };
                keys.iter().position(|x| *x == key).unwrap_or_else(|| {
                    keys.push(key);
                    keys.len() - 1
                })
            })
            .collect()
    };
    let n_focals = size_groups.iter().max().map_or(0, |m| m + 1);
    let mut focal_values = vec![0.0; n_focals];
    let mut focal_fixed = vec![false; n_focals];
    let mut focal_prior = vec![None; n_focals];
    for k in 0..n {
        focal_values[size_groups[k]] = focals[k];
        focal_fixed[size_groups[k]] |= input.known_focals[k].is_some();
        focal_prior[size_groups[k]] = prior(input, k);
    }
    let mut cameras: Vec<Option<BaCamera>> = (0..n)
        .map(|v| {
            let (Some(r), Some(c)) = (rot.world[v], pos.centers[v]) else { return None };
            in_main(v).then_some(BaCamera { rotation: r, center: c, focal: size_groups[v], principal: pps[v] })
        })
        .collect();
    let mut points: Vec<Option<DVec3>> = pos.points.clone();
    let mut obs: Vec<Vec<(usize, usize)>> = tracks.clone();
    filter(&mut obs, &mut points, &cameras, &focal_values, input, 50.0, 0.0);
    for round in 0..2 {
        let mut problem = BaProblem {
            cameras: &mut cameras,
            focals: &mut focal_values,
            focal_fixed: &focal_fixed,
            focal_prior: &focal_prior,
            points: &mut points,
            observations: &obs,
            keypoints: input.keypoints,
        };
        let report = bundle_adjust(&mut problem, &opts.ba);
        if round == 0 {
            stats.rms_px.0 = report.initial_rms_px;
        }
        stats.rms_px.1 = report.final_rms_px;
        // Retriangulation: every track's observations are candidates again, kept where they fit.
        obs = tracks.clone();
        filter(&mut obs, &mut points, &cameras, &focal_values, input, opts.max_reprojection_px, 0.0);
        if round == 1 {
            let (px, deg) = (opts.max_reprojection_px, opts.min_triangulation_deg);
            filter(&mut obs, &mut points, &cameras, &focal_values, input, px, deg);
        }
    }
    lap(&mut stats, 4);
    for k in 0..n {
        focals[k] = focal_values[size_groups[k]];
    }
    // Views that keep too few observations are not registered.
    let mut per_view = vec![0usize; n];
    obs.iter().zip(&points).filter(|(_, p)| p.is_some()).flat_map(|(t, _)| t).for_each(|&(v, _)| per_view[v] += 1);
    let cams: Vec<Option<PinholeCamera>> = (0..n)
        .map(|v| {
            let c = cameras[v].as_ref()?;
            (per_view[v] >= opts.min_view_observations).then(|| pinhole(c, focals[v], input.sizes[v]))
        })
        .collect();
    let points: Vec<SfmPoint> = obs
        .into_iter()
        .zip(points)
        .filter_map(|(t, p)| {
            let xyz = p?;
            let t: Track = t.into_iter().filter(|&(v, _)| cams[v].is_some()).collect();
            (t.len() >= 2).then(|| {
                let err = t.iter().map(|&(v, kp)| reprojection(&cameras, &focals, input, v, kp, xyz)).sum::<f64>();
                SfmPoint { error_px: err / t.len() as f64, xyz, observations: t }
            })
        })
        .collect();
    stats.observations = points.iter().map(|p| p.observations.len()).sum();
    Sfm { cameras: cams, focal_sources, points, edges: main_edges, groups, stats }
}

fn pinhole(c: &BaCamera, focal: f64, (w, h): (usize, usize)) -> PinholeCamera {
    let mut m = DMat4::from_mat3(c.rotation);
    m.w_axis = c.center.extend(1.0);
    PinholeCamera {
        intrinsics: Intrinsics { fx: focal, fy: focal, cx: c.principal.x, cy: c.principal.y },
        width: w,
        height: h,
        cam_to_world: m,
    }
}

/// Reprojection error (pixels) of point `x` in view `v` at keypoint `kp`; infinite behind it.
fn reprojection(cams: &[Option<BaCamera>], focals: &[f64], input: &SfmInput, v: usize, kp: usize, x: DVec3) -> f64 {
    let uv = cams[v].as_ref().and_then(|c| c.project(focals[v], x));
    uv.map_or(f64::INFINITY, |uv| (uv - input.keypoints[v].xy[kp]).length())
}

/// Keeps the observations of each track that reproject within `max_px` (on registered
/// cameras), re-triangulating a track whose point is missing, and drops tracks left with
/// fewer than two or whose rays meet at under `min_deg`.
fn filter(
    obs: &mut [Vec<(usize, usize)>],
    points: &mut [Option<DVec3>],
    cams: &[Option<BaCamera>],
    focal_values: &[f64],
    input: &SfmInput,
    max_px: f64,
    min_deg: f64,
) {
    let focal_of = |v: usize| cams[v].as_ref().map_or(0.0, |c| focal_values[c.focal]);
    let focals: Vec<f64> = (0..cams.len()).map(focal_of).collect();
    for (t, p) in obs.iter_mut().zip(points.iter_mut()) {
        t.retain(|&(v, _)| cams[v].is_some());
        if let Some(x) = *p {
            t.retain(|&(v, kp)| reprojection(cams, &focals, input, v, kp, x) <= max_px);
        }
        let ok = t.len() >= 2 && p.is_some() && {
            let x = p.expect("checked");
            let dirs: Vec<DVec3> =
                t.iter().map(|&(v, _)| (x - cams[v].as_ref().expect("kept").center).normalize()).collect();
            let mut min_cos = 1.0f64;
            for (a, da) in dirs.iter().enumerate() {
                for db in &dirs[a + 1..] {
                    min_cos = min_cos.min(da.dot(*db));
                }
            }
            min_cos.clamp(-1.0, 1.0).acos().to_degrees() >= min_deg
        };
        if !ok {
            t.clear();
            *p = None;
        }
    }
}
