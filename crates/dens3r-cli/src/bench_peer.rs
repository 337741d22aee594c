//! What every benchmark against a peer (PyTorch, Open3D) shares: the peer's Python, running a
//! measured child process and reading its JSON line, and peak memory.

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::Value;
use std::path::PathBuf;
use std::process::Command;

/// What a benchmark against a PyTorch peer needs: threads, the Python, a working folder.
#[derive(Args)]
pub struct PeerArgs {
    /// Threads for both sides (default: all cores).
    #[arg(long)]
    pub(crate) threads: Option<usize>,
    /// Python with torch, safetensors and numpy (default: .cache/bench-venv/bin/python3 made by
    /// scripts/bench-setup.sh, else python3).
    #[arg(long)]
    pub(crate) python: Option<PathBuf>,
    /// Working folder for weights and inputs (default: a temporary folder).
    #[arg(long)]
    pub(crate) workdir: Option<PathBuf>,
}

impl PeerArgs {
    /// `--threads`, else every core.
    pub(crate) fn threads(&self) -> usize {
        self.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
    }
}

/// The Python for benchmark peers: the given one, else .cache/bench-venv's
/// (scripts/bench-setup.sh), else `python3`.
pub(crate) fn bench_python(given: Option<PathBuf>) -> PathBuf {
    given.unwrap_or_else(|| {
        let venv = PathBuf::from(".cache/bench-venv/bin/python3");
        if venv.is_file() {
            venv
        } else {
            PathBuf::from("python3")
        }
    })
}

pub(crate) fn peak_rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Runs a measured child (ours or the peer's) and reads the JSON object on its last line.
pub(crate) fn child_json(cmd: &mut Command, what: &str) -> Result<Value> {
    let out = cmd.output().with_context(|| format!("cannot start the {what} run"))?;
    if !out.status.success() {
        bail!("{what} run failed: {}", String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or(""));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    serde_json::from_str(text.lines().last().unwrap_or(""))
        .with_context(|| format!("{what} run printed no JSON: {text}"))
}
