//! The model options shared by the commands that run the network.

use anyhow::Result;
use clap::Args;
use dens3r_backbone::verify::load_model;
use dens3r_backbone::Dens3r;
use std::path::PathBuf;

#[derive(Args)]
pub struct ModelArgs {
    /// Checkpoint (.safetensors; convert a .pth with scripts/pth_to_safetensors.py).
    #[arg(long)]
    pub weights: PathBuf,
    /// JSON with the head counts (enc_num_heads, dec_num_heads, or the converter's "args");
    /// default: head dim 64.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Long side of the network input (512, or 1024 for more detail).
    #[arg(long, default_value_t = 512)]
    pub size: u32,
    /// Keep portrait images as they are (upstream DUSt3R / MASt3R) instead of rotating them.
    #[arg(long)]
    pub keep_portrait: bool,
}

impl ModelArgs {
    /// Loads the model on the default device, warning about unused checkpoint keys.
    pub fn load(&self) -> Result<Dens3r> {
        let device = dens3r_backbone::Device::default();
        let (model, unexpected) =
            load_model(&self.weights, self.config.as_deref(), &device).map_err(anyhow::Error::msg)?;
        if !unexpected.is_empty() {
            eprintln!(
                "warning: {} checkpoint keys are not used by the model (first: {})",
                unexpected.len(),
                unexpected[0]
            );
        }
        Ok(model)
    }
}
