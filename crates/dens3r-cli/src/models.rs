//! `dens3r models`: the official checkpoints dens3r knows by name, where they are cached, and
//! their download (`--fetch NAME`, or any `--weights NAME`).

use anyhow::{anyhow, Result};
use clap::Args;
use dens3r_hub::{Known, Source};
use std::path::PathBuf;

#[derive(Args)]
pub struct ModelsArgs {
    /// Download this checkpoint into the cache now (otherwise the first `--weights NAME` does).
    #[arg(long)]
    fetch: Option<String>,
}

pub fn run(a: ModelsArgs) -> Result<()> {
    if let Some(name) = &a.fetch {
        let k = dens3r_hub::find(name)
            .ok_or_else(|| anyhow!("{name}: not a known checkpoint; `dens3r models` lists them"))?;
        let checked = reverify(k)?;
        let dir = fetch(k)?;
        println!("{name}: {}", dir.display());
        for line in checked {
            println!("  {line}");
        }
        return Ok(());
    }
    println!("{:<19} {:<7} {:>7}  {:<10}  predicts", "name", "family", "size", "where");
    for k in dens3r_hub::KNOWN {
        let place = match k.source {
            Source::Bundled => "bundled",
            Source::Manual { .. } => "by hand",
            Source::Hub { .. } if dens3r_hub::is_cached(k) => "cached",
            Source::Hub { .. } => "download",
        };
        println!("{:<19} {:<7} {:>5}MB  {:<10}  {}", k.name, k.family, k.size_mb, place, k.predicts);
        println!("{:<19} official name {}; licence {}; {}", "", k.official, k.licence, k.page);
    }
    println!(
        "`--weights NAME` (short or official name) downloads into {} ($DENS3R_HOME) from {} ($DENS3R_HUB_ENDPOINT), \
         resuming a cut download and checking the SHA-256 the hub publishes",
        dens3r_hub::home().join("models").display(),
        dens3r_hub::endpoint()
    );
    Ok(())
}

/// The folder of the known checkpoint `k` (the bundled one's, or its cache folder, downloaded
/// first when missing, with a progress bar on stderr).
pub fn fetch(k: &Known) -> Result<PathBuf> {
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "{msg} {bar:30} {bytes}/{total_bytes} [{elapsed} < {eta}, {bytes_per_sec}]",
        )
        .expect("a valid template"),
    );
    // The message changes once per file, not at every block.
    let mut current = String::new();
    let dir = dens3r_recon::model::fetch_known(k, &mut |line| eprintln!("{line}"), &mut |file, p| {
        if file != current {
            current = file.to_string();
            bar.set_message(current.clone());
        }
        if let Some(t) = p.total {
            bar.set_length(t);
        }
        bar.set_position(p.done);
    });
    bar.finish_and_clear();
    Ok(dir?)
}

/// `--fetch` on a cached checkpoint checks every cached file in full (format, SHA-256 against
/// its download record): a file of dens3r's that fails is removed to be fetched again, with a
/// warning naming it; one placed by hand that fails is named and left alone (an error).
fn reverify(k: &Known) -> Result<Vec<String>> {
    let mut lines = Vec::new();
    if !matches!(k.source, Source::Hub { .. }) {
        return Ok(lines);
    }
    let dir = dens3r_hub::model_dir(k);
    for file in dens3r_hub::catalogue::HUB_FILES {
        let path = dir.join(file);
        if !path.is_file() {
            continue;
        }
        match dens3r_hub::verify_cached(k, file) {
            Ok(msg) => lines.push(format!("{file}: verified, {msg}")),
            Err(e) if dir.join(format!("{file}.sha256")).is_file() => {
                eprintln!("warning: {e}; downloading it again");
                std::fs::remove_file(&path).map_err(|x| anyhow!("{}: cannot remove ({x})", path.display()))?;
            }
            Err(e) => return Err(anyhow!("{e}; remove it (dens3r did not place it) and run again")),
        }
    }
    Ok(lines)
}
