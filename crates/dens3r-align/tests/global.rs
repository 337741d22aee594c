//! Global alignment with oracle pairwise predictions: ground-truth pointmaps of a rendered room,
//! each pair in its own random similarity frame, with noise and random confidences. The
//! recovered cameras are compared with the truth after one similarity (the gauge).

use dens3r_align::{global_align, make_pairs, AlignOptions, PairGraph, PairPrediction};
use dens3r_geom::align::umeyama;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::transform::{axis_angle, rotation_angle_deg, Sim3};
use dens3r_geom::{DVec3, Intrinsics, PinholeCamera, Raster, Vec3};
use dens3r_render::path::room_walk;
use dens3r_render::procedural::{room, ROOM_HI, ROOM_LO};
use dens3r_render::World;
use glam::DMat3;
use rand::{Rng, SeedableRng};
use rand_distr_free::normal;

/// Box-Muller normal samples (no extra crate).
mod rand_distr_free {
    use rand::Rng;
    pub fn normal(rng: &mut impl Rng) -> f64 {
        let (u, v): (f64, f64) = (rng.gen_range(1e-12..1.0), rng.gen_range(0.0..1.0));
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

struct Truth {
    cameras: Vec<PinholeCamera>,
    pairs: Vec<PairPrediction>,
}

/// `n` views of the procedural room, different focals; every ordered pair of views as an
/// oracle prediction with relative noise `sigma` (per coordinate, times the point's distance).
fn oracle(n: usize, sigma: f64, seed: u64) -> Truth {
    oracle_with(n, sigma, seed, None, None)
}

/// [`oracle`], optionally with one field of view for every camera (`hfov`, degrees: one
/// camera's photos) and one image's points pulled towards its optical axis in x and y by a
/// factor (`squash`: the rays of a network that misjudges that image's focal) wherever they
/// appear.
fn oracle_with(n: usize, sigma: f64, seed: u64, hfov: Option<f64>, squash: Option<(usize, f32)>) -> Truth {
    let world = World::new(room(3)).unwrap();
    let (w, h) = (96, 72);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let cameras: Vec<PinholeCamera> = room_walk(ROOM_LO.as_dvec3(), ROOM_HI.as_dvec3(), 1.5, n, seed)
        .into_iter()
        .map(|pose| PinholeCamera {
            intrinsics: Intrinsics::from_hfov(w, h, hfov.unwrap_or(rng.gen_range(50.0..70.0))),
            width: w,
            height: h,
            cam_to_world: pose,
        })
        .collect();
    // Renderer pixel centres sit at integer coordinates with cx = W/2 as in the aligner.
    let mut own: Vec<Raster<Vec3>> =
        cameras.iter().map(|c| depth_to_pointmap(&world.render(c).depth, &c.intrinsics)).collect();
    if let Some((k, f)) = squash {
        own[k] = own[k].map(|p| Vec3::new(p.x * f, p.y * f, p.z));
    }
    let mut pairs = Vec::new();
    for (i, j) in make_pairs(n, PairGraph::Complete, true) {
        let sim = Sim3 {
            scale: rng.gen_range(0.3..3.0),
            rotation: axis_angle(
                DVec3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng)),
                rng.gen_range(0.0..3.0),
            ),
            translation: DVec3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng)),
        };
        let j_to_i = cameras[i].world_to_cam() * cameras[j].cam_to_world;
        let mut noisy = |p: Vec3, m: &glam::DMat4| -> Vec3 {
            if !(p.is_finite() && p.z > 0.0) {
                return Vec3::NAN;
            }
            let q = m.transform_point3(p.as_dvec3());
            let r = q.length() * sigma;
            let q = q + DVec3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng)) * r;
            sim.apply(q).as_vec3()
        };
        let pts_i = own[i].map(|&p| noisy(p, &glam::DMat4::IDENTITY));
        let pts_j = own[j].map(|&p| noisy(p, &j_to_i));
        let mut conf = || Raster::from_fn(w, h, |_, _| 1.0 + rng.gen_range(0.5f32..9.0));
        let (conf_i, conf_j) = (conf(), conf());
        pairs.push(PairPrediction { i, j, pts_i, pts_j, conf_i, conf_j });
    }
    Truth { cameras, pairs }
}

/// (max rotation error deg, max centre error / scene diagonal, max relative focal error).
fn errors(truth: &[PinholeCamera], est: &[PinholeCamera]) -> (f64, f64, f64) {
    let tc: Vec<DVec3> = truth.iter().map(|c| c.center()).collect();
    let ec: Vec<DVec3> = est.iter().map(|c| c.center()).collect();
    let gauge = umeyama(&ec, &tc, None, true).unwrap();
    let diag = (ROOM_HI - ROOM_LO).length() as f64;
    let mut rot: f64 = 0.0;
    let mut pos: f64 = 0.0;
    let mut foc: f64 = 0.0;
    for k in 0..truth.len() {
        let rt = DMat3::from_mat4(truth[k].cam_to_world);
        let re = gauge.rotation * DMat3::from_mat4(est[k].cam_to_world);
        rot = rot.max(rotation_angle_deg(&(rt.transpose() * re)));
        pos = pos.max((gauge.apply(ec[k]) - tc[k]).length() / diag);
        foc = foc.max((est[k].intrinsics.fx / truth[k].intrinsics.fx - 1.0).abs());
    }
    (rot, pos, foc)
}

#[test]
fn oracle_alignment_recovers_cameras() {
    let n = 8;
    let sizes = vec![(96, 72); n];
    for (sigma, strict) in [(0.0, true), (0.01, true), (0.03, false)] {
        let t = oracle(n, sigma, 11);
        let a = global_align(&sizes, &t.pairs, &AlignOptions::default(), |_, _| {}).unwrap();
        let est: Vec<PinholeCamera> = a.views.iter().map(|v| v.camera).collect();
        let (rot, pos, foc) = errors(&t.cameras, &est);
        eprintln!(
            "noise {:.0}%: max rotation error {rot:.3} deg, max centre error {:.3}% of the room diagonal, max focal error {:.3}%, loss {:.4} -> {:.4}",
            sigma * 100.0,
            pos * 100.0,
            foc * 100.0,
            a.loss.0,
            a.loss.1
        );
        if strict {
            assert!(rot < 1.0, "rotation error {rot} deg at noise {sigma}");
            assert!(pos < 0.01, "centre error {pos} at noise {sigma}");
            assert!(foc < 0.01, "focal error {foc} at noise {sigma}");
        }
        // The depth maps put every view's points where the truth has them (up to the gauge).
        if sigma > 0.0 {
            assert!(a.loss.1 < a.loss.0, "optimisation lowers the loss");
        } else {
            // Exact input: the initialisation is already at the optimum; Adam's normalised
            // steps may only jitter around it.
            assert!(a.loss.1 < 1e-3, "{:?}", a.loss);
            assert!(a.views.iter().all(|v| v.depth.data().iter().filter(|&&d| d > 0.0).count() > 96 * 72 / 2));
        }
    }
}

#[test]
fn bad_inputs_are_errors() {
    let t = oracle(4, 0.0, 5);
    let sizes = vec![(96, 72); 4];
    // Only forward pairs: image 3 never has a pointmap in its own frame.
    let fwd: Vec<PairPrediction> = t.pairs.iter().filter(|p| p.i < p.j).cloned().collect();
    let e = global_align(&sizes, &fwd, &AlignOptions::default(), |_, _| {}).unwrap_err();
    assert!(e.to_string().contains("symmetrize"), "{e}");
    // Two islands, {0, 1} and {2, 3}.
    let cut: Vec<PairPrediction> = t.pairs.iter().filter(|p| (p.i < 2) == (p.j < 2)).cloned().collect();
    let e = global_align(&sizes, &cut, &AlignOptions::default(), |_, _| {}).unwrap_err();
    assert!(e.to_string().contains("share no pair"), "{e}");
    // Wrong raster size.
    let e = global_align(&[(96, 72), (96, 72), (80, 60), (96, 72)], &t.pairs, &AlignOptions::default(), |_, _| {})
        .unwrap_err();
    assert!(e.to_string().contains("image 2 is 80x60"), "{e}");
}

/// PairViewer-style two-view poses: each camera resected by PnP-RANSAC in the pair frame.
/// Exact pointmaps give the exact pose; with 1% noise and a quarter of view j's points smeared
/// off the surface (as at depth edges), the smeared points are the outliers and rotation,
/// translation direction and focals still come back.
#[test]
fn relative_pose_by_pnp_ransac() {
    for (sigma, smear) in [(0.0, 0.0), (0.01, 0.25)] {
        let t = oracle(4, sigma, 21);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let (mut rot, mut dir, mut foc): (f64, f64, f64) = (0.0, 0.0, 0.0);
        for p in &t.pairs {
            let mut p = p.clone();
            let valid: Vec<Vec3> = p.pts_j.data().iter().filter(|q| q.is_finite()).copied().collect();
            let centre = valid.iter().sum::<Vec3>() / valid.len() as f32;
            for q in p.pts_j.data_mut() {
                if q.is_finite() && rng.gen_bool(smear) {
                    *q = centre + (*q - centre) * rng.gen_range(1.3..2.0);
                }
            }
            let r = dens3r_align::relative_pose(&p).expect("both views resect");
            let truth = t.cameras[p.i].world_to_cam() * t.cameras[p.j].cam_to_world;
            rot = rot.max(rotation_angle_deg(&(DMat3::from_mat4(truth).transpose() * DMat3::from_mat4(r.j_to_i))));
            let (a, b) = (truth.w_axis.truncate().normalize(), r.j_to_i.w_axis.truncate().normalize());
            dir = dir.max(a.dot(b).clamp(-1.0, 1.0).acos().to_degrees());
            foc = foc.max((r.focal_i / t.cameras[p.i].intrinsics.fx - 1.0).abs());
            foc = foc.max((r.focal_j / t.cameras[p.j].intrinsics.fx - 1.0).abs());
            assert!(r.inliers.0 > 0.99, "{:?}", r.inliers);
            assert!((r.inliers.1 - (1.0 - smear)).abs() < 0.05, "smeared points are the outliers: {:?}", r.inliers);
        }
        eprintln!(
            "two-view, noise {:.0}%, smear {:.0}%: rotation {rot:.3} deg, translation direction {dir:.3} deg, focal {:.3}%",
            sigma * 100.0,
            smear * 100.0,
            foc * 100.0
        );
        if sigma == 0.0 {
            assert!(rot < 1e-4 && dir < 1e-3 && foc < 1e-6, "{rot} {dir} {foc}");
        } else {
            assert!(rot < 0.5 && dir < 5.0 && foc < 0.05, "{rot} {dir} {foc}");
        }
    }
}

/// Known rotations (`AlignOptions::rotations`, e.g. averaged from keypoint pairs) in a frame of
/// their own, on noisy predictions (3%): the aligned cameras keep them exactly, up to the one
/// turn into the alignment's frame, so their relative rotations are the given ones (here the
/// true ones), where free alignment of the same predictions leaves them off.
#[test]
fn known_rotations_are_kept() {
    let n = 6;
    let sizes = vec![(96, 72); n];
    let t = oracle(n, 0.03, 13);
    let turn = axis_angle(DVec3::new(0.3, -1.0, 0.4), 1.2);
    let given: Vec<Option<DMat3>> = t.cameras.iter().map(|c| Some(turn * DMat3::from_mat4(c.cam_to_world))).collect();
    // Worst relative rotation of `views` against the true cameras' (no gauge needed).
    let worst = |views: &[dens3r_align::AlignedView]| -> f64 {
        let r = |k: usize| DMat3::from_mat4(views[k].camera.cam_to_world);
        let g = |k: usize| DMat3::from_mat4(t.cameras[k].cam_to_world);
        let mut worst: f64 = 0.0;
        for i in 0..n {
            for j in 0..n {
                let d = (r(i).transpose() * r(j)).transpose() * (g(i).transpose() * g(j));
                worst = worst.max(rotation_angle_deg(&d));
            }
        }
        worst
    };
    let opts = AlignOptions { rotations: given, ..AlignOptions::default() };
    let kept = worst(&global_align(&sizes, &t.pairs, &opts, |_, _| {}).unwrap().views);
    let free = worst(&global_align(&sizes, &t.pairs, &AlignOptions::default(), |_, _| {}).unwrap().views);
    eprintln!("worst relative rotation error: {kept:.2e} deg kept, {free:.3} deg free");
    assert!(kept < 1e-6 && free > 0.1, "{kept} vs {free}");
}

/// One camera's photos (every view at 60 degrees), one image's points squashed towards its axis
/// to 0.6 (a network misjudging that image's field of view), 2% noise: estimated per image,
/// that image's focal comes out far off the truth; shared (`AlignOptions::shared_focal`), every
/// image takes one focal, close to the truth. The price is printed: the squashed image's pose
/// then absorbs what its focal no longer can (here 0.3 -> 8 deg of rotation), which is why
/// sharing is opt-in.
#[test]
fn shared_focal_outvotes_one_misjudged_image() {
    let n = 8;
    let sizes = vec![(96, 72); n];
    let t = oracle_with(n, 0.02, 17, Some(60.0), Some((3, 0.6)));
    let run = |shared_focal: bool| {
        let opts = AlignOptions { shared_focal, ..AlignOptions::default() };
        let a = global_align(&sizes, &t.pairs, &opts, |_, _| {}).unwrap();
        a.views.iter().map(|v| v.camera).collect::<Vec<PinholeCamera>>()
    };
    let (own, shared) = (run(false), run(true));
    let (rot_own, _, foc_own) = errors(&t.cameras, &own);
    let (rot_shared, _, foc_shared) = errors(&t.cameras, &shared);
    eprintln!(
        "per image: max focal error {:.1}%, rotation {rot_own:.2} deg; shared: {:.1}%, {rot_shared:.2} deg",
        foc_own * 100.0,
        foc_shared * 100.0
    );
    assert!(shared.iter().all(|c| c.intrinsics.fx == shared[0].intrinsics.fx), "one focal for one camera");
    assert!(foc_own > 0.2 && foc_shared < 0.05, "{foc_own} {foc_shared}");
}
