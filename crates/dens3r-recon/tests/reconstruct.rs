//! The reconstruction pipeline end to end with an oracle predictor: rendered photos of the
//! procedural room go in as files; the "network" returns the true pointmaps (each pair in its
//! own random similarity frame), the true normals, and descriptors that are a known function of
//! the world position. Everything the pipeline adds (cache, matching, alignment, tracks,
//! outputs, fusion) is checked against the renderer's ground truth after one similarity.

use dens3r_backbone::predict::DescriptorMap;
use dens3r_geom::align::umeyama;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::transform::{axis_angle, rotation_angle_deg, Sim3};
use dens3r_geom::{DMat3, DVec3, Intrinsics, PinholeCamera, Raster, Vec3};
use dens3r_mesh::metrics::{mesh_metrics, MeshMetricsOptions};
use dens3r_recon::{
    list_images, load_images, reconstruct, write_outputs, Cameras, InputImage, KeypointOptions, OutputOptions,
    PairCache, PairPredictor, ReconOptions, ViewOutput, Wanted,
};
use dens3r_render::path::room_walk;
use dens3r_render::procedural::{room, ROOM_HI, ROOM_LO};
use dens3r_render::World;
use rand::{Rng, SeedableRng};
use std::cell::Cell;
use std::path::Path;

const W: usize = 160;
const H: usize = 112; // multiples of 16: preprocessing at --size 160 keeps every pixel

struct Truth {
    world: World,
    cams: Vec<PinholeCamera>,
    own: Vec<Raster<Vec3>>,
    normals: Vec<Raster<Vec3>>,
}

fn truth(n: usize) -> Truth {
    let walk = room_walk(ROOM_LO.as_dvec3(), ROOM_HI.as_dvec3(), 1.5, n, 4);
    truth_of(room(3), walk, W, H, None)
}

/// Photos of `objects` from camera-to-world `poses`, `w x h`, each camera's horizontal field
/// of view drawn from 55-70 degrees or `hfov` for all.
fn truth_of(
    objects: Vec<dens3r_render::Object>,
    poses: Vec<glam::DMat4>,
    w: usize,
    h: usize,
    hfov: Option<f64>,
) -> Truth {
    let world = World::new(objects).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let cams: Vec<PinholeCamera> = poses
        .into_iter()
        .map(|pose| PinholeCamera {
            intrinsics: Intrinsics::from_hfov(w, h, hfov.unwrap_or_else(|| rng.gen_range(55.0..70.0))),
            width: w,
            height: h,
            cam_to_world: pose,
        })
        .collect();
    let views: Vec<_> = cams.iter().map(|c| world.render(c)).collect();
    let own = cams.iter().zip(&views).map(|(c, v)| depth_to_pointmap(&v.depth, &c.intrinsics)).collect();
    let normals = views.iter().map(|v| v.normals.clone()).collect();
    Truth { world, cams, own, normals }
}

/// Writes the rendered photos as PNG files (the pipeline's input).
fn photos(t: &Truth, dir: &Path) {
    for (k, c) in t.cams.iter().enumerate() {
        t.world.render(c).rgb.save(dir.join(format!("view{k}.png"))).unwrap();
    }
}

/// Descriptor size: random Fourier features need more than Dens3R's 24 to be unique over a
/// room (the matcher takes any size).
const DIM: usize = 64;

/// Unit descriptors: random Fourier features of the world position (a known function of it,
/// so reciprocal nearest neighbours are true correspondences).
fn feature(p: DVec3, freqs: &[(DVec3, f64)]) -> [f32; DIM] {
    let mut out = [0f32; DIM];
    let norm = ((DIM / 2) as f64).sqrt();
    for (k, (f, ph)) in freqs.iter().enumerate() {
        let a = f.dot(p) + ph;
        out[2 * k] = (a.cos() / norm) as f32;
        out[2 * k + 1] = (a.sin() / norm) as f32;
    }
    out
}

struct Oracle<'a> {
    t: &'a Truth,
    freqs: Vec<(DVec3, f64)>,
    calls: Cell<usize>,
    /// Of those, the runs asked for descriptors (the others get none, as the network's).
    desc_calls: Cell<usize>,
}

impl<'a> Oracle<'a> {
    fn new(t: &'a Truth) -> Self {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(99);
        let freqs = (0..DIM / 2)
            .map(|_| {
                let d = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
                (d.normalize() * rng.gen_range(1.0f64..4.0).exp2(), rng.gen_range(0.0..std::f64::consts::TAU))
            })
            .collect();
        Self { t, freqs, calls: Cell::new(0), desc_calls: Cell::new(0) }
    }
}

impl PairPredictor for Oracle<'_> {
    fn id(&self) -> String {
        "oracle-v1".into()
    }

    fn predict(&self, _images: &[InputImage], i: usize, j: usize, want: Wanted) -> Result<[ViewOutput; 2], String> {
        self.calls.set(self.calls.get() + 1);
        self.desc_calls.set(self.desc_calls.get() + want.descriptors as usize);
        let t = self.t;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64((i * 100 + j) as u64);
        let sim = Sim3 {
            scale: rng.gen_range(0.3..3.0),
            rotation: axis_angle(DVec3::new(rng.gen(), rng.gen(), rng.gen()), rng.gen_range(0.0..3.0)),
            translation: DVec3::new(rng.gen(), rng.gen(), rng.gen()),
        };
        // Like a trained network's, descriptor confidence is high only where the other view of
        // the pair sees the same surface.
        let seen_by = |x: DVec3, o: usize| {
            let c = t.cams[o].world_to_cam().transform_point3(x);
            let (u, v) = t.cams[o].intrinsics.project(c);
            let (u, v) = (u.round(), v.round());
            c.z > 0.0 && u >= 0.0 && v >= 0.0 && (u as usize) < W && (v as usize) < H && {
                let z = t.own[o].get(u as usize, v as usize).z as f64;
                (z - c.z).abs() < 0.02 * c.z
            }
        };
        let view = |k: usize| {
            let other = if k == i { j } else { i };
            let to_i = t.cams[i].world_to_cam() * t.cams[k].cam_to_world;
            let to_world = t.cams[k].cam_to_world;
            let own = &t.own[k];
            let ok = |p: &Vec3| p.is_finite() && p.z > 0.0;
            let points =
                own.map(|p| if ok(p) { sim.apply(to_i.transform_point3(p.as_dvec3())).as_vec3() } else { Vec3::NAN });
            let conf = own.map(|p| if ok(p) { 5.0 } else { 1.0 });
            let desc_conf =
                own.map(|p| if ok(p) && seen_by(to_world.transform_point3(p.as_dvec3()), other) { 5.0 } else { 1.0 });
            let data = own
                .data()
                .iter()
                .flat_map(|p| {
                    if ok(p) {
                        feature(to_world.transform_point3(p.as_dvec3()), &self.freqs)
                    } else {
                        [0.0; DIM]
                    }
                })
                .collect();
            ViewOutput {
                points,
                conf,
                normals: Some(t.normals[k].clone()),
                desc: want.descriptors.then_some(DescriptorMap { width: W, height: H, dim: DIM, data }),
                desc_conf: want.descriptors.then_some(desc_conf),
            }
        };
        Ok([view(i), view(j)])
    }
}

/// A predictor with the oracle's id that must never run (everything comes from the cache).
struct Refuses;
impl PairPredictor for Refuses {
    fn id(&self) -> String {
        "oracle-v1".into()
    }
    fn predict(&self, _: &[InputImage], _: usize, _: usize, _: Wanted) -> Result<[ViewOutput; 2], String> {
        Err("the network was called".into())
    }
}

#[test]
fn oracle_photos_become_the_true_scene() {
    let n = 6;
    let t = truth(n);
    let dir = tempfile::tempdir().unwrap();
    let (photo_dir, out) = (dir.path().join("photos"), dir.path().join("out"));
    std::fs::create_dir_all(&photo_dir).unwrap();
    photos(&t, &photo_dir);
    let paths = list_images(std::slice::from_ref(&photo_dir)).unwrap();
    assert_eq!(paths.len(), n);
    let images = load_images(&paths, W as u32, false).unwrap();
    assert!(images.iter().all(|im| im.size() == (W, H)));

    let oracle = Oracle::new(&t);
    let cache = PairCache::new(Some(out.join("cache")));
    // Keypoint placement assumes each pair's first view in its camera frame (as the networks
    // give it); this oracle's random similarity frames test the alignment without it.
    let opts = ReconOptions { cameras: Cameras::Dense, keypoints: None, ..Default::default() };
    let mut stages = Vec::new();
    let rec = reconstruct(&images, &oracle, &cache, &opts, |s, d, _| stages.push((s, d))).unwrap();
    assert_eq!((rec.stats.pairs, oracle.calls.get(), rec.stats.cache_hits), (n * (n - 1), n * (n - 1), 0));
    // Descriptors are asked of one run per unordered pair: the one it is matched on.
    assert_eq!(oracle.desc_calls.get(), n * (n - 1) / 2);
    assert!(stages.iter().any(|s| s.0 == dens3r_recon::Stage::Align));

    // Cameras, up to one similarity (the gauge).
    let tc: Vec<DVec3> = t.cams.iter().map(|c| c.center()).collect();
    let est: Vec<PinholeCamera> = rec.alignment.views.iter().map(|v| v.camera).collect();
    let ec: Vec<DVec3> = est.iter().map(|c| c.center()).collect();
    let gauge = umeyama(&ec, &tc, None, true).unwrap();
    let diag = (ROOM_HI - ROOM_LO).length() as f64;
    let (mut rot, mut pos, mut foc) = (0f64, 0f64, 0f64);
    for k in 0..n {
        let re = gauge.rotation * DMat3::from_mat4(est[k].cam_to_world);
        rot = rot.max(rotation_angle_deg(&(DMat3::from_mat4(t.cams[k].cam_to_world).transpose() * re)));
        pos = pos.max((gauge.apply(ec[k]) - tc[k]).length() / diag);
        foc = foc.max((est[k].intrinsics.fx / t.cams[k].intrinsics.fx - 1.0).abs());
    }
    eprintln!("cameras: rotation {rot:.3} deg, centre {:.3}% of the room, focal {:.3}%", pos * 100.0, foc * 100.0);
    assert!(rot < 1.0 && pos < 0.01 && foc < 0.01, "{rot} {pos} {foc}");

    // Aligned depth (times the gauge scale) is the true depth.
    let mut rel = Vec::new();
    for (k, v) in rec.alignment.views.iter().enumerate() {
        for (d, p) in v.depth.data().iter().zip(t.own[k].data()) {
            if *d > 0.0 && p.is_finite() && p.z > 0.0 {
                rel.push((*d as f64 * gauge.scale / p.z as f64 - 1.0).abs());
            }
        }
    }
    rel.sort_by(f64::total_cmp);
    let med = rel[rel.len() / 2];
    eprintln!("depth: median relative error {:.3}% over {} pixels", med * 100.0, rel.len());
    assert!(med < 0.01 && rel.len() > n * W * H / 2);

    // Normals are each view's own (averaged over its pairs: the same truth every time).
    for (k, nm) in rec.normals.iter().enumerate() {
        let nm = nm.as_ref().unwrap();
        let worst = nm
            .data()
            .iter()
            .zip(t.normals[k].data())
            .filter(|(_, g)| g.length() > 0.5)
            .map(|(a, g)| a.dot(*g))
            .fold(1.0f32, f32::min);
        assert!(worst > 0.9999, "view {k}: normal cos {worst}");
    }

    // Matches join pixels that see the same world point (one pair per unordered pair).
    assert_eq!(rec.matches.len(), n * (n - 1) / 2);
    let world_at = |k: usize, (x, y): (usize, usize)| {
        let p = t.own[k].get(x, y);
        t.cams[k].cam_to_world.transform_point3(p.as_dvec3())
    };
    let (mut good, mut all) = (0, 0);
    for (a, b, ms) in &rec.matches {
        for m in ms {
            all += 1;
            let dd = (world_at(*a, m.a) - world_at(*b, m.b)).length();
            good += (dd < 0.05) as usize;
        }
    }
    eprintln!("matches: {good} of {all} within 5 cm of the true correspondence");
    assert!(all > 500 && good as f64 > 0.95 * all as f64);

    // Track points sit on the true surface where their cameras see it, and project onto their
    // keypoints in the true cameras. They are triangulated from keypoints at whole pixels (a
    // pixel is 1.4 cm at 2 m here), so they are as far from the truth as a pixel or two.
    let (mut off, mut reproj) = (Vec::new(), Vec::new());
    for p in &rec.points {
        let g = gauge.apply(p.xyz);
        let d = p.observations.iter().map(|&(k, (x, y))| (g - world_at(k, (x as usize, y as usize))).length());
        off.push(d.fold(f64::INFINITY, f64::min));
        for &(k, (x, y)) in &p.observations {
            let c = &t.cams[k];
            let (u, v) = c.intrinsics.project(c.world_to_cam().transform_point3(g));
            reproj.push((u - x).hypot(v - y));
        }
    }
    off.sort_by(f64::total_cmp);
    reproj.sort_by(f64::total_cmp);
    let (off_med, reproj_med) = (off[off.len() / 2], reproj[reproj.len() / 2]);
    eprintln!(
        "tracks: {} points ({} triangulated), median {off_med:.4} m from the truth, {reproj_med:.2} px",
        off.len(),
        rec.stats.triangulated_points
    );
    assert!(off.len() > 200 && off_med < 0.03 && reproj_med < 1.0, "{off_med} m, {reproj_med} px");
    assert!(rec.stats.triangulated_points > off.len() / 2);

    // Outputs: scene folder, exports, match pictures, mesh near the true surface.
    let oo = OutputOptions::default();
    let summary = write_outputs(&rec, &paths, &out, &oo, |_, _| {}).unwrap();
    let scene = dens3r_scene::Scene::open(&summary.scene).unwrap();
    assert_eq!(scene.frames().len(), n);
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        assert!(summary.colmap.join(f).is_file(), "{f}");
    }
    let pts3d = std::fs::read_to_string(summary.colmap.join("points3D.txt")).unwrap();
    assert_eq!(pts3d.lines().filter(|l| !l.starts_with('#')).count(), rec.points.len());
    assert!(summary.scene.join("transforms.json").is_file());
    let matched = rec.matches.iter().filter(|m| !m.2.is_empty()).count();
    assert!(matched >= n - 1);
    assert_eq!(std::fs::read_dir(out.join("matches")).unwrap().count(), matched);
    let mut mesh = dens3r_mesh::read_mesh(summary.mesh.as_ref().unwrap()).unwrap();
    for p in mesh.positions.iter_mut() {
        *p = gauge.apply(p.as_dvec3()).as_vec3();
    }
    let m =
        mesh_metrics(&mesh, &t.world.gt_mesh(), &MeshMetricsOptions { samples: 20_000, ..Default::default() }).unwrap();
    let voxel = summary.voxel as f64 * gauge.scale;
    eprintln!("mesh: {} triangles, voxel {voxel:.4} m, accuracy {:.4} m", summary.triangles, m.accuracy);
    assert!(m.accuracy < 0.5 * voxel, "mesh accuracy {} at voxel {voxel}", m.accuracy);

    // A second run reads every pair from the cache and gives the same cameras; a damaged
    // entry is recomputed (here: by a predictor that refuses, so the run names the pair).
    let again = reconstruct(&images, &Refuses, &cache, &opts, |_, _, _| {}).unwrap();
    assert_eq!(again.stats.cache_hits, n * (n - 1));
    for (a, b) in again.alignment.views.iter().zip(&rec.alignment.views) {
        assert_eq!(a.camera.cam_to_world, b.camera.cam_to_world);
    }
    let entry = std::fs::read_dir(out.join("cache"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|x| x == "d3c"))
        .unwrap();
    let mut bytes = std::fs::read(&entry).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 1;
    std::fs::write(&entry, bytes).unwrap();
    let e = reconstruct(&images, &Refuses, &cache, &opts, |_, _, _| {}).unwrap_err().to_string();
    assert!(e.contains("pair (view") && e.contains("the network was called"), "{e}");
}

#[path = "../../../tests/support/fixtures.rs"]
mod fixtures;

/// With the decoder shared by both views (fixture A), the pair `(1, 0)` asked right after
/// `(0, 1)` reuses that decoder pass with the views swapped (and the normal head's outputs),
/// and gives exactly what a
/// predictor that never saw `(0, 1)` gives; an unrelated pair in between is decoded anew.
#[test]
fn the_reverse_pair_reuses_the_decoder_pass_exactly() {
    use dens3r_recon::NetworkPredictor;
    let a = fixtures::parity(fixtures::A);
    let device = dens3r_backbone::Device::flex();
    let (model, _) =
        dens3r_backbone::verify::load_model(&a.join("weights.safetensors"), Some(&a.join("config.json")), &device)
            .unwrap();
    assert!(model.config.shared_decoder);
    let samples = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/room/images");
    let paths: Vec<_> = ["0000.png", "0001.png", "0002.png"].iter().map(|n| samples.join(n)).collect();
    let images = load_images(&paths, 64, true).unwrap();
    let all = Wanted::ALL;
    let both = NetworkPredictor::new(&model, "a".into());
    let _ = both.predict(&images, 0, 1, all).unwrap();
    let reused = both.predict(&images, 1, 0, all).unwrap();
    assert_eq!(both.decoder_passes(), 1);
    let alone = NetworkPredictor::new(&model, "a".into());
    let direct = alone.predict(&images, 1, 0, all).unwrap();
    for v in 0..2 {
        assert_eq!(reused[v].points.data(), direct[v].points.data(), "view {v} points");
        assert_eq!(reused[v].conf.data(), direct[v].conf.data(), "view {v} conf");
        let (Some(x), Some(y)) = (&reused[v].desc, &direct[v].desc) else { panic!("descriptors") };
        assert_eq!(x.data, y.data);
        let (Some(x), Some(y)) = (&reused[v].normals, &direct[v].normals) else { panic!("normals") };
        assert_eq!(x.data(), y.data(), "view {v} normals");
    }
    // (0, 2) then (1, 0): nothing pending fits, both are decoded.
    let mixed = NetworkPredictor::new(&model, "a".into());
    let _ = mixed.predict(&images, 0, 2, all).unwrap();
    let again = mixed.predict(&images, 1, 0, all).unwrap();
    assert_eq!(mixed.decoder_passes(), 2);
    assert_eq!(again[0].points.data(), direct[0].points.data());
    // Without descriptors (the reverse run reconstruct makes), the rest is the same.
    let lean = NetworkPredictor::new(&model, "a".into());
    let _ = lean.predict(&images, 0, 1, all).unwrap();
    let plain = lean.predict(&images, 1, 0, Wanted { descriptors: false }).unwrap();
    for v in 0..2 {
        assert!(plain[v].desc.is_none() && plain[v].desc_conf.is_none(), "view {v} descriptors");
        assert_eq!(plain[v].points.data(), direct[v].points.data(), "view {v} points");
        assert_eq!(plain[v].conf.data(), direct[v].conf.data(), "view {v} conf");
        assert_eq!(plain[v].normals.as_ref().unwrap().data(), direct[v].normals.as_ref().unwrap().data());
    }
}

/// The oracle, except that each pair's second view comes back in its own camera frame instead
/// of the first camera's: a network that has learned single-view geometry but not the pair's
/// relative pose (as a small model trained briefly has).
struct NoCrossView<'a>(Oracle<'a>);

impl PairPredictor for NoCrossView<'_> {
    fn id(&self) -> String {
        "oracle-no-cross-view".into()
    }

    fn predict(&self, images: &[InputImage], i: usize, j: usize, want: Wanted) -> Result<[ViewOutput; 2], String> {
        let [a, mut b] = self.0.predict(images, i, j, want)?;
        let t = self.0.t;
        b.points = t.own[j].map(|p| if p.is_finite() && p.z > 0.0 { *p } else { Vec3::NAN });
        Ok([a, b])
    }
}

/// Median and largest error (degrees) of the aligned cameras' relative rotations over all
/// view pairs (no gauge needed).
fn rotation_errors(t: &Truth, a: &dens3r_align::Alignment) -> (f64, f64) {
    let n = t.cams.len();
    let truth: Vec<DMat3> = t.cams.iter().map(|c| DMat3::from_mat4(c.cam_to_world)).collect();
    let est: Vec<DMat3> = a.views.iter().map(|v| DMat3::from_mat4(v.camera.cam_to_world)).collect();
    let mut errs = Vec::new();
    for p in 0..n {
        for q in p + 1..n {
            let rel = |c: &[DMat3]| c[p].transpose() * c[q];
            errs.push(rotation_angle_deg(&(rel(&truth).transpose() * rel(&est))));
        }
    }
    errs.sort_by(f64::total_cmp);
    (errs[errs.len() / 2], errs[errs.len() - 1])
}

/// Pairs placed by their matches recover the cameras that the network's missing cross-view
/// geometry loses: with the placement the relative rotations are those of the renderer's
/// cameras; without it (the network's cross-view pointmaps only) they are far off.
#[test]
fn matches_place_the_pairs_a_network_cannot() {
    let n = 5;
    let t = truth(n);
    let dir = tempfile::tempdir().unwrap();
    photos(&t, dir.path());
    let paths = list_images(&[dir.path().to_path_buf()]).unwrap();
    let images = load_images(&paths, W as u32, false).unwrap();
    let blind = NoCrossView(Oracle::new(&t));
    let cache = PairCache::new(None);
    // The walk's neighbours overlap (a capture's sequential graph).
    let graph = dens3r_align::PairGraph::SlidingWindow { k: 1, cyclic: false };
    // Reciprocal matches are few at 160x112 (20 between the walk's widest neighbours).
    let match_pose = Some(dens3r_align::match_pose::MatchPoseOptions { min_inliers: 12, ..Default::default() });
    let opts =
        ReconOptions { cameras: Cameras::Dense, graph: Some(graph), match_pose, keypoints: None, ..Default::default() };
    let with = reconstruct(&images, &blind, &cache, &opts, |_, _, _| {}).unwrap();
    let (med, worst) = rotation_errors(&t, &with.alignment);
    eprintln!(
        "placed by matches: {} of {} pairs; relative rotation error median {med:.3} deg, worst {worst:.3} deg",
        with.stats.posed_by_matches, with.stats.pairs
    );
    assert_eq!(with.stats.posed_by_matches, with.stats.pairs);
    assert!(med < 1.0 && worst < 3.0, "{med} {worst}");
    let opts = ReconOptions { match_pose: None, ..opts };
    let without = reconstruct(&images, &blind, &cache, &opts, |_, _, _| {}).unwrap();
    assert_eq!(without.stats.posed_by_matches, 0);
    let (med0, _) = rotation_errors(&t, &without.alignment);
    eprintln!("network cross-view pointmaps only: median relative rotation error {med0:.3} deg");
    assert!(med0 > 5.0, "{med0}");
}

/// A network that gets each view's depth right but neither its rays (x and y warped by up to
/// 0.05 z, about 13 px at the keypoint test's focal; a briefly trained model's are further
/// off, and its focal with them) nor the pair's relative pose (the second view comes
/// back in its own camera frame), and gives no descriptors.
struct DepthOnly<'a>(&'a Truth);

impl PairPredictor for DepthOnly<'_> {
    fn id(&self) -> String {
        "oracle-depth-only".into()
    }

    fn predict(&self, _: &[InputImage], i: usize, j: usize, _: Wanted) -> Result<[ViewOutput; 2], String> {
        let view = |k: usize| {
            let own = &self.0.own[k];
            let ok = |p: &Vec3| p.is_finite() && p.z > 0.0;
            let points = own.map(|p| {
                if ok(p) {
                    let (u, v) = (p.x / p.z, p.y / p.z);
                    Vec3::new(p.x + 0.05 * p.z * (5.0 * v).sin(), p.y + 0.05 * p.z * (5.0 * u).sin(), p.z)
                } else {
                    Vec3::NAN
                }
            });
            ViewOutput {
                points,
                conf: own.map(|p| if ok(p) { 5.0 } else { 1.0 }),
                normals: Some(self.0.normals[k].clone()),
                desc: None,
                desc_conf: None,
            }
        };
        Ok([view(i), view(j)])
    }
}

/// The room with every surface in fine high-contrast noise (non-repeating: a tiled photo's
/// mirrored copies give SIFT ambiguous matches), photographed from camera-to-world `poses`
/// (320x224, one camera of 62 degrees), loaded as `reconstruct` reads photos.
fn noise_room_photos(poses: Vec<glam::DMat4>) -> (Truth, Vec<InputImage>) {
    let objects = room(3)
        .into_iter()
        .map(|mut o| {
            o.material.texture = dens3r_render::Texture::Noise { scale: 0.05 };
            o
        })
        .collect();
    let t = truth_of(objects, poses, 2 * W, 2 * H, Some(62.0));
    let dir = tempfile::tempdir().unwrap();
    photos(&t, dir.path());
    let paths = list_images(&[dir.path().to_path_buf()]).unwrap();
    let images = load_images(&paths, 2 * W as u32, false).unwrap();
    (t, images)
}

/// Keypoint matches place the pairs of a network that knows only depth: the relative
/// rotations of the renderer's cameras come back (within the error its warped rays leave in
/// the focal, 4% here; closer with the focal known, which is then kept); without keypoints
/// they do not.
#[test]
fn keypoints_place_the_pairs_of_a_depth_only_network() {
    // Five views across the room, each looking at the same point of the far wall (neighbours
    // about 9 degrees apart), by one camera (one focal), as the keypoint path assumes of
    // same-size photos.
    let n = 5;
    let poses = (0..n)
        .map(|k| {
            let eye = DVec3::new(-0.8 + 0.4 * k as f64, -1.2, 1.3);
            dens3r_geom::camera::look_at(eye, DVec3::new(0.0, 2.0, 1.0), DVec3::Z).unwrap()
        })
        .collect();
    let (t, images) = noise_room_photos(poses);
    let net = DepthOnly(&t);
    let cache = PairCache::new(None);
    let graph = dens3r_align::PairGraph::SlidingWindow { k: 1, cyclic: false };
    let opts = ReconOptions { cameras: Cameras::Dense, graph: Some(graph), ..Default::default() };
    let with = reconstruct(&images, &net, &cache, &opts, |_, _, _| {}).unwrap();
    let (med, worst) = rotation_errors(&t, &with.alignment);
    eprintln!(
        "placed by keypoints: {} of {} pairs; relative rotation error median {med:.3} deg, worst {worst:.3} deg",
        with.stats.posed_by_keypoints, with.stats.pairs
    );
    assert_eq!(with.stats.posed_by_keypoints, with.stats.pairs);
    assert!(med < 1.5 && worst < 3.0, "{med} {worst}");
    // The camera's true focal, known (as a photo's EXIF or `--focal` gives it): kept as it is,
    // and the rotations need no focal estimate.
    let f = t.cams[0].intrinsics.fx;
    let mut known = images.clone();
    known.iter_mut().for_each(|im| im.set_focal(Some(f)));
    let kf = reconstruct(&known, &net, &cache, &opts, |_, _, _| {}).unwrap();
    let (medk, worstk) = rotation_errors(&t, &kf.alignment);
    eprintln!("with the focal known: median relative rotation error {medk:.3} deg, worst {worstk:.3} deg");
    assert_eq!((kf.stats.known_focals, kf.stats.posed_by_keypoints), (n, kf.stats.pairs));
    assert!(kf.alignment.views.iter().all(|v| (v.camera.intrinsics.fx / f - 1.0).abs() < 1e-9));
    assert!(medk < 0.2 && worstk < 0.5 && medk < med, "{medk} {worstk} ({med} estimated)");
    let opts = ReconOptions { keypoints: None, ..opts };
    let without = reconstruct(&images, &net, &cache, &opts, |_, _, _| {}).unwrap();
    let (med0, _) = rotation_errors(&t, &without.alignment);
    eprintln!("without keypoints: median relative rotation error {med0:.3} deg");
    assert!(med0 > 5.0, "{med0}");
}

/// Structure-from-motion's cameras through `reconstruct` (the default): the depth-only
/// network's photos of the noise room, eight views walking along the room, the focal unknown
/// (started from the network's warped rays): every view registered, relative rotations and
/// baseline directions near the truth, the focal within 1%, and each view's depth the
/// network's scaled onto the SfM points (the truth's depth up to one scale for all views).
#[test]
fn structure_from_motion_places_the_cameras_by_default() {
    let n = 8;
    let poses = (0..n)
        .map(|k| {
            let eye = DVec3::new(-1.0 + 0.3 * k as f64, -1.3 + 0.05 * k as f64, 1.2 + 0.04 * (k % 3) as f64);
            let at = DVec3::new(0.6 - 0.15 * k as f64, 2.0, 0.9);
            dens3r_geom::camera::look_at(eye, at, DVec3::Z).unwrap()
        })
        .collect();
    let (t, images) = noise_room_photos(poses);
    let net = DepthOnly(&t);
    let rec = reconstruct(&images, &net, &PairCache::new(None), &ReconOptions::default(), |_, _, _| {}).unwrap();
    let sfm = rec.stats.sfm.as_ref().expect("cameras by structure from motion");
    assert_eq!((rec.stats.registered, rec.alignment.views.len()), (n, n), "{:?}", rec.stats.warnings);
    let (med, worst) = rotation_errors(&t, &rec.alignment);
    let est: Vec<_> = rec.alignment.views.iter().map(|v| v.camera).collect();
    let m = dens3r_geom::metrics::cameras::camera_metrics(&est, &t.cams);
    let trans = dens3r_geom::metrics::cameras::median(&m.translation_deg);
    let f = (est[0].intrinsics.fx / t.cams[0].intrinsics.fx - 1.0).abs();
    eprintln!(
        "SfM: rotation median {med:.3} worst {worst:.3} deg, baselines {trans:.3} deg, focal {f:.4}, RMS {:.2} px",
        sfm.rms_px.1
    );
    assert!(med < 0.2 && worst < 0.5 && trans < 1.0 && f < 0.01, "{med} {worst} {trans} {f}");
    assert!(sfm.rms_px.1 < 1.0 && rec.points.len() > 200, "{} px, {} points", sfm.rms_px.1, rec.points.len());
    // Depth: one scale for every view against the truth (the SfM's gauge), within 2%.
    let ratios: Vec<f64> = (0..n)
        .map(|k| {
            let (d, own) = (&rec.alignment.views[k].depth, &t.own[k]);
            let mut r: Vec<f64> = d
                .data()
                .iter()
                .zip(own.data())
                .filter(|(z, p)| **z > 0.0 && p.is_finite() && p.z > 0.0)
                .map(|(z, p)| *z as f64 / p.z as f64)
                .collect();
            r.sort_by(f64::total_cmp);
            r[r.len() / 2]
        })
        .collect();
    let (lo, hi) = ratios.iter().fold((f64::INFINITY, 0.0f64), |(a, b), &r| (a.min(r), b.max(r)));
    assert!(hi / lo < 1.02, "depth scales {ratios:?}");
}

/// A camera panning across the room, 28 degrees a step with a 62 degree field of view:
/// neighbours share about half their view and keypoints place them; views two steps apart
/// share little and stay unplaced. Those pairs' cross-view pointmaps (the depth-only network's
/// guess: no motion) are left out where placed pairs already join their images, so they no
/// longer pull the placed cameras; kept (`drop_unplaced: false`), they do. (Where two views
/// share little more than one wall, the essential matrix alone leaves a pair up to 5.5
/// degrees off here; the wall's homography and the depth pick the pose.)
#[test]
fn unplaced_pairs_do_not_pull_placed_cameras() {
    let n = 5;
    let poses = (0..n)
        .map(|k| {
            let eye = DVec3::new(-0.8 + 0.4 * k as f64, -1.6, 1.1);
            let a = (-56.0 + 28.0 * k as f64).to_radians();
            let target = eye + DVec3::new(a.sin(), a.cos(), -0.3);
            dens3r_geom::camera::look_at(eye, target, DVec3::Z).unwrap()
        })
        .collect();
    let (t, mut images) = noise_room_photos(poses);
    let f = t.cams[0].intrinsics.fx;
    images.iter_mut().for_each(|im| im.set_focal(Some(f)));
    let net = DepthOnly(&t);
    let cache = PairCache::new(None);
    let graph = dens3r_align::PairGraph::SlidingWindow { k: 2, cyclic: false };
    let opts = ReconOptions { cameras: Cameras::Dense, graph: Some(graph), ..Default::default() };
    let with = reconstruct(&images, &net, &cache, &opts, |_, _, _| {}).unwrap();
    let (med, worst) = rotation_errors(&t, &with.alignment);
    let s = &with.stats;
    eprintln!(
        "placed by keypoints {} of {} pairs, {} left out; relative rotation error median {med:.3} deg, worst {worst:.3} deg",
        s.posed_by_keypoints, s.pairs, s.pairs_left_out
    );
    // The four neighbour pairs (both orders) placed, the three two-step pairs not, and left out.
    assert_eq!((s.posed_by_keypoints, s.pairs_left_out), (8, 6));
    assert!(med < 1.5 && worst < 4.0, "{med} {worst}");
    // Kept, with the rotations free in the alignment, they pull; with the rotations the
    // placed pairs average to held fixed (the default), they cannot.
    let free = KeypointOptions { fix_rotations: false, ..KeypointOptions::default() };
    let kept = ReconOptions { drop_unplaced: false, keypoints: Some(free), ..opts.clone() };
    let all = reconstruct(&images, &net, &cache, &kept, |_, _, _| {}).unwrap();
    let (med_all, worst_all) = rotation_errors(&t, &all.alignment);
    eprintln!("every pair aligned, rotations free: median {med_all:.3} deg, worst {worst_all:.3} deg");
    assert_eq!((all.stats.pairs_left_out, all.stats.fixed_rotations), (0, 0));
    assert!(med_all > 20.0 && med_all > 5.0 * med, "{med_all} vs {med}");
    let kept = ReconOptions { drop_unplaced: false, ..opts };
    let fixed = reconstruct(&images, &net, &cache, &kept, |_, _, _| {}).unwrap();
    let (med_fixed, worst_fixed) = rotation_errors(&t, &fixed.alignment);
    eprintln!("every pair aligned, rotations fixed: median {med_fixed:.3} deg, worst {worst_fixed:.3} deg");
    assert_eq!(fixed.stats.fixed_rotations, n);
    assert!(med_fixed < 1.5 && worst_fixed < 4.0, "{med_fixed} {worst_fixed}");
}

/// SIFT on the bundled orbit's renders as `reconstruct` prepares them (512 px): flat
/// background, where the SIFT crate's sub-pixel step overflows (a panic in checked builds, the
/// Python extension's among them, before the workspace's profile override); keypoints come
/// back without a panic.
#[test]
fn keypoints_of_flat_renders_do_not_panic() {
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/orbit/images");
    let paths: Vec<_> = (0..3).map(|k| dir.join(format!("000{k}.png"))).collect();
    let images = load_images(&paths, 512, false).unwrap();
    for im in &images {
        assert!(!dens3r_align::keypoints::detect(&im.rgb(), 4000).is_empty(), "{}", im.name);
    }
}

/// Issue 77, 7: when no group of photos held half of them, `reconstruct` fell back to the
/// dense path over all of them, and unrelated scenes became one. Three rooms papered in
/// different noise (3, 2 and 2 photos; no SIFT match between rooms): the largest room is
/// reconstructed by structure from motion, the others are named and left out, never merged.
#[test]
fn separate_scenes_are_never_merged() {
    let room_of = |scale: f32, n: usize| {
        let objects = room(3)
            .into_iter()
            .map(|mut o| {
                o.material.texture = dens3r_render::Texture::Noise { scale };
                o
            })
            .collect();
        let poses = (0..n)
            .map(|k| {
                let eye = DVec3::new(-0.5 + 0.25 * k as f64, -1.2, 1.3);
                dens3r_geom::camera::look_at(eye, DVec3::new(0.0, 2.0, 1.0), DVec3::Z).unwrap()
            })
            .collect();
        truth_of(objects, poses, 2 * W, 2 * H, Some(62.0))
    };
    let rooms = [room_of(0.05, 3), room_of(0.031, 2), room_of(0.019, 2)];
    let dir = tempfile::tempdir().unwrap();
    let mut paths = Vec::new();
    for (r, t) in rooms.iter().enumerate() {
        let d = dir.path().join(format!("room{r}"));
        std::fs::create_dir_all(&d).unwrap();
        photos(t, &d);
        paths.extend(list_images(&[d]).unwrap());
    }
    let images = load_images(&paths, 2 * W as u32, false).unwrap();
    let all = Truth {
        world: World::new(room(3)).unwrap(),
        cams: rooms.iter().flat_map(|t| t.cams.clone()).collect(),
        own: rooms.iter().flat_map(|t| t.own.clone()).collect(),
        normals: rooms.iter().flat_map(|t| t.normals.clone()).collect(),
    };
    let rec =
        reconstruct(&images, &DepthOnly(&all), &PairCache::new(None), &ReconOptions::default(), |_, _, _| {}).unwrap();
    let w = rec.stats.warnings.join(" | ");
    assert!(rec.stats.sfm.is_some(), "the dense path merged the rooms: {w}");
    assert_eq!(rec.inputs, vec![0, 1, 2], "{w}");
    assert!(w.contains("never merged"), "{w}");
}
