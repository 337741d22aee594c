//! `dens3r pairs`: one shard of a reconstruction's network work into a pair cache, for any
//! scheduler (Slurm array jobs, Kubernetes jobs); `reconstruct --cache DIR` then reads it.

use crate::reconstruct::{network_id, open_cache, Pairing};
use anyhow::Result;
use clap::Args;
use dens3r_recon::{compute_shard, list_images, load_images, NetworkPredictor, ReconOptions, Shard, Stage};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct PairsArgs {
    /// Photos: a folder or files, as `reconstruct` takes them.
    #[arg(required = true)]
    photos: Vec<PathBuf>,
    /// The pair cache to fill (a folder every shard and the later `reconstruct --cache` share).
    #[arg(long, value_name = "DIR")]
    cache: PathBuf,
    /// Which share of the work: I/N (from 0/N to N-1/N).
    #[arg(long, default_value = "0/1", value_parser = Shard::parse)]
    shard: Shard,
    #[command(flatten)]
    model: crate::model_args::ModelArgs,
    /// As the `reconstruct` that will read the cache: sfm needs each photo's own pass, dense
    /// the graph's pairs.
    #[command(flatten)]
    pairing: Pairing,
    /// Run the network on the GPU.
    #[arg(long)]
    gpu: bool,
}

pub fn run(a: PairsArgs) -> Result<()> {
    crate::model_args::check_size(a.model.size)?;
    let graph = a.pairing.graph()?;
    let (weights, config) = a.model.resolve()?;
    let t0 = Instant::now();
    let paths = list_images(&a.photos)?;
    let settings = dens3r_recon::model::model_settings(config.as_deref())?;
    let images = load_images(&paths, a.model.size, a.model.keep_portrait || settings.keep_portrait)?;
    // The same photos as the reconstruct that reads the cache.
    let (images, _) = crate::reconstruct::scene_photos(images)?;
    let model = crate::model_args::load_network(&weights, config.as_deref(), a.gpu, a.model.precision)?;
    let cache = open_cache(Some(a.cache.clone()), None)?;
    let network = NetworkPredictor::new(&model, network_id(&a.model, &weights, config.as_deref(), &cache)?);
    let opts = ReconOptions { cameras: a.pairing.cameras(), graph, ..Default::default() };
    let bar = crate::reconstruct::bar("network", 0, "runs");
    let mut warnings = Vec::new();
    let stats = compute_shard(&images, &network, &cache, &opts, a.shard, &mut warnings, &mut |stage, done, total| {
        if stage == Stage::Predict {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        }
    })?;
    bar.finish_and_clear();
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "shard {}/{}: {} of {} network runs ({} already cached) in {:.1}s -> {}",
        a.shard.index,
        a.shard.count,
        stats.entries,
        stats.total,
        stats.cached,
        t0.elapsed().as_secs_f64(),
        a.cache.display()
    );
    Ok(())
}
