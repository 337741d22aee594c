//! Pairs -> matches -> global alignment -> tracks: the in-memory reconstruction.

use crate::cache::PairCache;
use crate::input::InputImage;
use crate::predictor::{PairPredictor, ViewOutput, Wanted};
use crate::sfm::{reconstruct_sfm, SfmSettings};
use crate::tracks::{track_points, TrackOptions};
use crate::ReconError;
use dens3r_align::cycle_focal::{focal_from_cycles, CycleFocal, CycleFocalOptions};
use dens3r_align::keypoints::{detect, match_mutual, Keypoints};
use dens3r_align::match_pose::{pose_from_keypoints, pose_from_matches, KeypointPoseOptions, MatchPoseOptions};
use dens3r_align::matching::{reciprocal_matches, Descriptors, Match, MatchOptions};
use dens3r_align::{
    average_rotations, consistent_rotations, global_align, verified_subgraph, AlignOptions, Alignment, PairGraph,
    PairPrediction,
};
use dens3r_geom::focal::{focal_or_fallback, median};
use dens3r_geom::transform::Sim3;
use dens3r_geom::{DVec3, Raster, Vec3};
use dens3r_io::panics::catch_quietly;
use dens3r_scene::export::TrackPoint;
use dens3r_sfm::SfmStats;
use glam::{DMat3, DVec2};
use image::RgbImage;
use rayon::prelude::*;
use std::collections::{HashMap, HashSet};
use std::time::Instant;

/// Reconstruction settings.
#[derive(Debug, Clone, PartialEq)]
pub struct ReconOptions {
    /// Which photos are paired: the network's pairs, both orders of each (dense), or the
    /// SIFT matches (sfm). None: every pair up to 30 photos, retrieval above
    /// ([`crate::graph::resolve`]).
    pub graph: Option<PairGraph>,
    /// Global alignment.
    pub align: AlignOptions,
    /// Descriptor matching (skipped when the model has no descriptor head).
    pub matching: MatchOptions,
    /// Tracks: which become 3-D points, triangulated where the cameras allow.
    pub tracks: TrackOptions,
    /// Place each pair's second view by its matches (PnP-RANSAC on the first view's points)
    /// and its own-frame pointmap where enough matches agree ([`dens3r_align::match_pose`]),
    /// instead of the network's cross-view pointmap; `None` keeps the network's everywhere.
    pub match_pose: Option<MatchPoseOptions>,
    /// Place pairs by SIFT keypoint matches and their epipolar geometry first, where enough
    /// agree ([`dens3r_align::match_pose::pose_from_keypoints`]): the rotation then owes
    /// nothing to the network's depth or descriptors. `None` skips keypoints.
    pub keypoints: Option<KeypointOptions>,
    /// How the cameras are found: global structure-from-motion (the default), or the
    /// network's pairs and DUSt3R's dense alignment.
    pub cameras: Cameras,
    /// Leave out of the alignment the pairs neither keypoints nor matches placed, among
    /// images that placed pairs already connect ([`dens3r_align::verified_subgraph`]): a
    /// network's unverified cross-view pointmaps then cannot pull verified cameras. Off keeps
    /// every pair (for a network whose cross-view pointmaps are trusted).
    pub drop_unplaced: bool,
}

/// Keypoint matching settings ([`ReconOptions::keypoints`]).
#[derive(Debug, Clone, PartialEq)]
pub struct KeypointOptions {
    /// Strongest SIFT keypoints kept per image.
    pub max_keypoints: usize,
    /// Lowe's ratio test.
    pub ratio: f32,
    /// When a placement is trusted.
    pub pose: KeypointPoseOptions,
    /// A placement whose rotation is further than this (degrees) from what the placements
    /// with more inliers imply is dropped ([`dens3r_align::consistent_rotations`]).
    pub max_disagreement_deg: f64,
    /// Where no image has a known focal and all share a size (one camera), the focal at which
    /// the keypoint pairs' rotations close their cycles replaces the network's estimate, when
    /// the cycles pick one clearly ([`focal_from_cycles`]); `None` keeps the network's.
    pub cycle_focal: Option<CycleFocalOptions>,
    /// The cameras the placed pairs connect take the rotations that agree best with those
    /// pairs ([`dens3r_align::average_rotations`]), and the alignment keeps them: a pair's
    /// keypoint rotation is far more accurate than what aligning the network's pointmaps
    /// makes of it.
    pub fix_rotations: bool,
}

impl Default for KeypointOptions {
    fn default() -> Self {
        Self {
            max_keypoints: 4000,
            ratio: 0.8,
            pose: KeypointPoseOptions::default(),
            max_disagreement_deg: 15.0,
            cycle_focal: Some(CycleFocalOptions::default()),
            fix_rotations: true,
        }
    }
}

/// How `reconstruct` finds the cameras ([`ReconOptions::cameras`]).
#[derive(Debug, Clone, PartialEq)]
pub enum Cameras {
    /// SIFT keypoints through global structure-from-motion ([`crate::sfm`]); the network gives
    /// depth and normals. The pair graph says which photos are matched.
    Sfm(Box<SfmSettings>),
    /// The network's pairs (the pair graph), placed by keypoints and matches where they
    /// agree, then DUSt3R's dense global alignment.
    Dense,
}

impl Default for ReconOptions {
    fn default() -> Self {
        Self {
            cameras: Cameras::Sfm(Box::default()),
            graph: None,
            align: AlignOptions::default(),
            matching: MatchOptions::default(),
            tracks: TrackOptions::default(),
            match_pose: Some(MatchPoseOptions::default()),
            keypoints: Some(KeypointOptions::default()),
            drop_unplaced: true,
        }
    }
}

/// Pipeline stages, for progress reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Network runs (or cache reads) over the ordered pairs.
    Predict,
    /// Global alignment iterations.
    Align,
    /// Image descriptors for a retrieval graph.
    Retrieve,
    /// SIFT keypoints of each photo (structure-from-motion cameras).
    Keypoints,
}

/// What one run produced (all maps at each image's network size, own orientation).
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// Frame names, input order.
    pub names: Vec<String>,
    /// Colours per frame.
    pub rgb: Vec<RgbImage>,
    /// Cameras, aligned depth and confidence.
    pub alignment: Alignment,
    /// Confidence-weighted mean of the pair predictions' normals (camera frame), if any.
    pub normals: Vec<Option<Raster<Vec3>>>,
    /// Reciprocal matches per matched pair `(i, j, matches)`, `i < j`.
    pub matches: Vec<(usize, usize, Vec<Match>)>,
    /// Tracks as 3-D points (for COLMAP's points3D).
    pub points: Vec<TrackPoint>,
    /// The photos' object masks at the maps' size, where given ([`InputImage::mask`]).
    pub masks: Vec<Option<Raster<bool>>>,
    /// Each frame's index among the input photos (photos not registered have no frame).
    pub inputs: Vec<usize>,
    /// Counts, timings and warnings.
    pub stats: ReconStats,
}

/// Counts and timings of a run.
#[derive(Debug, Clone, Default)]
pub struct ReconStats {
    /// Ordered pairs in the graph.
    pub pairs: usize,
    /// Of those, read from the cache.
    pub cache_hits: usize,
    /// Seconds predicting (network or cache).
    pub predict_seconds: f64,
    /// Seconds matching.
    pub match_seconds: f64,
    /// Seconds aligning.
    pub align_seconds: f64,
    /// Ordered pairs whose second view was placed by its matches (see
    /// [`ReconOptions::match_pose`]).
    pub posed_by_matches: usize,
    /// Ordered pairs placed by keypoint matches (see [`ReconOptions::keypoints`]); these are
    /// not counted in `posed_by_matches`.
    pub posed_by_keypoints: usize,
    /// Ordered pairs keypoints placed but whose rotation contradicted the stronger placements
    /// ([`KeypointOptions::max_disagreement_deg`]); not counted in `posed_by_keypoints`.
    pub keypoint_inconsistent: usize,
    /// The focal the keypoint pairs' cycles gave every image ([`KeypointOptions::cycle_focal`]),
    /// used as a known focal by the alignment.
    pub cycle_focal: Option<CycleFocal>,
    /// Cameras whose rotation was averaged from the keypoint pairs and kept by the alignment
    /// ([`KeypointOptions::fix_rotations`]).
    pub fixed_rotations: usize,
    /// Seconds detecting and matching keypoints and placing pairs by them.
    pub keypoint_seconds: f64,
    /// Ordered pairs left out of the alignment: unplaced pairs among images that placed pairs
    /// already connect ([`dens3r_align::verified_subgraph`]).
    pub pairs_left_out: usize,
    /// Images whose focal was known (EXIF or given) and kept.
    pub known_focals: usize,
    /// Track points triangulated from the cameras (the rest took a view's aligned depth).
    pub triangulated_points: usize,
    /// Things the user should know (fallbacks, cache problems).
    pub warnings: Vec<String>,
    /// Photos given cameras (all of them on the dense path).
    pub registered: usize,
    /// Photos structure-from-motion left out, by name.
    pub unregistered: Vec<String>,
    /// Structure-from-motion's counts and timings, where its cameras were used.
    pub sfm: Option<SfmStats>,
    /// How the photos were paired.
    pub graph: crate::graph::GraphInfo,
}

/// Reconstructs `images`: cameras as [`ReconOptions::cameras`] says, depth and normals from
/// the network. `progress(stage, done, total)` reports each stage.
pub fn reconstruct(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    opts: &ReconOptions,
    progress: impl FnMut(Stage, usize, usize),
) -> Result<Reconstruction, ReconError> {
    let n = images.len();
    if n < 2 {
        return Err(ReconError::Other(format!("reconstruction needs at least 2 photos, got {n}")));
    }
    match &opts.cameras {
        Cameras::Sfm(settings) => reconstruct_sfm(images, predictor, cache, opts, settings, progress),
        Cameras::Dense => reconstruct_dense(images, predictor, cache, opts, progress),
    }
}

/// The ordered pair `(i, j)`'s network output, through `cache`; with descriptors where the
/// pair is `matched` on this run (each unordered pair is matched once, on the run with the
/// smaller index first where both run; those runs are cached apart from runs without them).
pub(crate) fn pair_output(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    (i, j): (usize, usize),
    matched: bool,
    warnings: &mut Vec<String>,
) -> Result<([ViewOutput; 2], bool), ReconError> {
    let id = predictor.id();
    let want = Wanted { descriptors: matched };
    let key = if matched {
        PairCache::key(&id, &images[i], &images[j])
    } else {
        PairCache::key(&format!("{id} without descriptors"), &images[i], &images[j])
    };
    let sizes = [images[i].size(), images[j].size()];
    cache.load_or(&key, sizes, warnings, || {
        let err = |msg: String| ReconError::Predict { a: images[i].name.clone(), b: images[j].name.clone(), msg };
        let out = predictor.predict(images, i, j, want).map_err(err)?;
        for (v, k) in [(0, i), (1, j)] {
            out[v].check(sizes[v]).map_err(|m| err(format!("{}: {m}", images[k].name)))?;
        }
        Ok::<_, ReconError>(out)
    })
}

/// Runs the pair graph over `images`, matches, aligns and triangulates tracks (the dense path).
pub fn reconstruct_dense(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    opts: &ReconOptions,
    mut progress: impl FnMut(Stage, usize, usize),
) -> Result<Reconstruction, ReconError> {
    let n = images.len();
    let sizes: Vec<(usize, usize)> = images.iter().map(|im| im.size()).collect();
    // Every pair, each followed by its reverse (the set DUSt3R symmetrises to): a predictor
    // may reuse work between the two runs of one pair.
    let mut warnings: Vec<String> = images.iter().flat_map(|im| im.warnings.iter().cloned()).collect();
    let graph = crate::graph::plan_pairs(images, predictor, cache, opts.graph, &mut warnings, &mut progress)?;
    let order: Vec<(usize, usize)> = graph.list.iter().flat_map(|&(i, j)| [(i, j), (j, i)]).collect();
    let ordered: HashSet<(usize, usize)> = order.iter().copied().collect();
    let known_focals = images.iter().filter(|im| im.focal.is_some()).count();
    let mut stats =
        ReconStats { pairs: order.len(), known_focals, registered: n, graph, warnings, ..Default::default() };
    let mut normal_sum: Vec<Option<(Vec<Vec3>, Vec<f32>)>> = vec![None; n];
    let mut matches = Vec::new();
    let mut preds = Vec::with_capacity(order.len());
    progress(Stage::Predict, 0, order.len());
    for (e, &(i, j)) in order.iter().enumerate() {
        let t = Instant::now();
        // Each unordered pair is matched once, on the run with the smaller index first: only
        // that run needs descriptors (cached apart from runs without them).
        let matched = i < j || !ordered.contains(&(j, i));
        let (out, hit) = pair_output(images, predictor, cache, (i, j), matched, &mut stats.warnings)?;
        stats.cache_hits += usize::from(hit);
        stats.predict_seconds += t.elapsed().as_secs_f64();
        for (v, k) in [(0, i), (1, j)] {
            if let Some(nm) = &out[v].normals {
                accumulate_normals(&mut normal_sum[k], nm, &out[v].conf);
            }
        }
        if matched {
            let t = Instant::now();
            if let Some(ms) = match_pair(&out, &opts.matching).map_err(ReconError::Other)? {
                let (a, b, ms) = if i < j { (i, j, ms) } else { (j, i, ms.into_iter().map(swap).collect()) };
                matches.push((a, b, ms));
            }
            stats.match_seconds += t.elapsed().as_secs_f64();
        }
        let [vi, vj] = out;
        preds.push(PairPrediction { i, j, pts_i: vi.points, pts_j: vj.points, conf_i: vi.conf, conf_j: vj.conf });
        progress(Stage::Predict, e + 1, order.len());
    }
    matches.sort_by_key(|m| (m.0, m.1));
    // The photos as the maps see them: SIFT's input, the tracks' colours and the scene's frames.
    let rgb: Vec<RgbImage> = images.iter().map(|im| im.rgb()).collect();
    let mut placed = HashMap::new();
    let mut rotations = Vec::new();
    if let Some(kp) = &opts.keypoints {
        let t = Instant::now();
        let warnings = std::sync::Mutex::new(Vec::new());
        let kpp = place_by_keypoints(images, &rgb, &mut preds, &order, &mut matches, kp, &warnings);
        placed = kpp.placed;
        stats.keypoint_inconsistent = kpp.inconsistent;
        stats.cycle_focal = kpp.cycle_focal;
        stats.fixed_rotations = kpp.rotations.iter().filter(|r| r.is_some()).count();
        rotations = kpp.rotations;
        stats.warnings.extend(warnings.into_inner().unwrap());
        stats.posed_by_keypoints = placed.len();
        stats.keypoint_seconds = t.elapsed().as_secs_f64();
    }
    if let Some(mp) = &opts.match_pose {
        let by_matches = place_by_matches(&mut preds, &order, &matches, &placed, mp);
        stats.posed_by_matches = by_matches.len();
        placed.extend(by_matches);
    }
    // Pairs placed by geometry outrank the network's cross-view guesses: where they connect
    // images, the unplaced pairs among those images are left out of the alignment (the
    // reverse of a placed pair first takes its placement, so no image loses its own frame).
    let keep = if opts.drop_unplaced {
        let mirrored = mirror_placements(&mut preds, &order, &placed);
        let verified: Vec<bool> = order.iter().map(|p| placed.contains_key(p) || mirrored.contains(p)).collect();
        verified_subgraph(n, &order, &verified)
    } else {
        vec![true; order.len()]
    };
    stats.pairs_left_out = keep.iter().filter(|&&k| !k).count();
    let mut keep = keep.into_iter();
    preds.retain(|_| keep.next().expect("one flag per pair"));

    let t = Instant::now();
    let iters = opts.align.iterations;
    // Known focals (EXIF, `--focal`, or the keypoint cycles') are kept; the rest are estimated.
    let cycle = stats.cycle_focal.as_ref().map(|c| c.focal);
    let align =
        AlignOptions { focals: images.iter().map(|im| im.focal.or(cycle)).collect(), rotations, ..opts.align.clone() };
    let alignment = global_align(&sizes, &preds, &align, |it, _| progress(Stage::Align, it, iters))?;
    stats.align_seconds = t.elapsed().as_secs_f64();
    stats.warnings.extend(alignment.warnings.iter().cloned());
    let estimated: Vec<Option<f64>> = (alignment.views.iter().enumerate())
        .map(|(k, v)| align.known_focal(k).is_none().then_some(v.camera.intrinsics.fx))
        .collect();
    let tried = opts.keypoints.is_some() || opts.match_pose.is_some();
    stats.warnings.extend(camera_warnings(&sizes, &estimated, tried && placed.is_empty()));
    drop(preds);

    let normals = normal_sum
        .into_iter()
        .zip(&sizes)
        .map(|(s, &(w, h))| {
            s.map(|(sum, _)| {
                let v = sum.into_iter().map(|n| n.try_normalize().unwrap_or(Vec3::ZERO)).collect();
                Raster::from_vec(w, h, v).expect("sizes checked")
            })
        })
        .collect();
    let (points, triangulated) = track_points(&alignment, &rgb, &matches, &opts.tracks);
    stats.triangulated_points = triangulated.iter().filter(|&&t| t).count();
    Ok(Reconstruction {
        names: images.iter().map(|im| im.name.clone()).collect(),
        rgb,
        alignment,
        normals,
        matches,
        points,
        masks: images.iter().map(|im| im.mask.clone()).collect(),
        inputs: (0..n).collect(),
        stats,
    })
}

/// Same-size photos whose estimated focals differ by more than this factor get a warning.
const FOCAL_SPREAD_WARNING: f64 = 2.0;

/// What a run's cameras say about their own reliability: `unplaced` when placement by keypoints
/// or matches was tried and placed no pair (every camera then comes from the network's
/// cross-view pointmaps alone); `estimated` is each image's estimated focal (`None` where it
/// was known), compared among photos of one size, which one camera at one zoom would share.
fn camera_warnings(sizes: &[(usize, usize)], estimated: &[Option<f64>], unplaced: bool) -> Vec<String> {
    let mut warnings = Vec::new();
    if unplaced {
        warnings.push(
            "no pair was placed by SIFT keypoints or the network's matches (too little texture or overlap?): \
             every camera comes from the network's pointmaps alone, which only a well-trained network \
             places reliably (not the bundled dens3r-s); photos with more texture or an official \
             checkpoint (--weights) do better"
                .to_string(),
        );
    }
    let mut by_size: HashMap<(usize, usize), Vec<f64>> = HashMap::new();
    for (&size, f) in sizes.iter().zip(estimated) {
        if let Some(f) = f {
            by_size.entry(size).or_default().push(*f);
        }
    }
    let mut groups: Vec<_> = by_size.into_iter().filter(|(_, f)| f.len() > 1).collect();
    groups.sort_by_key(|g| g.0);
    for ((w, h), f) in groups {
        let valid: Vec<f64> = f.iter().copied().filter(|v| v.is_finite() && *v > 0.0).collect();
        let lo = valid.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = valid.iter().copied().fold(0.0, f64::max);
        if valid.len() < f.len() || hi > FOCAL_SPREAD_WARNING * lo {
            warnings.push(format!(
                "the estimated focals of the {} photos of {w}x{h} span {lo:.1} to {hi:.1} px{}: their \
                 cameras are likely wrong; give the focal if it is known (--focal, or photos with EXIF), \
                 or share one (--shared-focal)",
                f.len(),
                if valid.len() < f.len() {
                    ", and some are no positive number".to_string()
                } else {
                    format!(", more than {FOCAL_SPREAD_WARNING}x apart")
                }
            ));
        }
    }
    warnings
}

/// A pair's second view placed in its first view's frame: points, their confidence and the
/// similarity that placed them.
type Placement = (Raster<Vec3>, Raster<f32>, Sim3);

/// Replaces each ordered pair's cross-view pointmap (view `j` in camera `i`'s frame) by view
/// `j`'s own-frame pointmap (from the reverse run) placed by the pair's matches, where they
/// agree on a camera; returns the ordered pairs placed so, each with the similarity that took
/// view `j`'s own-frame points into camera `i`'s frame.
fn place_by_matches(
    preds: &mut [PairPrediction],
    order: &[(usize, usize)],
    matches: &[(usize, usize, Vec<Match>)],
    skip: &HashMap<(usize, usize), Sim3>,
    opts: &MatchPoseOptions,
) -> HashMap<(usize, usize), Sim3> {
    let index: HashMap<(usize, usize), usize> = order.iter().enumerate().map(|(e, &p)| (p, e)).collect();
    let placed: Vec<Option<Placement>> = order
        .iter()
        .map(|&(i, j)| {
            if skip.contains_key(&(i, j)) {
                return None;
            }
            let rev = *index.get(&(j, i))?;
            let (a, b) = (i.min(j), i.max(j));
            let ms = &matches.iter().find(|m| m.0 == a && m.1 == b)?.2;
            let ms: Vec<Match> = if i < j { ms.clone() } else { ms.iter().copied().map(swap).collect() };
            let e = index[&(i, j)];
            let pose = pose_from_matches(&preds[e].pts_i, &preds[rev].pts_i, &ms, opts)?;
            Some((pose.points, preds[rev].conf_i.clone(), pose.transform))
        })
        .collect();
    let mut done = HashMap::new();
    for (e, p) in placed.into_iter().enumerate() {
        if let Some((pts, conf, t)) = p {
            preds[e].pts_j = pts;
            preds[e].conf_j = conf;
            done.insert(order[e], t);
        }
    }
    done
}

/// Gives each unplaced ordered pair `(i, j)` whose reverse `(j, i)` was placed (by the
/// similarity `T` taking view `i`'s own-frame points into camera `j`'s frame) that placement
/// inverted: view `j`'s own-frame points through `T^-1` into camera `i`'s frame, so both orders
/// of the pair agree. Returns the pairs so placed.
fn mirror_placements(
    preds: &mut [PairPrediction],
    order: &[(usize, usize)],
    placed: &HashMap<(usize, usize), Sim3>,
) -> HashSet<(usize, usize)> {
    let index: HashMap<(usize, usize), usize> = order.iter().enumerate().map(|(e, &p)| (p, e)).collect();
    let mut done = HashSet::new();
    for (e, &(i, j)) in order.iter().enumerate() {
        if placed.contains_key(&(i, j)) {
            continue;
        }
        let (Some(t), Some(&rev)) = (placed.get(&(j, i)), index.get(&(j, i))) else { continue };
        let inv = t.inverse();
        preds[e].pts_j =
            preds[rev].pts_i.map(|q| if q.is_finite() { inv.apply(q.as_dvec3()).as_vec3() } else { Vec3::NAN });
        preds[e].conf_j = preds[rev].conf_i.clone();
        done.insert((i, j));
    }
    done
}

/// A pair's second view placed in its first view's frame: points, their confidence, the
/// matches that placed it and the similarity that did.
type Placed = (Raster<Vec3>, Raster<f32>, Vec<Match>, Sim3);

/// Places ordered pairs by SIFT keypoint matches ([`pose_from_keypoints`]) where enough agree,
/// replacing their cross-view pointmaps as [`place_by_matches`] does; a placed pair's matches
/// (the keypoint inliers, at the nearest pixels) replace the network's in `matches`, so tracks
/// and match pictures follow the geometry used. Returns the ordered pairs placed, with their
/// similarities (as [`place_by_matches`]), the pairs dropped as inconsistent and the focal
/// their cycles gave.
fn place_by_keypoints(
    images: &[InputImage],
    rgb: &[RgbImage],
    preds: &mut [PairPrediction],
    order: &[(usize, usize)],
    matches: &mut Vec<(usize, usize, Vec<Match>)>,
    opts: &KeypointOptions,
    warnings: &std::sync::Mutex<Vec<String>>,
) -> KeypointPlacement {
    let index: HashMap<(usize, usize), usize> = order.iter().enumerate().map(|(e, &p)| (p, e)).collect();
    // A panic inside the SIFT crate costs that image its keypoints, not the run.
    let kps: Vec<Keypoints> = images
        .par_iter()
        .zip(rgb)
        .map(|(im, rgb)| {
            catch_quietly(|| detect(rgb, opts.max_keypoints)).unwrap_or_else(|e| {
                warnings.lock().unwrap().push(format!("{}: no SIFT keypoints ({e})", im.name));
                Keypoints::default()
            })
        })
        .collect();
    // Depth from the network, rays from one pinhole: each own-frame pointmap rebuilt from its
    // z at one focal per image (the median over its own-frame pointmaps' Weiszfeld focals;
    // one for all images when they share a size, as one camera's photos do). A network's
    // depth is learned long before its rays (dens3r-s's own-frame points miss any pinhole by
    // about 70 px at 512 px), and the epipolar geometry needs the one focal the global
    // alignment will start from.
    let known: Vec<Option<f64>> = images.iter().map(|im| im.focal).collect();
    let mut focals = pooled_focals(preds, &known);
    let unordered: Vec<(usize, usize)> = order.iter().filter(|p| p.0 < p.1).copied().collect();
    let pair_kp: HashMap<(usize, usize), (Vec<DVec2>, Vec<DVec2>)> = unordered
        .par_iter()
        .map(|&(i, j)| {
            let m = match_mutual(&kps[i], &kps[j], opts.ratio);
            ((i, j), m.iter().map(|&(p, q)| (kps[i].xy[p], kps[j].xy[q])).unzip())
        })
        .collect();
    // One camera, no focal known: the focal that closes the keypoint pairs' cycles, where
    // they pick one clearly.
    let one_size = rgb.iter().all(|im| im.dimensions() == rgb[0].dimensions());
    let mut cycle_focal = None;
    if let (Some(co), true, true) = (&opts.cycle_focal, one_size, known.iter().all(Option::is_none)) {
        let c = DVec2::new(rgb[0].width() as f64 / 2.0, rgb[0].height() as f64 / 2.0);
        let mut cyc: Vec<(usize, usize, Vec<DVec2>, Vec<DVec2>)> = pair_kp
            .iter()
            .map(|(&(i, j), (a, b))| (i, j, a.iter().map(|q| *q - c).collect(), b.iter().map(|q| *q - c).collect()))
            .collect();
        cyc.sort_by_key(|p| (p.0, p.1));
        cycle_focal = focal_from_cycles(images.len(), &cyc, focals[0], co);
        if let Some(cf) = &cycle_focal {
            focals = vec![cf.focal; images.len()];
        }
    }
    let own: Vec<Raster<Vec3>> = preds.iter().map(|p| pinhole(&p.pts_i, focals[p.i])).collect();
    let placed: Vec<Option<Placed>> = order
        .par_iter()
        .map(|&(i, j)| {
            let rev = *index.get(&(j, i))?;
            let e = index[&(i, j)];
            // Matched once per unordered pair, read both ways.
            let (a, b) = if i < j {
                pair_kp.get(&(i, j))?.clone()
            } else {
                let (b, a) = pair_kp.get(&(j, i))?.clone();
                (a, b)
            };
            let (pose, inl) = pose_from_keypoints(&own[e], &own[rev], (focals[i], focals[j]), &a, &b, &opts.pose)?;
            let px = |r: &Raster<Vec3>, q: DVec2| {
                let x = (q.x.round().max(0.0) as usize).min(r.width() - 1);
                let y = (q.y.round().max(0.0) as usize).min(r.height() - 1);
                (x, y)
            };
            let kept: Vec<Match> = (0..a.len())
                .filter(|&k| inl[k])
                .map(|k| {
                    let (pa, pb) = (px(&own[e], a[k]), px(&own[rev], b[k]));
                    let conf = preds[e].conf_i.get(pa.0, pa.1).min(*preds[rev].conf_i.get(pb.0, pb.1));
                    Match { a: pa, b: pb, conf }
                })
                .collect();
            Some((pose.points, preds[rev].conf_i.clone(), kept, pose.transform))
        })
        .collect();
    // A placement whose rotation contradicts the stronger ones around it (repeated texture
    // matched across the object) is dropped.
    let edges: Vec<(usize, usize, DMat3, f64)> = placed
        .iter()
        .zip(order)
        .filter_map(|(p, &(i, j))| p.as_ref().map(|p| (i, j, p.3.rotation, p.2.len() as f64)))
        .collect();
    let consistent = consistent_rotations(images.len(), &edges, opts.max_disagreement_deg);
    // One rotation per camera from the pairs kept: the alignment keeps them.
    let kept_edges: Vec<(usize, usize, DMat3, f64)> =
        edges.iter().zip(&consistent).filter(|(_, &c)| c).map(|(e, _)| *e).collect();
    let rotations =
        if opts.fix_rotations { average_rotations(images.len(), &kept_edges, 30) } else { vec![None; images.len()] };
    let mut verdicts = consistent.into_iter();
    let (mut placed, mut inconsistent) = (placed, 0);
    for p in placed.iter_mut().filter(|p| p.is_some()) {
        if !verdicts.next().unwrap_or(true) {
            *p = None;
            inconsistent += 1;
        }
    }
    if placed.iter().all(Option::is_none) {
        return KeypointPlacement { placed: HashMap::new(), inconsistent, cycle_focal, rotations };
    }
    for (p, o) in preds.iter_mut().zip(own) {
        p.pts_i = o;
    }
    let mut done = HashMap::new();
    let mut kept: HashMap<(usize, usize), Vec<Match>> = HashMap::new();
    for (e, p) in placed.into_iter().enumerate() {
        let Some((pts, conf, ms, t)) = p else { continue };
        preds[e].pts_j = pts;
        preds[e].conf_j = conf;
        let (i, j) = order[e];
        done.insert((i, j), t);
        // One set of matches per unordered pair: the run with the smaller index first wins.
        let (key, ms) = if i < j { ((i, j), ms) } else { ((j, i), ms.into_iter().map(swap).collect()) };
        if i < j || !kept.contains_key(&key) {
            kept.insert(key, ms);
        }
    }
    for (&(a, b), ms) in &kept {
        match matches.iter_mut().find(|m| m.0 == a && m.1 == b) {
            Some(m) => m.2 = ms.clone(),
            None => matches.push((a, b, ms.clone())),
        }
    }
    matches.sort_by_key(|m| (m.0, m.1));
    KeypointPlacement { placed: done, inconsistent, cycle_focal, rotations }
}

/// What [`place_by_keypoints`] did.
struct KeypointPlacement {
    /// Ordered pairs placed, with the similarity taking the second view into the first's frame.
    placed: HashMap<(usize, usize), Sim3>,
    /// Ordered pairs dropped as inconsistent with the others.
    inconsistent: usize,
    /// The focal the pairs' cycles gave, if they gave one.
    cycle_focal: Option<CycleFocal>,
    /// Camera-to-world rotations averaged over the pairs placed (the largest group of them).
    rotations: Vec<Option<DMat3>>,
}

/// One focal per image: its `known` focal where given; else the median of the Weiszfeld
/// focals of its own-frame pointmaps (the pairs it comes first in), pooled into one median
/// over the images without a known focal when every image has the same size.
fn pooled_focals(preds: &[PairPrediction], known: &[Option<f64>]) -> Vec<f64> {
    let n = known.len();
    let mut per: Vec<Vec<f64>> = vec![Vec::new(); n];
    for p in preds.iter().filter(|p| known[p.i].is_none()) {
        let f = focal_or_fallback(&p.pts_i, p.pts_i.width(), p.pts_i.height()).unwrap_or_else(|f| f);
        per[p.i].push(f);
    }
    let sizes: HashSet<(usize, usize)> = preds.iter().map(|p| (p.pts_i.width(), p.pts_i.height())).collect();
    if sizes.len() == 1 {
        let mut all: Vec<f64> = per.concat();
        let f = median(&mut all).unwrap_or(1.0);
        per = vec![vec![f]; n];
    }
    known.iter().zip(per.iter_mut()).map(|(k, v)| k.unwrap_or_else(|| median(v).unwrap_or(1.0))).collect()
}

/// A pointmap rebuilt from its depth (z) along the rays of a pinhole of focal `f` (principal
/// point at the centre, as global alignment assumes); invalid points stay invalid.
fn pinhole(pts: &Raster<Vec3>, f: f64) -> Raster<Vec3> {
    let (cx, cy) = (pts.width() as f64 / 2.0, pts.height() as f64 / 2.0);
    let mut out = pts.clone();
    for y in 0..pts.height() {
        for x in 0..pts.width() {
            let z = pts.get(x, y).z as f64;
            let q = if z.is_finite() && z > 0.0 {
                DVec3::new((x as f64 - cx) / f * z, (y as f64 - cy) / f * z, z).as_vec3()
            } else {
                Vec3::NAN
            };
            *out.get_mut(x, y) = q;
        }
    }
    out
}

fn swap(m: Match) -> Match {
    Match { a: m.b, b: m.a, conf: m.conf }
}

fn accumulate_normals(acc: &mut Option<(Vec<Vec3>, Vec<f32>)>, n: &Raster<Vec3>, conf: &Raster<f32>) {
    let (sum, wsum) = acc.get_or_insert_with(|| (vec![Vec3::ZERO; n.data().len()], vec![0.0; n.data().len()]));
    for (k, (&nk, &c)) in n.data().iter().zip(conf.data()).enumerate() {
        if nk.is_finite() && nk.length_squared() > 0.0 && c.is_finite() && c > 0.0 {
            sum[k] += nk * c;
            wsum[k] += c;
        }
    }
}

/// Reciprocal matches of one pair run, or None when the model has no descriptors.
fn match_pair(out: &[ViewOutput; 2], opts: &MatchOptions) -> Result<Option<Vec<Match>>, String> {
    let (Some(da), Some(db)) = (&out[0].desc, &out[1].desc) else { return Ok(None) };
    reciprocal_matches(&descriptors(da), &descriptors(db), match_conf(&out[0]), match_conf(&out[1]), opts).map(Some)
}

/// The confidence a view's matches are filtered by: the descriptor's own, else the pointmap's.
fn match_conf(v: &ViewOutput) -> &[f32] {
    v.desc_conf.as_ref().unwrap_or(&v.conf).data()
}

fn descriptors(m: &dens3r_backbone::predict::DescriptorMap) -> Descriptors<'_> {
    Descriptors { width: m.width, height: m.height, dim: m.dim, data: &m.data }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::transform::axis_angle;
    use glam::DMat3;

    /// Two cameras around a few world points; pair (1, 0) placed by the similarity that takes
    /// view 0's own points (at half scale) into camera 1's frame. Mirroring gives pair (0, 1)
    /// view 1's points in camera 0's frame at view 0's scale, as the cameras say, and leaves
    /// placed pairs alone.
    #[test]
    fn the_reverse_of_a_placed_pair_takes_its_placement_inverted() {
        let world: Vec<DVec3> = (0..12).map(|k| DVec3::new(k as f64 * 0.1 - 0.5, (k % 3) as f64 * 0.2, 3.0)).collect();
        // World -> camera k: x_k = R_k x + t_k.
        let (r0, t0) = (DMat3::IDENTITY, DVec3::ZERO);
        let (r1, t1) = (axis_angle(DVec3::Y, 0.3), DVec3::new(-0.7, 0.1, 0.2));
        let raster = |f: &dyn Fn(DVec3) -> DVec3| {
            Raster::from_vec(4, 3, world.iter().map(|&p| f(p).as_vec3()).collect()).unwrap()
        };
        // Own-frame pointmaps: view 0 at half its true scale, view 1 at true scale.
        let own0 = raster(&|p| (r0 * p + t0) * 0.5);
        let own1 = raster(&|p| r1 * p + t1);
        let ones = Raster::from_vec(4, 3, vec![2.0f32; 12]).unwrap();
        let nan = Raster::from_vec(4, 3, vec![Vec3::NAN; 12]).unwrap();
        let pred = |i, j, pts_i: &Raster<Vec3>| PairPrediction {
            i,
            j,
            pts_i: pts_i.clone(),
            pts_j: nan.clone(),
            conf_i: ones.clone(),
            conf_j: ones.clone(),
        };
        let mut preds = vec![pred(0, 1, &own0), pred(1, 0, &own1)];
        let order = [(0, 1), (1, 0)];
        // (1, 0): own0 (half scale, camera 0) -> camera 1: x_1 = R1 (2 y) + t1.
        let t10 = Sim3 { scale: 2.0, rotation: r1, translation: t1 };
        let placed = HashMap::from([((1, 0), t10)]);
        let mirrored = mirror_placements(&mut preds, &order, &placed);
        assert_eq!(mirrored, HashSet::from([(0, 1)]));
        // Expected: view 1's points in camera 0's frame, at view 0's (half) scale.
        for (k, &p) in world.iter().enumerate() {
            let want = (r0 * p + t0) * 0.5;
            let got = preds[0].pts_j.data()[k].as_dvec3();
            assert!((got - want).length() < 1e-5, "{k}: {got} vs {want}");
        }
        assert!(preds[1].pts_j.data().iter().all(|p| p.is_nan()), "a placed pair is left alone");
    }

    /// The noise-surface bunny's run (no pair placed; its ten 512x384 views' estimated focals
    /// 47.8-700.1 px) warns twice; the gravel bunny's kind of run (pairs placed, focals known
    /// from the cycles) and photos of another size, known focals and focals within 2x do not.
    #[test]
    fn cameras_that_cannot_be_trusted_are_named() {
        let bunny = [616.4, 668.5, 700.1, 161.2, 664.0, 47.8, 627.3, 70.9, 641.0, 632.2].map(Some);
        let w = camera_warnings(&[(512, 384); 10], &bunny, true);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[0].contains("no pair was placed"), "{w:?}");
        assert!(w[1].contains("10 photos of 512x384") && w[1].contains("47.8 to 700.1"), "{w:?}");
        assert!(camera_warnings(&[(512, 384); 10], &[None; 10], false).is_empty());
        // Within 2x of each other; the odd one out is of another size or known.
        let sizes = [(512, 384), (512, 384), (512, 384), (384, 512)];
        assert!(camera_warnings(&sizes, &[Some(400.0), Some(790.0), Some(500.0), Some(40.0)], false).is_empty());
        assert!(camera_warnings(&sizes, &[Some(400.0), Some(500.0), None, Some(40.0)], false).is_empty());
        let w = camera_warnings(&sizes, &[Some(400.0), Some(810.0), Some(500.0), Some(40.0)], false);
        assert!(w.len() == 1 && w[0].contains("3 photos of 512x384"), "{w:?}");
        // A NaN focal is no agreement either.
        assert_eq!(camera_warnings(&sizes, &[Some(400.0), Some(f64::NAN), None, None], false).len(), 1);
    }
}
