//! `dens3r verify`: parity of a checkpoint against arrays dumped from the PyTorch model.

use anyhow::{bail, Result};
use clap::Args;
use dens3r_backbone::verify::{verify_dir, Comparison, ABS_TOL, REL_TOL};
use dens3r_backbone::Precision;
use std::path::PathBuf;

#[derive(Args)]
pub struct VerifyArgs {
    /// Folder with the weights (weights.safetensors, or an official weights.pth as published),
    /// config.json, img1.npy [img2.npy] and reference arrays.
    dir: PathBuf,
    /// Run the network on the GPU (the default build's `gpu-network` feature, or `cuda`).
    #[arg(long)]
    gpu: bool,
    /// Compute in this precision (f32, f16, bf16). The reference is f32: with f16 / bf16 the
    /// table measures the reduced precision's error (printed, not held to the f32 tolerance;
    /// a non-finite output still fails).
    #[arg(long, default_value_t = Precision::F32)]
    precision: Precision,
}

pub fn run(a: VerifyArgs) -> Result<()> {
    let device = dens3r_backbone::device::network_device_at(a.gpu, a.precision)?;
    if let Some(note) = dens3r_backbone::device::precision_note(a.gpu, a.precision) {
        eprintln!("{note}");
    }
    let results = verify_dir(&a.dir, &device)?;
    let reduced = a.precision != Precision::F32;
    // A reduced precision is measured over each array's scale (Comparison::range_error).
    let col = if reduced { "abs/|ref|max" } else { "max rel" };
    println!("{:<44} {:>20} {:>11} {:>12}  status", "array", "shape", "max abs", col);
    for r in &results {
        let shape = format!("{:?}", r.shape);
        let second = if reduced { r.range_error() } else { r.max_rel };
        println!(
            "{:<44} {:>20} {:>11.3e} {:>12.3e}  {}",
            r.name,
            shape,
            r.max_abs,
            second,
            match (r.pass, reduced) {
                (true, _) => "ok",
                (false, false) => "FAIL",
                (false, true) => "over f32 tolerance",
            }
        );
    }
    let failed = results.iter().filter(|r| !r.pass).count();
    println!(
        "{} arrays compared, {failed} over tolerance (abs {ABS_TOL:e}; confidences rel {REL_TOL:e})",
        results.len()
    );
    if reduced {
        let worst = results.iter().map(Comparison::range_error).fold(0.0, f64::max);
        let what = if a.precision == Precision::BF16 && !a.gpu {
            format!(" (on the CPU: {})", dens3r_backbone::device::CPU_BF16_SCOPE)
        } else {
            String::new()
        };
        println!(
            "computed in {}{what}: the errors above are that precision's against the f32 reference (largest {:.2}% \
             of an array's range); the tolerance holds for f32 only",
            a.precision,
            100.0 * worst
        );
        if results.iter().any(|r| !r.max_abs.is_finite()) {
            bail!("non-finite outputs in {}: this network overflows that precision; use --precision f32", a.precision);
        }
        return Ok(());
    }
    if failed > 0 {
        bail!("{failed} arrays differ from the reference beyond tolerance");
    }
    Ok(())
}
