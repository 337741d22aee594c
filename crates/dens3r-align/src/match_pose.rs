//! A pair's second view placed by its matches instead of the network's cross-view pointmap
//! (MASt3R-SfM's idea, on dense outputs): the second view's **own-frame** pointmap (from the
//! pair run the other way round, where it is the first view) is moved into the first view's
//! frame by the similarity that best maps its matched points onto the first view's points at
//! the matching pixels, found by RANSAC over three-match samples and refitted on the inliers.
//!
//! A network's single-view geometry (a view in its own frame) is learned long before its
//! cross-view geometry; with matching descriptors, a pair's relative pose then needs only the
//! former. The result is used only where enough matches agree; otherwise the network's own
//! cross-view pointmap stays. (A 3-D/3-D fit, not PnP: the DLT behind PnP with an unknown
//! focal is degenerate when the matches lie on one plane, as a wall's do.)

use crate::epipolar::{essential_ransac, triangulate, EpipolarOptions};
use crate::matching::Match;
use crate::resection::SplitMix;
use dens3r_geom::align::umeyama;
use dens3r_geom::focal::median;
use dens3r_geom::transform::Sim3;
use dens3r_geom::{Raster, Vec3};
use glam::{DMat3, DVec2, DVec3};

/// When a matched placement is trusted.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchPoseOptions {
    /// Fewest inlier matches.
    pub min_inliers: usize,
    /// Smallest inlier fraction of the usable matches.
    pub min_inlier_ratio: f64,
    /// Inlier distance, as a fraction of the first view's median distance from its points'
    /// centroid (the scene's size in its units).
    pub threshold: f64,
    /// RANSAC samples tried.
    pub iterations: usize,
}

impl Default for MatchPoseOptions {
    fn default() -> Self {
        Self { min_inliers: 30, min_inlier_ratio: 0.25, threshold: 0.03, iterations: 256 }
    }
}

/// A second view placed in the first view's frame.
#[derive(Debug, Clone)]
pub struct MatchedPose {
    /// The similarity taking the second view's own-frame points into the first view's frame.
    pub transform: Sim3,
    /// The second view's points in the first view's frame (NaN where invalid).
    pub points: Raster<Vec3>,
    /// Inlier matches.
    pub inliers: usize,
    /// Matches with a finite point in both views.
    pub usable: usize,
}

/// Places view 2 from `matches` (`a` in view 1, `b` in view 2): `pts1` is view 1 in a frame of
/// a pair run with it first and `own2` view 2 in a frame of a pair run with it first (each its
/// camera frame up to a similarity, as [`crate::PairPrediction`]s are). The result is view 2's
/// points in `pts1`'s frame. `None` when too few matches agree on one similarity.
pub fn pose_from_matches(
    pts1: &Raster<Vec3>,
    own2: &Raster<Vec3>,
    matches: &[Match],
    opts: &MatchPoseOptions,
) -> Option<MatchedPose> {
    let (mut src, mut dst, mut wts) = (Vec::new(), Vec::new(), Vec::new());
    for m in matches {
        let ((xa, ya), (xb, yb)) = (m.a, m.b);
        if xa >= pts1.width() || ya >= pts1.height() || xb >= own2.width() || yb >= own2.height() {
            continue;
        }
        let (p, q) = (*own2.get(xb, yb), *pts1.get(xa, ya));
        if p.is_finite() && q.is_finite() {
            src.push(p.as_dvec3());
            dst.push(q.as_dvec3());
            wts.push(if m.conf.is_finite() && m.conf > 0.0 { m.conf as f64 } else { 1.0 });
        }
    }
    let usable = src.len();
    if usable < opts.min_inliers.max(3) {
        return None;
    }
    // The inlier distance in view 1's units: a fraction of the scene's size there (all of view
    // 1's points, so a tight cluster of matches does not shrink it).
    let all: Vec<DVec3> = pts1.data().iter().step_by(7).filter(|p| p.is_finite()).map(|p| p.as_dvec3()).collect();
    let centroid = all.iter().copied().sum::<DVec3>() / all.len().max(1) as f64;
    let mut spread: Vec<f64> = all.iter().map(|q| (*q - centroid).length()).collect();
    let thr = opts.threshold * dens3r_geom::focal::median(&mut spread)?;
    if !(thr.is_finite() && thr > 0.0) {
        return None;
    }
    let inliers_of =
        |t: &Sim3| -> Vec<bool> { src.iter().zip(&dst).map(|(p, q)| (t.apply(*p) - *q).length() < thr).collect() };
    let fit = |mask: &[bool]| -> Option<Sim3> {
        let pick = |v: &[DVec3]| -> Vec<DVec3> { v.iter().zip(mask).filter(|(_, &m)| m).map(|(x, _)| *x).collect() };
        let w: Vec<f64> = wts.iter().zip(mask).filter(|(_, &m)| m).map(|(x, _)| *x).collect();
        umeyama(&pick(&src), &pick(&dst), Some(&w), true).ok().filter(|t| t.scale.is_finite() && t.scale > 0.0)
    };
    let mut rng = SplitMix(0x5eed_u64 ^ usable as u64);
    let mut best: Option<(usize, Vec<bool>)> = None;
    for _ in 0..opts.iterations {
        let (i, j, k) = (rng.below(usable), rng.below(usable), rng.below(usable));
        if i == j || j == k || i == k {
            continue;
        }
        let mut mask = vec![false; usable];
        for x in [i, j, k] {
            mask[x] = true;
        }
        let Some(t) = fit(&mask) else { continue };
        let m = inliers_of(&t);
        let n = m.iter().filter(|&&x| x).count();
        if best.as_ref().is_none_or(|b| n > b.0) {
            best = Some((n, m));
        }
    }
    // Refit on the inliers until they stop changing.
    let (_, mut mask) = best?;
    let mut transform = fit(&mask)?;
    for _ in 0..5 {
        let m = inliers_of(&transform);
        if m == mask {
            break;
        }
        mask = m;
        transform = fit(&mask)?;
    }
    let inliers = mask.iter().filter(|&&m| m).count();
    if inliers < opts.min_inliers || (inliers as f64) < opts.min_inlier_ratio * usable as f64 {
        return None;
    }
    let points = own2.map(|q| if q.is_finite() { transform.apply(q.as_dvec3()).as_vec3() } else { Vec3::NAN });
    Some(MatchedPose { transform, points, inliers, usable })
}

/// When a pair placed by keypoint matches ([`pose_from_keypoints`]) is trusted.
#[derive(Debug, Clone, PartialEq)]
pub struct KeypointPoseOptions {
    /// Essential-matrix RANSAC.
    pub epipolar: EpipolarOptions,
    /// Fewest inlier matches.
    pub min_inliers: usize,
    /// Smallest inlier fraction of the matches.
    pub min_inlier_ratio: f64,
}

impl Default for KeypointPoseOptions {
    fn default() -> Self {
        Self { epipolar: EpipolarOptions::default(), min_inliers: 30, min_inlier_ratio: 0.3 }
    }
}

/// Places view 2 by keypoint correspondences `(a[k] in view 1, b[k] in view 2)`, pixels) and
/// their epipolar geometry, so that its rotation owes nothing to the network's depth: the
/// essential matrix at the views' focals `(f1, f2)` (pixels; principal point at the centre)
/// gives the rotation and the translation's
/// direction, and the inliers' triangulated depths against the network's depths at the same
/// pixels give the translation's length and view 2's scale (medians of the ratios). `pts1` and
/// `own2` must be camera-frame pointmaps (each up to its own scale) along pinhole rays with the
/// principal point at the image centre; `reconstruct` rebuilds the network's so. Returns the
/// placement and the inlier mask; `None` when too few matches agree or no scale can be read.
pub fn pose_from_keypoints(
    pts1: &Raster<Vec3>,
    own2: &Raster<Vec3>,
    (f1, f2): (f64, f64),
    a: &[DVec2],
    b: &[DVec2],
    opts: &KeypointPoseOptions,
) -> Option<(MatchedPose, Vec<bool>)> {
    let norm = |p: &Raster<Vec3>, f: f64, q: DVec2| {
        DVec2::new((q.x - p.width() as f64 / 2.0) / f, (q.y - p.height() as f64 / 2.0) / f)
    };
    let na: Vec<DVec2> = a.iter().map(|&q| norm(pts1, f1, q)).collect();
    let nb: Vec<DVec2> = b.iter().map(|&q| norm(own2, f2, q)).collect();
    let pose = essential_ransac(&na, &nb, (f1 * f2).sqrt(), &opts.epipolar)?;
    let inliers = pose.inlier_count();
    if inliers < opts.min_inliers || (inliers as f64) < opts.min_inlier_ratio * a.len() as f64 {
        return None;
    }
    let depth_at = |p: &Raster<Vec3>, q: DVec2| -> Option<f64> {
        let (x, y) = (q.x.round(), q.y.round());
        if x < 0.0 || y < 0.0 || x >= p.width() as f64 || y >= p.height() as f64 {
            return None;
        }
        let z = p.get(x as usize, y as usize).z as f64;
        (z.is_finite() && z > 0.0).then_some(z)
    };
    // Each inlier's network depth over its triangulated depth, in both views, under a pose.
    let ratios = |r: &DMat3, t: DVec3| -> (Vec<f64>, Vec<f64>) {
        let (mut s1, mut s2) = (Vec::new(), Vec::new());
        for k in (0..a.len()).filter(|&k| pose.inliers[k]) {
            let Some((za, zb)) = triangulate(r, t, na[k], nb[k]) else { continue };
            if let (Some(d1), Some(d2)) = (depth_at(pts1, a[k]), depth_at(own2, b[k])) {
                if za > 0.0 && zb > 0.0 {
                    s1.push(d1 / za);
                    s2.push(d2 / zb);
                }
            }
        }
        (s1, s2)
    };
    // Where the epipolar geometry leaves alternatives (most inliers on one plane), the pose
    // whose triangulated depths agree best with the network's (up to one scale per view:
    // least spread of the log ratios) wins.
    let spread = |v: &[f64]| -> f64 {
        let mut l: Vec<f64> = v.iter().map(|x| x.ln()).collect();
        let Some(m) = median(&mut l.clone()) else { return f64::INFINITY };
        l.iter_mut().for_each(|x| *x = (*x - m).abs());
        median(&mut l).unwrap_or(f64::INFINITY)
    };
    let (r, t) = std::iter::once((pose.rotation, pose.translation))
        .chain(pose.alternatives.iter().copied())
        .map(|(r, t)| {
            let (s1, s2) = ratios(&r, t);
            let score =
                if s1.len() < opts.min_inliers.min(inliers) { f64::INFINITY } else { spread(&s1) + spread(&s2) };
            (r, t, score)
        })
        .min_by(|x, y| x.2.total_cmp(&y.2))
        .map(|(r, t, _)| (r, t))
        .expect("at least the pose itself");
    let (mut s1, mut s2) = ratios(&r, t);
    if s1.len() < opts.min_inliers.min(inliers) {
        return None;
    }
    let (s1, s2) = (median(&mut s1)?, median(&mut s2)?);
    if !(s1.is_finite() && s2.is_finite() && s1 > 0.0 && s2 > 0.0) {
        return None;
    }
    // own2 = s2 * (camera 2, unit baseline); camera 1 = R^T (camera 2 - t); pts1 = s1 * camera 1.
    let rt = r.transpose();
    let transform = Sim3 { scale: s1 / s2, rotation: rt, translation: -s1 * (rt * t) };
    let points = own2.map(|q| if q.is_finite() { transform.apply(q.as_dvec3()).as_vec3() } else { Vec3::NAN });
    Some((MatchedPose { transform, points, inliers, usable: a.len() }, pose.inliers))
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::transform::axis_angle;

    /// Two cameras (focal 200, 160x120) looking at a bumpy surface; view 2 turned 20 degrees
    /// about y and moved; its own points are given at a third of the true scale.
    /// The farthest of a few placed points from view 2's true point in camera 1's frame
    /// (`own2` is [`scene`]'s: a third of the true scale).
    fn worst_placed(placed: &Raster<Vec3>, own2: &Raster<Vec3>, rot: DMat3, t: DVec3) -> f64 {
        [(60, 80), (10, 10), (100, 150), (30, 120)]
            .into_iter()
            .map(|(y, x)| {
                let truth = rot.transpose() * (own2.get(x, y).as_dvec3() * 3.0 - t);
                (placed.get(x, y).as_dvec3() - truth).length()
            })
            .fold(0.0, f64::max)
    }

    fn scene() -> (Raster<Vec3>, Raster<Vec3>, DMat3, DVec3, Vec<Match>) {
        let (w, h, f) = (160usize, 120usize, 200.0f64);
        let depth = |x: f64, y: f64| 3.0 + 0.6 * (x * 9.0).sin() * (y * 7.0).cos();
        // Surface points in camera 1: the ray through each pixel hits depth(x, y).
        let ray = |u: f64, v: f64| DVec3::new((u - 80.0) / f, (v - 60.0) / f, 1.0);
        let pts1 = Raster::from_fn(w, h, |x, y| {
            let r = ray(x as f64, y as f64);
            (r * depth(r.x, r.y)).as_vec3()
        });
        let rot = axis_angle(DVec3::Y, 20f64.to_radians());
        let t = DVec3::new(-0.8, 0.1, 0.2);
        // View 2's own points: march each of its rays to the surface (fixed-point on depth).
        let own2 = Raster::from_fn(w, h, |x, y| {
            let d2 = ray(x as f64, y as f64);
            let mut s = 3.0;
            for _ in 0..60 {
                let p1 = rot.transpose() * (d2 * s - t);
                s += (depth(p1.x / p1.z, p1.y / p1.z) - p1.z) * 0.5;
            }
            (d2 * s / 3.0).as_vec3()
        });
        // Matches: every 7th pixel of view 1 projected into view 2.
        let mut m = Vec::new();
        for y in (0..h).step_by(7) {
            for x in (0..w).step_by(7) {
                let c = rot * pts1.get(x, y).as_dvec3() + t;
                let (u, v) = (f * c.x / c.z + 80.0, f * c.y / c.z + 60.0);
                if u >= 0.0 && v >= 0.0 && u < w as f64 - 0.5 && v < h as f64 - 0.5 {
                    m.push(Match { a: (x, y), b: (u.round() as usize, v.round() as usize), conf: 2.0 });
                }
            }
        }
        (pts1, own2, rot, t, m)
    }

    /// The pose and placed points of `own2` (view 2's points at a third of the truth,
    /// mapped by `frame`) against the truth.
    fn check(frame: &dens3r_geom::transform::Sim3) {
        let (pts1, own2, rot, t, m) = scene();
        let moved = own2.map(|q| frame.apply(q.as_dvec3()).as_vec3());
        let p = pose_from_matches(&pts1, &moved, &m, &MatchPoseOptions::default()).expect("a pose");
        // Camera 2's orientation in camera 1's frame: the fitted map composed with `frame`
        // against the truth (rot^T).
        let dr = p.transform.rotation * frame.rotation * rot;
        let angle = dens3r_geom::transform::rotation_angle_deg(&dr);
        assert!(angle < 0.5, "rotation error {angle} deg");
        assert!((p.transform.scale * frame.scale - 3.0).abs() < 0.03, "scale {}", p.transform.scale * frame.scale);
        assert!(p.inliers as f64 > 0.9 * p.usable as f64, "{} of {}", p.inliers, p.usable);
        // Every placed point is view 2's true point in camera 1's frame.
        let worst = worst_placed(&p.points, &own2, rot, t);
        assert!(worst < 0.05, "placed points off by {worst}");
    }

    #[test]
    fn recovers_the_relative_pose_focal_and_placed_points() {
        use dens3r_geom::transform::Sim3;
        // View 2's points in its camera frame (as Dens3R gives a pair's first view) ...
        check(&Sim3::IDENTITY);
        // ... or in any similarity of it.
        check(&Sim3 {
            scale: 0.4,
            rotation: axis_angle(DVec3::new(0.3, -1.0, 0.5).normalize(), 0.7),
            translation: DVec3::new(0.5, -2.0, 1.0),
        });
    }

    /// Keypoints: every 5th pixel of view 1 and its exact (sub-pixel) projection in view 2,
    /// the last `outliers` of them moved to random places in view 2.
    fn keypoints(pts1: &Raster<Vec3>, rot: DMat3, t: DVec3, outliers: usize) -> (Vec<DVec2>, Vec<DVec2>) {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for y in (0..120).step_by(5) {
            for x in (0..160).step_by(5) {
                let c = rot * pts1.get(x, y).as_dvec3() + t;
                let (u, v) = (200.0 * c.x / c.z + 80.0, 200.0 * c.y / c.z + 60.0);
                if u >= 0.0 && v >= 0.0 && u < 159.5 && v < 119.5 {
                    a.push(DVec2::new(x as f64, y as f64));
                    b.push(DVec2::new(u, v));
                }
            }
        }
        let n = b.len();
        let mut rng = SplitMix(3);
        for q in &mut b[n - outliers..] {
            *q = DVec2::new(rng.below(1600) as f64 / 10.0, rng.below(1200) as f64 / 10.0);
        }
        (a, b)
    }

    /// The epipolar placement recovers the relative rotation, view 2's scale (its points are
    /// given at a third of the truth) and its points in view 1's frame, with a quarter of the
    /// correspondences wrong; nearly none of the wrong ones are inliers.
    #[test]
    fn keypoints_place_the_second_view() {
        let (pts1, own2, rot, t, _) = scene();
        let (a, _) = keypoints(&pts1, rot, t, 0);
        let n = a.len();
        let (a, b) = keypoints(&pts1, rot, t, n / 4);
        let (p, inl) =
            pose_from_keypoints(&pts1, &own2, (200.0, 200.0), &a, &b, &KeypointPoseOptions::default()).expect("a pose");
        let dr = p.transform.rotation * rot;
        let angle = dens3r_geom::transform::rotation_angle_deg(&dr);
        // Random correspondences that fall near an epipolar line tilt the fit slightly.
        assert!(angle < 0.25, "rotation error {angle} deg");
        assert!((p.transform.scale / 3.0 - 1.0).abs() < 0.04, "scale {}", p.transform.scale);
        let wrong = inl[n - n / 4..].iter().filter(|&&m| m).count();
        let right = inl[..n - n / 4].iter().filter(|&&m| m).count();
        // A random point lies within the threshold of its epipolar line about 2% of the time.
        assert!(
            wrong as f64 <= 0.05 * (n / 4) as f64 && right as f64 > 0.95 * (n - n / 4) as f64,
            "{right} right and {wrong} wrong inliers"
        );
        let worst = worst_placed(&p.points, &own2, rot, t);
        // 3% of the scene's depth (about 3).
        assert!(worst < 0.1, "placed points off by {worst}");
    }

    /// Two views sharing only a wall (the plane z = 3 + 0.4 x, in a 25 degree strip of each
    /// 320x320 view, focal 250), 28 degrees apart, keypoints with +-0.2 px noise and exact
    /// depths: the epipolar fit alone lands about 7 degrees off; the plane's homography
    /// offers the true pose, and the network's depth (here exact) picks it.
    #[test]
    fn depth_picks_the_pose_on_a_plane() {
        let (w, h, f) = (320usize, 320usize, 250.0f64);
        let rot = axis_angle(DVec3::Y, -28f64.to_radians());
        let t = DVec3::new(0.35, 0.0, 0.15);
        let ray = |x: f64, y: f64| DVec3::new((x - w as f64 / 2.0) / f, (y - h as f64 / 2.0) / f, 1.0);
        // Plane n . x = c in each camera's frame.
        let (n1, c1) = (DVec3::new(-0.4, 0.0, 1.0), 3.0);
        let (n2, c2) = (rot * n1, c1 + (rot * n1).dot(t));
        let on_plane = |n: DVec3, c: f64, x: usize, y: usize| {
            let d = ray(x as f64, y as f64);
            let s = c / n.dot(d);
            if s > 0.0 {
                (d * s).as_vec3()
            } else {
                Vec3::NAN
            }
        };
        let pts1 = Raster::from_fn(w, h, |x, y| on_plane(n1, c1, x, y));
        let own2 = Raster::from_fn(w, h, |x, y| on_plane(n2, c2, x, y) * 0.5);
        let (a, b) = crate::epipolar::tests::planar_scene(rot, t, f);
        let px = |q: DVec2| DVec2::new(q.x * f + w as f64 / 2.0, q.y * f + h as f64 / 2.0);
        let (a, b): (Vec<DVec2>, Vec<DVec2>) = a.into_iter().zip(b).map(|(p, q)| (px(p), px(q))).unzip();
        assert!(a.iter().chain(&b).all(|q| q.x >= 0.0 && q.y >= 0.0 && q.x < w as f64 && q.y < h as f64));
        let opts = KeypointPoseOptions::default();
        let norm = |v: &[DVec2]| v.iter().map(|q| (*q - DVec2::new(160.0, 160.0)) / f).collect::<Vec<_>>();
        let plain = crate::epipolar::essential_ransac(&norm(&a), &norm(&b), f, &opts.epipolar).unwrap();
        let plain_err = dens3r_geom::transform::rotation_angle_deg(&(plain.rotation.transpose() * rot));
        eprintln!("epipolar fit alone: {plain_err:.2} deg off, {} alternative(s)", plain.alternatives.len());
        assert!(plain_err > 2.0 && !plain.alternatives.is_empty(), "{plain_err}");
        let (p, _) = pose_from_keypoints(&pts1, &own2, (f, f), &a, &b, &opts).expect("a pose");
        let angle = dens3r_geom::transform::rotation_angle_deg(&(p.transform.rotation * rot));
        assert!(angle < 0.5, "rotation error {angle} deg");
        assert!((p.transform.scale / 2.0 - 1.0).abs() < 0.02, "scale {}", p.transform.scale);
    }

    /// Correspondences with no common geometry place nothing.
    #[test]
    fn keypoints_that_disagree_are_refused() {
        let (pts1, own2, rot, t, _) = scene();
        let (a, _) = keypoints(&pts1, rot, t, 0);
        let n = a.len();
        let (_, b) = keypoints(&pts1, rot, t, n);
        assert!(pose_from_keypoints(&pts1, &own2, (200.0, 200.0), &a, &b, &KeypointPoseOptions::default()).is_none());
    }

    #[test]
    fn random_matches_are_refused() {
        let (pts1, own2, _, _, m) = scene();
        assert!(pose_from_matches(&pts1, &own2, &m, &MatchPoseOptions::default()).is_some());
        // Shuffle the view-2 pixels: no camera explains them.
        let n = m.len();
        let shuffled: Vec<Match> =
            m.iter().enumerate().map(|(i, x)| Match { b: m[(i * 7919 + 13) % n].b, ..*x }).collect();
        assert!(pose_from_matches(&pts1, &own2, &shuffled, &MatchPoseOptions::default()).is_none());
        assert!(pose_from_matches(&pts1, &own2, &m[..10], &MatchPoseOptions::default()).is_none());
    }
}
