//! `dens3r view OUT`: serves an output folder's page on 127.0.0.1 (for browsers that refuse
//! a page opened from the file system).

use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct ViewArgs {
    /// An output folder of `reconstruct` or `predict` (it holds index.html).
    pub folder: PathBuf,
    /// Port on 127.0.0.1 (0: any free port).
    #[arg(long, default_value_t = 8473)]
    pub port: u16,
}

pub fn run(a: ViewArgs) -> Result<()> {
    if !a.folder.is_dir() {
        bail!(
            "{}: folder not found; give the -o folder of `dens3r reconstruct` or `dens3r predict`",
            a.folder.display()
        );
    }
    if !a.folder.join("index.html").is_file() {
        bail!(
            "{}: no index.html (written by `dens3r reconstruct` and `dens3r predict` since the viewer came in); run one of them into it again",
            a.folder.display()
        );
    }
    let server = dens3r_viewer::serve::Server::bind(&a.folder, a.port).map_err(anyhow::Error::msg)?;
    if !dens3r_viewer::VIEWER_BUNDLED {
        eprintln!("warning: this build has no 3-D viewer (run scripts/build-viewer.sh, then rebuild): the page shows pictures and the summary only");
    }
    println!("serving {} at {} (only on this machine; Ctrl-C stops)", a.folder.display(), server.url());
    server.run();
    Ok(())
}
