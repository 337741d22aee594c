//! `dens3r convert`: an official `.pth` (or any checkpoint) into a folder every command takes
//! as `--weights`, natively.

use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct ConvertArgs {
    /// The checkpoint: an official `.pth` (Dens3R, DUSt3R, MASt3R), a `.safetensors`, or a
    /// Hugging Face folder.
    input: PathBuf,
    /// Output folder: `model.safetensors` (f32) and `config.json` (the `.pth`'s constructor
    /// call, so no `--config` is needed).
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the `model.safetensors` OUTPUT already holds.
    #[arg(long)]
    overwrite: bool,
}

pub fn run(a: ConvertArgs) -> Result<()> {
    if !a.input.exists() {
        bail!("{}: checkpoint not found (a .pth, .safetensors or Hugging Face folder)", a.input.display());
    }
    if !a.overwrite && a.output.join("model.safetensors").exists() {
        bail!(
            "{}: already holds model.safetensors; convert into a new folder, or pass --overwrite",
            a.output.display()
        );
    }
    let c = dens3r_backbone::convert::to_folder(&a.input, &a.output)?;
    let config = match (&c.args, c.config) {
        (Some(args), _) => format!("config.json with its constructor call ({})", args.split('(').next().unwrap_or("")),
        (None, true) => "the input folder's config.json".to_string(),
        (None, false) => {
            "no config.json (the checkpoint records no constructor call: give --config when you use it)".to_string()
        }
    };
    println!("converted {} tensors into {} (model.safetensors, f32; {config})", c.tensors, a.output.display());
    Ok(())
}
