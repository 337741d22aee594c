//! `dens3r pairs`: one shard of a reconstruction's network work into a pair cache, for any
//! scheduler (Slurm array jobs, Kubernetes jobs); `reconstruct --cache DIR` then reads it.

use crate::reconstruct::{network_id, open_cache, Align};
use anyhow::{bail, Result};
use clap::Args;
use dens3r_align::PairGraph;
use dens3r_recon::{compute_shard, list_images, load_images, Cameras, NetworkPredictor, ReconOptions, Shard, Stage};
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
    /// As `reconstruct --align` will run: sfm needs each photo's own pass, dense the graph's
    /// pairs.
    #[arg(long, value_enum, default_value = "sfm")]
    align: Align,
    /// As `reconstruct --graph` (dense only).
    #[arg(long, default_value = "auto", value_name = "GRAPH")]
    graph: String,
    /// Window of --graph swin / logwin.
    #[arg(long, default_value_t = 3)]
    window: usize,
    /// Close the window around the end.
    #[arg(long)]
    cyclic: bool,
    /// Run the network on the GPU.
    #[arg(long)]
    gpu: bool,
}

pub fn run(a: PairsArgs) -> Result<()> {
    crate::model_args::check_size(a.model.size)?;
    let graph = match a.graph.as_str() {
        "auto" => None,
        g => Some(PairGraph::parse(g, a.window, a.cyclic).map_err(|e| anyhow::anyhow!("--graph {e} (or auto)"))?),
    };
    let (weights, config) = a.model.resolve()?;
    let t0 = Instant::now();
    let paths = list_images(&a.photos)?;
    let settings = dens3r_recon::model::model_settings(config.as_deref())?;
    let images = load_images(&paths, a.model.size, a.model.keep_portrait || settings.keep_portrait)?;
    if images.len() < 2 {
        bail!("reconstruction needs at least 2 photos, got {}", images.len());
    }
    let model = crate::model_args::load_network(&weights, config.as_deref(), a.gpu, a.model.precision)?;
    let cache = open_cache(Some(a.cache.clone()), None)?;
    let network = NetworkPredictor::new(&model, network_id(&a.model, &weights, config.as_deref(), &cache)?);
    let opts = ReconOptions {
        cameras: match a.align {
            Align::Sfm => Cameras::Sfm(Box::default()),
            Align::Dense => Cameras::Dense,
        },
        graph,
        ..Default::default()
    };
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
