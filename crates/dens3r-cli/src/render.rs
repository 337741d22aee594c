//! `dens3r render`.

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use dens3r_geom::Intrinsics;
use dens3r_render::noise::Noise;
use dens3r_render::procedural::{self, ObjectTexture, ROOM_HI, ROOM_LO};
use dens3r_render::{path, World};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

#[derive(Clone, Copy, PartialEq, ValueEnum)]
pub enum Procedural {
    /// A furnished 4 m room (floor, walls, ceiling, boxes, spheres, tori).
    Room,
    /// A smooth bumpy closed object ("blob") of radius about 1.
    Blob,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum CameraPath {
    /// Circle around the scene, looking at its centre.
    Orbit,
    /// Walk inside the room, looking across it.
    Walk,
}

#[derive(Args)]
pub struct RenderArgs {
    /// Mesh file to render (.ply, .obj, .off).
    #[arg(long, conflicts_with = "procedural", required_unless_present = "procedural")]
    mesh: Option<PathBuf>,
    /// Procedural scene to render instead of a mesh.
    #[arg(long, value_enum)]
    procedural: Option<Procedural>,
    /// Camera path (default: walk for the room, orbit otherwise).
    #[arg(long, value_enum)]
    path: Option<CameraPath>,
    /// Number of views.
    #[arg(long, default_value_t = 30)]
    views: usize,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    width: usize,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    height: usize,
    /// Horizontal field of view, degrees.
    #[arg(long, default_value_t = 60.0)]
    hfov: f64,
    /// Orbit radius as a multiple of the scene's bounding radius.
    #[arg(long, default_value_t = 1.8)]
    distance: f64,
    /// Seed for procedural content and camera jitter.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Multiplicative Gaussian depth noise (0.01 = 1% of the depth), like a depth sensor.
    #[arg(long, default_value_t = 0.0)]
    depth_noise: f32,
    /// Tilt every normal by a random angle of this RMS, degrees.
    #[arg(long, default_value_t = 0.0)]
    normal_noise: f32,
    /// Surface pattern of a mesh or blob: noise, checker, plain, or an image file (a
    /// photograph tiled over the surface, as a real object's texture).
    #[arg(long, default_value = "noise")]
    texture: String,
    /// Output scene folder.
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the scene an earlier dens3r run wrote in OUTPUT (staged, moved in at the end;
    /// files of yours there are never touched).
    #[arg(long)]
    overwrite: bool,
}

/// Most pixels per rendered view (8192 x 8192).
const MAX_RENDER_PIXELS: usize = 8192 * 8192;

/// Refuses options that cannot work, and an output folder that holds a scene.
fn check(a: &RenderArgs) -> Result<()> {
    crate::predict::refuse_existing_scene(&a.output, a.overwrite)?;
    if a.views == 0 || a.views > 10_000 {
        bail!("--views must be in 1..=10000, got {}", a.views);
    }
    let max = dens3r_scene::MAX_IMAGE_SIDE;
    if !(1..=max).contains(&a.width) || !(1..=max).contains(&a.height) {
        bail!("--width and --height must be in 1..={max}, got {}x{}", a.width, a.height);
    }
    // Each pixel keeps about 28 bytes of layers (colour, depth, normals, ids) while it renders.
    if a.width * a.height > MAX_RENDER_PIXELS {
        bail!(
            "--width {} --height {}: {} Mpixels per view (about {:.1} GB of layers); at most {} Mpixels, e.g. 8192x8192",
            a.width,
            a.height,
            a.width * a.height / 1_000_000,
            (a.width * a.height * 28) as f64 / 1e9,
            MAX_RENDER_PIXELS / 1_000_000
        );
    }
    if !(a.hfov > 1.0 && a.hfov < 179.0) {
        bail!("--hfov must be between 1 and 179 degrees, got {}", a.hfov);
    }
    if !(0.0..1.0).contains(&a.depth_noise) || !(0.0..90.0).contains(&a.normal_noise) {
        bail!("--depth-noise must be in [0, 1) and --normal-noise in [0, 90) degrees");
    }
    if a.procedural == Some(Procedural::Room) && a.texture != "noise" {
        bail!("--texture applies to --mesh and --procedural blob; the room has its own materials");
    }
    if !(a.distance > 0.0 && a.distance.is_finite()) {
        bail!("--distance must be positive, got {}", a.distance);
    }
    Ok(())
}

/// The `--texture` value as an object texture (an image file is read and decoded here).
fn object_texture(spec: &str) -> Result<ObjectTexture> {
    Ok(match spec {
        "noise" => ObjectTexture::Noise,
        "checker" => ObjectTexture::Checker,
        "plain" => ObjectTexture::Plain,
        path => {
            let img = dens3r_backbone::preprocess::open_oriented(std::path::Path::new(path)).with_context(|| {
                format!("--texture {path}: not noise, checker or plain, and not a readable image file")
            })?;
            ObjectTexture::Photo(Arc::new(img.to_rgb8()))
        }
    })
}

pub fn run(a: RenderArgs) -> Result<()> {
    check(&a)?;
    let t0 = Instant::now();
    let texture = object_texture(&a.texture)?;
    let (objects, default_path) = match (&a.mesh, a.procedural) {
        (Some(p), _) => {
            let mesh = dens3r_mesh::read_mesh(p)?;
            (procedural::single_object_with(mesh, a.seed as u32, texture), CameraPath::Orbit)
        }
        (None, Some(Procedural::Room)) => (procedural::room(a.seed), CameraPath::Walk),
        (None, Some(Procedural::Blob)) => (
            procedural::single_object_with(procedural::blob_mesh(a.seed, 5), a.seed as u32, texture),
            CameraPath::Orbit,
        ),
        (None, None) => bail!("give --mesh FILE or --procedural room|blob"),
    };
    let world = World::new(objects).map_err(anyhow::Error::msg).context("cannot build the scene")?;
    let poses = match a.path.unwrap_or(default_path) {
        CameraPath::Orbit => {
            let (lo, hi) = world.bounds();
            let center = ((lo + hi) * 0.5).as_dvec3();
            let radius = ((hi - lo).length() * 0.5) as f64;
            path::orbit(center, radius * a.distance, 25.0, 15.0, a.views)
        }
        CameraPath::Walk => {
            if !matches!(a.procedural, Some(Procedural::Room)) {
                bail!("--path walk needs --procedural room (a mesh is orbited)");
            }
            path::room_walk(ROOM_LO.as_dvec3(), ROOM_HI.as_dvec3(), 1.5, a.views, a.seed)
        }
    };
    let k = Intrinsics::from_hfov(a.width, a.height, a.hfov);
    let bar = indicatif::ProgressBar::new(a.views as u64).with_style(
        indicatif::ProgressStyle::with_template("render {bar:30} {pos}/{len} views [{elapsed} < {eta}]")
            .expect("valid template"),
    );
    let summary = dens3r_render::render_to_scene(
        &world,
        k,
        (a.width, a.height),
        &poses,
        &procedural::classes(),
        &a.output,
        |n| bar.set_position(n as u64),
    )?;
    bar.finish_and_clear();
    if a.depth_noise > 0.0 || a.normal_noise > 0.0 {
        let noise = Noise { depth_sigma: a.depth_noise, normal_deg: a.normal_noise, seed: a.seed };
        dens3r_render::noise::add_noise(&a.output, &noise)?;
        println!("added noise: depth {:.2}%, normals {:.1} deg RMS", 100.0 * a.depth_noise, a.normal_noise);
    }
    println!(
        "rendered {} views of {}x{} into {} ({:.0}% pixels with depth, ground-truth mesh {} triangles, {:.1}s)",
        summary.frames,
        a.width,
        a.height,
        a.output.display(),
        100.0 * summary.coverage,
        summary.gt_triangles,
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
