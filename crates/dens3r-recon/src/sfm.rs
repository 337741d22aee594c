//! Cameras by global structure-from-motion ([`dens3r_sfm`]), depth and normals by the network:
//! SIFT keypoints of every photo -> the SfM's cameras and points (no network) -> one network
//! pass per registered photo (its self-pair, through the pair cache) for depth, confidence and normals ->
//! each registered view's depth scaled onto the SfM by the median ratio at its track points.
//! Views the SfM does not register are left out and named; with fewer than half registered,
//! the run falls back to the network's pairs and the dense alignment ([`crate::pipeline`]).

use crate::cache::{MonoMaps, PairCache};
use crate::input::InputImage;
use crate::pipeline::{reconstruct_dense, ReconOptions, ReconStats, Reconstruction, Stage};
use crate::predictor::PairPredictor;
use crate::ReconError;
use dens3r_align::keypoints::{detect_with_gain, Keypoints};
use dens3r_align::matching::Match;
use dens3r_align::{AlignedView, Alignment};
use dens3r_io::panics::catch_quietly;
use dens3r_scene::export::TrackPoint;
use dens3r_sfm::{run, Sfm, SfmInput, SfmOptions};
use image::RgbImage;
use rayon::prelude::*;
use std::time::Instant;

/// Structure-from-motion settings of `reconstruct` ([`crate::ReconOptions::cameras`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SfmSettings {
    /// Strongest SIFT keypoints kept per photo.
    pub max_keypoints: usize,
    /// SIFT's difference-of-Gaussians gain ([`detect_with_gain`]): 3 keeps extrema of a third
    /// of OpenCV's contrast threshold, for the weak texture of rooms.
    pub sift_gain: f32,
    /// The stages' settings.
    pub sfm: SfmOptions,
}

impl Default for SfmSettings {
    fn default() -> Self {
        Self { max_keypoints: 4000, sift_gain: 3.0, sfm: SfmOptions::default() }
    }
}

/// Photo `k`'s own depth, confidence and normals (its self-pair, one network pass), through
/// `cache`.
pub(crate) fn mono_output(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    k: usize,
    warnings: &mut Vec<String>,
) -> Result<(MonoMaps, bool), ReconError> {
    let im = &images[k];
    let key = PairCache::key(&format!("{} mono", predictor.id()), im, im);
    cache.mono_or(&key, im.size(), warnings, || {
        let err = |msg: String| ReconError::Predict { a: im.name.clone(), b: im.name.clone(), msg };
        let v = predictor.predict_mono(images, k).map_err(err)?;
        v.check(im.size()).map_err(|m| err(m.to_string()))?;
        let depth = v.points.map(|p| if p.is_finite() && p.z > 0.0 { p.z } else { 0.0 });
        Ok(MonoMaps { depth, conf: v.conf, normals: v.normals })
    })
}

/// Runs the network once on each photo of `which` (its self-pair), through the cache.
fn mono_passes(
    images: &[InputImage],
    which: &[usize],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    stats: &mut ReconStats,
    progress: &mut impl FnMut(Stage, usize, usize),
) -> Result<Vec<Option<MonoMaps>>, ReconError> {
    let mut out: Vec<Option<MonoMaps>> = (0..images.len()).map(|_| None).collect();
    progress(Stage::Predict, 0, which.len());
    for (done, &k) in which.iter().enumerate() {
        let t = Instant::now();
        let (m, hit) = mono_output(images, predictor, cache, k, &mut stats.warnings)?;
        stats.cache_hits += usize::from(hit);
        out[k] = Some(m);
        stats.predict_seconds += t.elapsed().as_secs_f64();
        progress(Stage::Predict, done + 1, which.len());
    }
    stats.pairs = which.len();
    Ok(out)
}

/// Each registered view's depth scale: the median of SfM depth over network depth at its
/// track points (the network's depth is known up to scale); views with fewer than 5 usable
/// points take the median scale of the others.
fn depth_scales(sfm: &Sfm, kps: &[Keypoints], mono: &[Option<MonoMaps>]) -> Vec<Option<f64>> {
    let n = mono.len();
    let mut ratios: Vec<Vec<f64>> = vec![Vec::new(); n];
    for p in &sfm.points {
        for &(v, kp) in &p.observations {
            let Some(cam) = &sfm.cameras[v] else { continue };
            let z = cam.world_to_cam().transform_point3(p.xyz).z;
            let xy = kps[v].xy[kp];
            let (x, y) = (xy.x.round(), xy.y.round());
            let Some(m) = &mono[v] else { continue };
            let d = &m.depth;
            if x < 0.0 || y < 0.0 || x as usize >= d.width() || y as usize >= d.height() {
                continue;
            }
            let zn = *d.get(x as usize, y as usize) as f64;
            if zn > 0.0 && z > 0.0 {
                ratios[v].push(z / zn);
            }
        }
    }
    let med = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut own: Vec<Option<f64>> = ratios.iter_mut().map(|r| (r.len() >= 5).then(|| med(r))).collect();
    let mut all: Vec<f64> = own.iter().flatten().copied().collect();
    let fallback = (!all.is_empty()).then(|| med(&mut all));
    for (v, s) in own.iter_mut().enumerate() {
        if sfm.cameras[v].is_none() {
            *s = None;
        } else if s.is_none() {
            *s = fallback;
        }
    }
    own
}

/// `reconstruct` with SfM cameras (see the module's documentation).
pub fn reconstruct_sfm(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    opts: &ReconOptions,
    settings: &SfmSettings,
    mut progress: impl FnMut(Stage, usize, usize),
) -> Result<Reconstruction, ReconError> {
    let n = images.len();
    let sizes: Vec<(usize, usize)> = images.iter().map(|im| im.size()).collect();
    let rgb: Vec<RgbImage> = images.iter().map(|im| im.rgb()).collect();
    // The user's focals are kept; EXIF focals are priors that bundle adjustment refines.
    let known_focals: Vec<Option<f64>> = images.iter().map(|im| im.focal.filter(|_| im.focal_fixed)).collect();
    let prior_focals: Vec<Option<f64>> = images.iter().map(|im| im.focal.filter(|_| !im.focal_fixed)).collect();
    let mut stats = ReconStats {
        known_focals: images.iter().filter(|im| im.focal.is_some()).count(),
        warnings: images.iter().flat_map(|im| im.warnings.iter().cloned()).collect(),
        ..Default::default()
    };
    let t = Instant::now();
    // A panic inside the SIFT crate costs that photo its keypoints, not the run. Photos go in
    // groups (in parallel within each) so that progress is reported as they finish.
    let mut detected: Vec<Result<Keypoints, String>> = Vec::with_capacity(n);
    progress(Stage::Keypoints, 0, n);
    for (group, rgbs) in images.chunks(16).zip(rgb.chunks(16)) {
        detected.par_extend(group.par_iter().zip(rgbs).map(|(im, rgb)| {
            catch_quietly(|| detect_with_gain(rgb, settings.max_keypoints, settings.sift_gain))
                .map_err(|e| format!("{}: no SIFT keypoints ({e})", im.name))
        }));
        progress(Stage::Keypoints, detected.len(), n);
    }
    let kps: Vec<Keypoints> = detected
        .into_iter()
        .map(|r| {
            r.unwrap_or_else(|w| {
                stats.warnings.push(w);
                Keypoints::default()
            })
        })
        .collect();
    stats.keypoint_seconds = t.elapsed().as_secs_f64();
    // Structure from motion needs no network: a focal not known starts at 1.2 times the
    // photo's long side (COLMAP's guess) and bundle adjustment finds it.
    stats.graph = crate::graph::plan_pairs(images, predictor, cache, opts.graph, &mut stats.warnings, &mut progress)?;
    let pairs = &stats.graph.list;
    progress(Stage::Align, 0, 1);
    let t = Instant::now();
    let guesses: Vec<f64> = sizes.iter().map(|&(w, h)| 1.2 * w.max(h) as f64).collect();
    let input = SfmInput {
        keypoints: &kps,
        sizes: &sizes,
        known_focals: &known_focals,
        prior_focals: &prior_focals,
        focal_guess: &guesses,
        pairs,
    };
    let sfm = run(&input, &settings.sfm);
    // Only the keypoints' positions are read from here: their descriptors (half a GB at 300
    // photos) go before the network's maps come.
    let mut kps = kps;
    kps.iter_mut().for_each(|k| k.desc = Vec::new());
    stats.align_seconds = t.elapsed().as_secs_f64();
    progress(Stage::Align, 1, 1);
    let registered: Vec<usize> = (0..n).filter(|&v| sfm.cameras[v].is_some()).collect();
    // Groups of photos that share verified matches among themselves but none with each other
    // are separate scenes: never merged, by the dense path either.
    let scenes: Vec<&Vec<usize>> = sfm.groups.iter().filter(|g| g.len() > 1).collect();
    if registered.len() < 3.max(n.div_ceil(2)) && (scenes.len() < 2 || registered.len() < 2) {
        if scenes.len() >= 2 {
            // Several scenes, none registered: the dense path on the largest one alone.
            let group = scenes[0].clone();
            let subset: Vec<InputImage> = group.iter().map(|&v| images[v].clone()).collect();
            let mut dense = reconstruct_dense(&subset, predictor, cache, opts, progress)?;
            dense.inputs = dense.inputs.iter().map(|&k| group[k]).collect();
            let left: Vec<&str> = (0..n).filter(|v| !group.contains(v)).map(|v| images[v].name.as_str()).collect();
            dense.stats.warnings.insert(
                0,
                format!(
                    "structure from motion registered {} of {n} photos, and they fall into {} groups that share no verified match: \
                     only the largest ({} photos) is reconstructed, by the network's pairs and the dense alignment; groups are never merged; left out: {}",
                    registered.len(),
                    scenes.len(),
                    group.len(),
                    left.join(", ")
                ),
            );
            return Ok(dense);
        }
        let mut dense = reconstruct_dense(images, predictor, cache, opts, progress)?;
        dense.stats.warnings.insert(
            0,
            format!(
                "structure from motion registered {} of {n} photos (too little texture or overlap for SIFT?): \
                 the cameras come from the network's pairs and the dense alignment instead",
                registered.len()
            ),
        );
        return Ok(dense);
    }
    let unregistered: Vec<String> =
        (0..n).filter(|v| !registered.contains(v)).map(|v| images[v].name.clone()).collect();
    if !unregistered.is_empty() {
        let groups = sfm.groups.iter().filter(|g| g.len() > 1).count();
        stats.warnings.push(format!(
            "{} of {n} photos not registered by structure from motion and left out: {}{}",
            unregistered.len(),
            unregistered.join(", "),
            if groups > 1 {
                format!(" ({groups} groups of photos share no verified match: only the largest is reconstructed, groups are never merged)")
            } else {
                String::new()
            }
        ));
    }
    let mono = mono_passes(images, &registered, predictor, cache, &mut stats, &mut progress)?;
    let scales = depth_scales(&sfm, &kps, &mono);
    // Frames of the registered views only, in input order.
    let index: Vec<Option<usize>> = {
        let mut next = 0;
        (0..n)
            .map(|v| {
                sfm.cameras[v].map(|_| {
                    next += 1;
                    next - 1
                })
            })
            .collect()
    };
    let mut mono = mono;
    let mut views = Vec::with_capacity(registered.len());
    let mut normals = Vec::with_capacity(registered.len());
    for &v in &registered {
        let m = mono[v].take().expect("one per view");
        let s = scales[v].unwrap_or(1.0) as f32;
        views.push(AlignedView {
            camera: sfm.cameras[v].expect("registered"),
            depth: m.depth.map(|z| z * s),
            conf: m.conf,
        });
        normals.push(m.normals);
    }
    let matches: Vec<(usize, usize, Vec<Match>)> = sfm
        .edges
        .iter()
        .filter_map(|e| {
            let (a, b) = (index[e.i]?, index[e.j]?);
            let px = |v: usize, k: usize| {
                let p = kps[v].xy[k];
                (p.x.round().max(0.0) as usize, p.y.round().max(0.0) as usize)
            };
            Some((
                a,
                b,
                e.inliers.iter().map(|&(ka, kb)| Match { a: px(e.i, ka), b: px(e.j, kb), conf: 1.0 }).collect(),
            ))
        })
        .collect();
    let points: Vec<TrackPoint> = sfm
        .points
        .iter()
        .filter_map(|p| {
            let observations: Vec<(usize, (f64, f64))> = p
                .observations
                .iter()
                .filter_map(|&(v, k)| Some((index[v]?, (kps[v].xy[k].x, kps[v].xy[k].y))))
                .collect();
            let (v0, k0) = p.observations[0];
            let xy = kps[v0].xy[k0];
            let img = &rgb[v0];
            let (x, y) = ((xy.x.round() as u32).min(img.width() - 1), (xy.y.round() as u32).min(img.height() - 1));
            (observations.len() >= 2).then(|| TrackPoint {
                xyz: p.xyz,
                rgb: img.get_pixel(x, y).0,
                error: p.error_px,
                observations,
            })
        })
        .collect();
    stats.triangulated_points = points.len();
    stats.registered = registered.len();
    stats.known_focals = registered.iter().filter(|&&v| images[v].focal.is_some()).count();
    stats.unregistered = unregistered;
    stats.sfm = Some(sfm.stats.clone());
    let keep = |v: &usize| index[*v].is_some();
    Ok(Reconstruction {
        names: registered.iter().map(|&v| images[v].name.clone()).collect(),
        rgb: rgb.into_iter().enumerate().filter(|(v, _)| keep(v)).map(|(_, r)| r).collect(),
        alignment: Alignment {
            views,
            pair_transforms: vec![],
            loss: (sfm.stats.rms_px.0, sfm.stats.rms_px.1),
            warnings: vec![],
        },
        normals,
        matches,
        points,
        masks: images.iter().enumerate().filter(|(v, _)| keep(v)).map(|(_, im)| im.mask.clone()).collect(),
        inputs: registered,
        stats,
    })
}
