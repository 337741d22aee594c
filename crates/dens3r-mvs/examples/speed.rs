//! Times PatchMatch on five rendered views of a textured wall and sphere at a given size:
//! `cargo run --release -p dens3r-mvs --example speed -- 1600 1067`.

use dens3r_geom::{look_at, Intrinsics, PinholeCamera};
use dens3r_mvs::{run_mvs, MvsError, MvsOptions, PriorMaps, Stage, ViewSource};
use dens3r_render::{Material, Object, RenderedView, Shape, Texture, World};
use glam::{DVec3, Quat, Vec3};
use image::RgbImage;
use std::time::Instant;

struct Rendered {
    cameras: Vec<PinholeCamera>,
    views: Vec<RenderedView>,
}

impl ViewSource for Rendered {
    fn len(&self) -> usize {
        self.cameras.len()
    }
    fn camera(&self, i: usize) -> PinholeCamera {
        self.cameras[i]
    }
    fn name(&self, i: usize) -> String {
        format!("{i:04}")
    }
    fn image(&self, i: usize) -> Result<RgbImage, MvsError> {
        Ok(self.views[i].rgb.clone())
    }
    fn prior(&self, i: usize) -> Result<Option<PriorMaps>, MvsError> {
        Ok(Some(PriorMaps { depth: self.views[i].depth.clone(), normals: None, conf: None }))
    }
}

fn main() {
    let args: Vec<usize> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let (w, h) = (args.first().copied().unwrap_or(1600), args.get(1).copied().unwrap_or(1067));
    let obj = |shape, t: Vec3, scale: f32, seed| Object {
        name: "o".into(),
        shape,
        rotation: Quat::IDENTITY,
        translation: t,
        class_id: 1,
        material: Material { color: [0.9, 0.8, 0.7], texture: Texture::Noise { scale }, seed },
    };
    let world = World::new(vec![
        obj(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, 0.06, 5),
        obj(Shape::Cuboid { half: Vec3::new(5.0, 5.0, 0.05) }, Vec3::new(0.0, 0.0, -2.0), 0.1, 6),
    ])
    .unwrap();
    let k = Intrinsics::from_hfov(w, h, 50.0);
    let cameras: Vec<PinholeCamera> = [(0.0, 0.0), (0.7, 0.0), (-0.7, 0.0), (0.0, 0.6), (0.0, -0.6)]
        .iter()
        .map(|&(x, y)| PinholeCamera {
            intrinsics: k,
            width: w,
            height: h,
            cam_to_world: look_at(DVec3::new(x, y, 4.0), DVec3::ZERO, DVec3::Y).unwrap(),
        })
        .collect();
    let t = Instant::now();
    let views = cameras.iter().map(|c| world.render(c)).collect();
    eprintln!("rendered in {:.1} s", t.elapsed().as_secs_f64());
    let r = Rendered { cameras, views };
    let mut o = MvsOptions { max_size: w.max(h), ..Default::default() };
    o.patch_match.prior_weight = 0.0;
    let only_first = std::env::var("ONLY_FIRST").is_ok();
    let t = Instant::now();
    let mut last = Instant::now();
    let res = run_mvs(&r, None, &o, |stage, done, total| {
        eprintln!("{stage:?} {done}/{total} {:.2} s", last.elapsed().as_secs_f64());
        last = Instant::now();
        if only_first && stage == Stage::Photometric && done == 1 {
            std::process::exit(0);
        }
    })
    .unwrap();
    eprintln!(
        "{} x {}: {:.2} s total, {:.2} s per view, kept {:.1}%",
        w,
        h,
        t.elapsed().as_secs_f64(),
        res.seconds_per_view.iter().sum::<f64>() / res.seconds_per_view.len() as f64,
        100.0 * res.kept_fraction()
    );
}
