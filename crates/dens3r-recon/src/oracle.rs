//! A predictor that reads the answer: ground-truth depth and normals of a rendered scene folder
//! (`dens3r render`), with the errors a network makes, for benchmarks that measure everything
//! but the network (`dens3r bench scale`: hundreds of views without hours of inference). Each
//! photo's frame is found by its file stem; nothing is held between calls.
//!
//! The errors, per view and seeded by its name: an unknown scale (0.5-2x, as a network's
//! depth of a single view), a smooth multiplicative warp of +-3% across the image, 1% noise per
//! pixel, normals turned by 3 degrees. Confidence is 5 where the truth has depth, 1 elsewhere.

use crate::input::InputImage;
use crate::predictor::{PairPredictor, ViewOutput, Wanted};
use dens3r_geom::{PinholeCamera, Raster, Vec3};
use dens3r_scene::Scene;
use glam::{DMat3, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

/// Ground truth with a network's errors (see the module's documentation).
pub struct SceneOracle<'a> {
    dir: PathBuf,
    scene: Scene,
    /// Gives [`PairPredictor::embed`] (the oracle has no image descriptors of its own).
    embedder: Option<&'a dyn PairPredictor>,
}

impl<'a> SceneOracle<'a> {
    /// The oracle of the scene folder `dir`; `embedder` answers retrieval's descriptors.
    pub fn new(dir: &Path, embedder: Option<&'a dyn PairPredictor>) -> Result<Self, dens3r_scene::SceneError> {
        Ok(Self { dir: dir.to_path_buf(), scene: Scene::open(dir)?, embedder })
    }

    fn frame(&self, im: &InputImage) -> Result<&dens3r_scene::Frame, String> {
        let stem = im.path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        self.scene
            .frames()
            .iter()
            .find(|f| f.name == stem || Path::new(&f.image).file_stem().is_some_and(|s| s.to_string_lossy() == stem))
            .ok_or_else(|| format!("{}: no frame of that name in the oracle's scene {}", im.name, self.dir.display()))
    }

    /// Image `k`'s own-frame points with the module's errors, its camera and its normals.
    fn view(&self, images: &[InputImage], k: usize) -> Result<(Raster<Vec3>, PinholeCamera, Raster<Vec3>), String> {
        let im = &images[k];
        let f = self.frame(im)?;
        let (w, h) = im.size();
        if (f.width, f.height) != (w, h) {
            return Err(format!(
                "{}: the oracle's frame is {}x{}, the network input {w}x{h}: render at the network size",
                im.name, f.width, f.height
            ));
        }
        let depth = self.scene.depth(f).map_err(|e| e.to_string())?.ok_or("the oracle's frame has no depth")?;
        let normals = self.scene.normals(f).map_err(|e| e.to_string())?;
        let cam = f.camera();
        let mut rng = ChaCha8Rng::seed_from_u64(dens3r_io::hash::fnv1a(f.name.as_bytes(), 0x0ac1e));
        let scale = (rng.gen::<f64>() * 2.0 - 1.0).exp2();
        let waves: Vec<(f64, f64, f64)> = (0..3)
            .map(|_| {
                (rng.gen::<f64>() * 2.0 - 1.0, rng.gen::<f64>() * 2.0 - 1.0, rng.gen::<f64>() * std::f64::consts::TAU)
            })
            .collect();
        let turn = DMat3::from_axis_angle(
            DVec3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng)).normalize_or(DVec3::X),
            3f64.to_radians(),
        );
        let mut points = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let z = *depth.get(x, y) as f64;
                if !(z.is_finite() && z > 0.0) {
                    points.push(Vec3::NAN);
                    continue;
                }
                let (u, v) = (x as f64 / w as f64, y as f64 / h as f64);
                let warp: f64 = waves.iter().map(|&(a, b, p)| (3.0 * (a * u + b * v) + p).sin()).sum::<f64>() / 3.0;
                let zn = z * scale * (1.0 + 0.03 * warp) * (1.0 + 0.01 * normal(&mut rng));
                points.push((cam.intrinsics.unproject(x as f64, y as f64) * zn).as_vec3());
            }
        }
        let points = Raster::from_vec(w, h, points).expect("w x h points");
        let normals = match normals {
            Some(n) => n.map(|v| if v.is_finite() { (turn * v.as_dvec3()).as_vec3() } else { Vec3::Z * -1.0 }),
            None => dens3r_geom::normals::normals_from_pointmap(&points),
        };
        Ok((points, cam, normals))
    }
}

impl PairPredictor for SceneOracle<'_> {
    fn id(&self) -> String {
        format!("scene-oracle-v1 {}", self.dir.display())
    }

    /// Both views in camera `i`'s frame by the true poses, each with its own errors.
    fn predict(&self, images: &[InputImage], i: usize, j: usize, _want: Wanted) -> Result<[ViewOutput; 2], String> {
        let (pi, ci, ni) = self.view(images, i)?;
        let (pj, cj, nj) = self.view(images, j)?;
        let to_i = ci.world_to_cam() * cj.cam_to_world;
        let pj = pj.map(|p| if p.is_finite() { to_i.transform_point3(p.as_dvec3()).as_vec3() } else { *p });
        Ok([output(pi, ni), output(pj, nj)])
    }

    fn predict_mono(&self, images: &[InputImage], i: usize) -> Result<ViewOutput, String> {
        let (p, _, n) = self.view(images, i)?;
        Ok(output(p, n))
    }

    fn embed(&self, images: &[InputImage], i: usize) -> Result<Option<Vec<f32>>, String> {
        self.embedder.map_or(Ok(None), |e| e.embed(images, i))
    }
}

fn output(points: Raster<Vec3>, normals: Raster<Vec3>) -> ViewOutput {
    let conf = points.map(|p| if p.is_finite() { 5.0 } else { 1.0 });
    ViewOutput { points, conf, normals: Some(normals), desc: None, desc_conf: None }
}

/// A standard normal number (Box-Muller).
fn normal(rng: &mut ChaCha8Rng) -> f64 {
    let (a, b): (f64, f64) = (rng.gen_range(f64::MIN_POSITIVE..1.0), rng.gen());
    (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
}
