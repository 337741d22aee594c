//! `dens3r verify`: parity of a checkpoint against arrays dumped from the PyTorch model.

use anyhow::{bail, Result};
use clap::Args;
use dens3r_backbone::verify::{verify_dir, ABS_TOL, REL_TOL};
use std::path::PathBuf;

#[derive(Args)]
pub struct VerifyArgs {
    /// Folder with weights.safetensors, config.json, img1.npy [img2.npy] and reference arrays.
    dir: PathBuf,
    /// Run the network on the GPU (the default build's `gpu-network` feature, or `cuda`).
    #[arg(long)]
    gpu: bool,
}

pub fn run(a: VerifyArgs) -> Result<()> {
    let device = dens3r_backbone::device::network_device(a.gpu)?;
    let results = verify_dir(&a.dir, &device)?;
    println!("{:<44} {:>20} {:>11} {:>11}  status", "array", "shape", "max abs", "max rel");
    for r in &results {
        let shape = format!("{:?}", r.shape);
        println!(
            "{:<44} {:>20} {:>11.3e} {:>11.3e}  {}",
            r.name,
            shape,
            r.max_abs,
            r.max_rel,
            if r.pass { "ok" } else { "FAIL" }
        );
    }
    let failed = results.iter().filter(|r| !r.pass).count();
    println!(
        "{} arrays compared, {failed} over tolerance (abs {ABS_TOL:e}; confidences rel {REL_TOL:e})",
        results.len()
    );
    if failed > 0 {
        bail!("{failed} arrays differ from the reference beyond tolerance");
    }
    Ok(())
}
