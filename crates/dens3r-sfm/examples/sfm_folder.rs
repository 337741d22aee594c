//! Structure-from-motion on a rendered scene folder's images, scored against its cameras:
//! `cargo run --example sfm_folder -- SCENE [MAX_KEYPOINTS]`.

use dens3r_align::keypoints::detect_with_gain;
use dens3r_geom::metrics::cameras::{camera_metrics, median};
use dens3r_scene::Scene;
use dens3r_sfm::{run, SfmInput, SfmOptions};
use rayon::prelude::*;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = Scene::open(std::path::Path::new(&args[1])).expect("a scene folder");
    let max: usize = args.get(2).map_or(4000, |m| m.parse().expect("a number"));
    let gain: f32 = args.get(3).map_or(3.0, |m| m.parse().expect("a number"));
    let frames = scene.frames();
    let t = Instant::now();
    let kps: Vec<_> = frames
        .par_iter()
        .map(|f| detect_with_gain(&image::open(scene.root().join(&f.image)).expect("an image").to_rgb8(), max, gain))
        .collect();
    println!("SIFT {:.1}s, {} keypoints in the first", t.elapsed().as_secs_f64(), kps[0].len());
    let sizes: Vec<(usize, usize)> = frames.iter().map(|f| (f.camera().width, f.camera().height)).collect();
    let n = frames.len();
    let pairs = dens3r_align::make_pairs(n, dens3r_align::PairGraph::Complete, false);
    let guess = vec![1.2 * sizes[0].0 as f64; n];
    let input = SfmInput {
        keypoints: &kps,
        sizes: &sizes,
        known_focals: &vec![None; n],
        prior_focals: &vec![None; n],
        focal_guess: &guess,
        pairs: &pairs,
    };
    if std::env::var("EDGES").is_ok() {
        debug_edges(&scene, &kps, &pairs, frames[0].camera().intrinsics.fx);
    }
    let t = Instant::now();
    let mut opts = SfmOptions::default();
    let env = |k: &str| std::env::var(k).ok().map(|v| v.parse::<f64>().expect("a number"));
    if let Some(v) = env("HUBER") {
        opts.ba.huber_px = v;
    }
    if let Some(v) = env("MINTRI") {
        opts.min_triangulation_deg = v;
    }
    if let Some(v) = env("REPROJ") {
        opts.max_reprojection_px = v;
    }
    if let Some(v) = env("RATIO") {
        opts.view_graph.ratio = v as f32;
    }
    let sfm = run(&input, &opts);
    println!("SfM {:.1}s: {:?}", t.elapsed().as_secs_f64(), sfm.stats);
    println!("groups {:?}", sfm.groups.iter().map(|g| g.len()).collect::<Vec<_>>());
    let reg: Vec<usize> = (0..n).filter(|&v| sfm.cameras[v].is_some()).collect();
    let est: Vec<_> = reg.iter().map(|&v| sfm.cameras[v].unwrap()).collect();
    let truth: Vec<_> = reg.iter().map(|&v| frames[v].camera()).collect();
    let m = camera_metrics(&est, &truth);
    println!(
        "registered {}/{n}; rotation median {:.3} max {:.3} deg; translation median {:.3} deg; focal {:.1} vs {:.1}",
        reg.len(),
        median(&m.rotation_deg),
        m.rotation_deg.iter().copied().fold(0.0, f64::max),
        median(&m.translation_deg),
        est.first().map_or(0.0, |c| c.intrinsics.fx),
        truth.first().map_or(0.0, |c| c.intrinsics.fx)
    );
}

#[allow(dead_code)]
fn debug_edges(scene: &Scene, kps: &[dens3r_align::keypoints::Keypoints], pairs: &[(usize, usize)], f: f64) {
    use dens3r_sfm::view_graph::{match_pairs, verify, ViewGraphOptions};
    let frames = scene.frames();
    let opts = ViewGraphOptions::default();
    let m = match_pairs(kps, pairs, &opts);
    let n = frames.len();
    let pps: Vec<glam::DVec2> =
        frames.iter().map(|fr| glam::DVec2::new(fr.width as f64 / 2.0, fr.height as f64 / 2.0)).collect();
    let edges = verify(kps, &m, &vec![f; n], &pps, &opts);
    for e in &edges {
        let (ci, cj) = (frames[e.i].camera(), frames[e.j].camera());
        let ri = glam::DMat3::from_mat4(ci.cam_to_world);
        let rj = glam::DMat3::from_mat4(cj.cam_to_world);
        // x_j = R x_i: R = Rj^T Ri
        let truth = rj.transpose() * ri;
        let err = dens3r_geom::transform::rotation_angle_deg(&(truth.transpose() * e.rotation));
        let matches = m.iter().find(|p| p.i == e.i && p.j == e.j).map_or(0, |p| p.matches.len());
        println!("edge {}-{}: {} inliers of {}, rotation error {:.2} deg", e.i, e.j, e.inliers.len(), matches, err);
    }
}
