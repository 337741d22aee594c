//! `dens3r info`.

use anyhow::Result;
use clap::Args;
use dens3r_scene::{Layer, Scene};
use std::path::PathBuf;

#[derive(Args)]
pub struct InfoArgs {
    /// Scene folder.
    scene: PathBuf,
}

pub fn run(a: InfoArgs) -> Result<()> {
    let s = Scene::open(&a.scene)?;
    let frames = s.frames();
    println!("scene     {}", a.scene.display());
    println!("frames    {}", frames.len());
    let mut sizes: Vec<(usize, usize)> = frames.iter().map(|f| (f.width, f.height)).collect();
    sizes.sort();
    sizes.dedup();
    let sizes: Vec<String> = sizes.iter().map(|(w, h)| format!("{w}x{h}")).collect();
    println!("sizes     {}", sizes.join(", "));
    let k = frames[0].camera().intrinsics;
    println!("K[0]      fx {:.2} fy {:.2} cx {:.2} cy {:.2}", k.fx, k.fy, k.cx, k.cy);
    let centers: Vec<_> = frames.iter().map(|f| f.camera().center()).collect();
    let lo = centers.iter().fold(centers[0], |a, c| a.min(*c));
    let hi = centers.iter().fold(centers[0], |a, c| a.max(*c));
    println!("centres   x [{:.3}, {:.3}]  y [{:.3}, {:.3}]  z [{:.3}, {:.3}]", lo.x, hi.x, lo.y, hi.y, lo.z, hi.z);
    for layer in Layer::ALL {
        let n = frames.iter().filter(|f| s.has(f, layer)).count();
        println!("{:<9} {n}/{}", layer.location().0, frames.len());
    }
    let mut depths = Vec::new();
    for f in frames {
        if let Some(d) = s.depth(f)? {
            depths.extend(d.data().iter().filter(|v| v.is_finite() && **v > 0.0).map(|v| *v as f64));
        }
    }
    if !depths.is_empty() {
        let n = depths.len();
        let med = dens3r_geom::focal::median(&mut depths).unwrap_or(0.0);
        println!("depth     {n} valid pixels, min {:.3} median {:.3} max {:.3}", depths[0], med, depths[n - 1]);
    }
    let classes = s.classes()?;
    if !classes.is_empty() {
        let list: Vec<String> = classes.iter().map(|(k, v)| format!("{k}={v}")).collect();
        println!("classes   {}", list.join(" "));
    }
    if s.root().join("gt_mesh.ply").is_file() {
        println!("gt mesh   gt_mesh.ply");
    }
    Ok(())
}
