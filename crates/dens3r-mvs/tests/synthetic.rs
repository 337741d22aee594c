//! PatchMatch and fusion against analytic truth: a textured plane and a textured sphere seen by
//! five rendered cameras (depth and normals from the ray caster, independent of the code under
//! test).

use dens3r_geom::{look_at, Intrinsics, PinholeCamera, Raster};
use dens3r_mvs::{run_mvs, MvsError, MvsOptions, MvsResult, PriorMaps, ViewSource};
use dens3r_render::{Material, Object, RenderedView, Shape, Texture, World};
use glam::{DVec3, Quat, Vec3};
use image::RgbImage;

/// Rendered views held in memory, with an optional prior per view.
struct Rendered {
    cameras: Vec<PinholeCamera>,
    views: Vec<RenderedView>,
    priors: Vec<Option<PriorMaps>>,
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
        Ok(self.priors[i].clone())
    }
}

fn object(shape: Shape, translation: Vec3, texture: Texture, seed: u32) -> Object {
    Object {
        name: "o".into(),
        shape,
        rotation: Quat::IDENTITY,
        translation,
        class_id: 1,
        material: Material { color: [0.9, 0.8, 0.7], texture, seed },
    }
}

/// Five cameras 4 units from the origin, looking at it from a cross of directions.
fn cameras(w: usize, h: usize) -> Vec<PinholeCamera> {
    let k = Intrinsics::from_hfov(w, h, 50.0);
    [(0.0, 0.0), (0.7, 0.0), (-0.7, 0.0), (0.0, 0.6), (0.0, -0.6)]
        .iter()
        .map(|&(x, y)| PinholeCamera {
            intrinsics: k,
            width: w,
            height: h,
            cam_to_world: look_at(DVec3::new(x, y, 4.0), DVec3::ZERO, DVec3::Y).unwrap(),
        })
        .collect()
}

fn render(world: &World, cameras: Vec<PinholeCamera>) -> Rendered {
    let views: Vec<RenderedView> = cameras.iter().map(|c| world.render(c)).collect();
    let priors = vec![None; views.len()];
    Rendered { cameras, views, priors }
}

/// World points each view sees (as SfM tracks would give): its true depth on a coarse grid.
fn truth_points(r: &Rendered) -> Vec<Vec<DVec3>> {
    r.cameras
        .iter()
        .zip(&r.views)
        .map(|(c, v)| {
            let mut pts = Vec::new();
            for y in (4..c.height).step_by(16) {
                for x in (4..c.width).step_by(16) {
                    let d = *v.depth.get(x, y) as f64;
                    if d > 0.0 {
                        pts.push(c.cam_to_world.transform_point3(c.intrinsics.unproject(x as f64, y as f64) * d));
                    }
                }
            }
            pts
        })
        .collect()
}

/// Pixels of view `i` whose 7 x 7 neighbourhood is all surface (no silhouette edges).
fn interior(depth: &Raster<f32>) -> Raster<bool> {
    let (w, h) = (depth.width(), depth.height());
    Raster::from_fn(w, h, |x, y| {
        if x < 8 || y < 8 || x + 8 >= w || y + 8 >= h {
            return false;
        }
        (y - 3..=y + 3).all(|yy| (x - 3..=x + 3).all(|xx| *depth.get(xx, yy) > 0.0))
    })
}

/// Share of the reference view's interior pixels whose depth is within `tol` of the truth, and
/// the median normal error (degrees) there.
fn score(res: &MvsResult, truth: &RenderedView, i: usize, tol: f32) -> (f64, f64) {
    let maps = &res.views[i].maps;
    let inside = interior(&truth.depth);
    let (mut ok, mut total) = (0usize, 0usize);
    let mut angles = Vec::new();
    for y in 0..maps.depth.height() {
        for x in 0..maps.depth.width() {
            if !*inside.get(x, y) {
                continue;
            }
            let (d, t) = (*maps.depth.get(x, y), *truth.depth.get(x, y));
            total += 1;
            if ((d - t) / t).abs() <= tol {
                ok += 1;
            }
            let (n, m) = (*maps.normals.get(x, y), *truth.normals.get(x, y));
            angles.push(n.dot(m).clamp(-1.0, 1.0).acos().to_degrees() as f64);
        }
    }
    angles.sort_by(|a, b| a.total_cmp(b));
    (ok as f64 / total.max(1) as f64, angles[angles.len() / 2])
}

fn noise(scale: f32) -> Texture {
    Texture::Noise { scale }
}

#[test]
fn a_textured_plane_is_recovered_within_half_a_percent() {
    // A wall tilted 25 degrees about y, 1 unit behind the origin.
    let wall = Object {
        rotation: Quat::from_rotation_y(25f32.to_radians()),
        ..object(Shape::Cuboid { half: Vec3::new(4.0, 4.0, 0.05) }, Vec3::new(0.0, 0.0, -1.0), noise(0.08), 3)
    };
    let r = render(&World::new(vec![wall]).unwrap(), cameras(320, 240));
    let pts = truth_points(&r);
    let mut o = MvsOptions::default();
    o.patch_match.prior_weight = 0.0;
    let res = run_mvs(&r, Some(pts), &o, |_, _, _| {}).unwrap();
    let (within, normal_deg) = score(&res, &r.views[0], 0, 0.005);
    eprintln!("plane: {:.1}% within 0.5%, median normal error {normal_deg:.2} deg", within * 100.0);
    assert!(within > 0.95, "only {:.1}% of the plane's pixels within 0.5% of the truth", within * 100.0);
    assert!(normal_deg < 3.0, "median normal error {normal_deg:.2} deg");
}

#[test]
fn a_textured_sphere_is_recovered_within_half_a_percent() {
    let sphere = object(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, noise(0.06), 5);
    let wall = object(Shape::Cuboid { half: Vec3::new(5.0, 5.0, 0.05) }, Vec3::new(0.0, 0.0, -2.0), noise(0.1), 6);
    let r = render(&World::new(vec![sphere, wall]).unwrap(), cameras(320, 240));
    let pts = truth_points(&r);
    let mut o = MvsOptions::default();
    o.patch_match.prior_weight = 0.0;
    let res = run_mvs(&r, Some(pts), &o, |_, _, _| {}).unwrap();
    // Score the sphere only: pixels whose true depth is nearer than the wall.
    let truth = &r.views[0];
    let only_sphere = RenderedView { depth: truth.depth.map(|d| if *d < 3.5 { *d } else { 0.0 }), ..truth.clone() };
    let (within, normal_deg) = score(&res, &only_sphere, 0, 0.005);
    eprintln!("sphere: {:.1}% within 0.5%, median normal error {normal_deg:.2} deg", within * 100.0);
    assert!(within > 0.9, "only {:.1}% of the sphere's pixels within 0.5% of the truth", within * 100.0);
    assert!(normal_deg < 3.0, "median normal error {normal_deg:.2} deg");
}

/// Each view's own depth, scaled by `factor` (a prior that is off by a known amount), its
/// true normals, full confidence.
fn priors(r: &Rendered, factor: f32) -> Vec<Option<PriorMaps>> {
    r.views
        .iter()
        .map(|v| Some(PriorMaps { depth: v.depth.map(|d| d * factor), normals: Some(v.normals.clone()), conf: None }))
        .collect()
}

#[test]
fn the_prior_moves_a_texture_less_plane_to_it() {
    // A plain wall: no photometric evidence anywhere on it.
    let wall = object(Shape::Cuboid { half: Vec3::new(6.0, 6.0, 0.05) }, Vec3::new(0.0, 0.0, -1.0), Texture::Plain, 2);
    let mut r = render(&World::new(vec![wall]).unwrap(), cameras(160, 120));
    let pts = truth_points(&r);
    // The prior says the wall is 3% nearer than it is: with the prior on, PatchMatch follows it.
    r.priors = priors(&r, 0.97);
    let with = run_mvs(&r, Some(pts.clone()), &MvsOptions::default(), |_, _, _| {}).unwrap();
    let mut o = MvsOptions::default();
    o.patch_match.prior_weight = 0.0;
    let without = run_mvs(&r, Some(pts), &o, |_, _, _| {}).unwrap();
    let near_prior = |res: &MvsResult| {
        let maps = &res.views[0].maps;
        let t = &r.views[0].depth;
        let inside = interior(t);
        let (mut ok, mut n) = (0, 0);
        for y in 0..t.height() {
            for x in 0..t.width() {
                if *inside.get(x, y) {
                    n += 1;
                    let p = 0.97 * *t.get(x, y);
                    ok += (((*maps.depth.get(x, y) - p) / p).abs() < 0.005) as usize;
                }
            }
        }
        ok as f64 / n as f64
    };
    let (a, b) = (near_prior(&with), near_prior(&without));
    eprintln!("texture-less wall: {:.1}% of pixels at the prior with it, {:.1}% without", 100.0 * a, 100.0 * b);
    assert!(a > 0.95, "with the prior only {:.1}% of the wall's pixels follow it", 100.0 * a);
    assert!(b < 0.5, "without the prior {:.1}% of the wall's pixels sit at the prior's depth", 100.0 * b);
}
