//! `dens3r bench train`: training steps of the same network on the same batch, Rust (burn
//! autodiff on the flex CPU backend) against a PyTorch step written from the spec
//! (`bench/torch_dens3r_train.py`): same initial weights, same losses and stage weights, same
//! clipping and AdamW with the same learning rates, same threads, each side in its own process
//! so peak memory is its own. Prints seconds per step, the ratio, peak RSS, and both sides'
//! losses (step 0 compares the losses; later steps the optimiser).

use crate::bench_peer::{bench_python, child_json, peak_rss_mb, PeerArgs};
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use dens3r_backbone::{verify::heads_from_config, ModelConfig, Params, Weights};
use dens3r_scene::npy::{read_f32, write_f32};
use dens3r_train::loss::Matches;
use dens3r_train::pair::PairTarget;
use dens3r_train::train::Batch;
use dens3r_train::{Arch, Dataset, Stage, TrainConfig, Trainer};
use glam::Vec3;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Args)]
pub struct TrainBenchArgs {
    /// The network (official constructor keywords, TOML or JSON).
    #[arg(long, default_value = "configs/small.toml")]
    arch: PathBuf,
    /// Scene folders to draw the batch from.
    #[arg(long, default_value = "data-samples/orbit")]
    data: Vec<PathBuf>,
    /// Network input WxH.
    #[arg(long, default_value = "224x160")]
    size: String,
    /// Pairs per step.
    #[arg(long, default_value_t = 2)]
    batch: usize,
    /// Training steps per side (on the same batch).
    #[arg(long, default_value_t = 3)]
    steps: usize,
    /// 1 (pointmaps + matching) or 2 (+ normal head).
    #[arg(long, default_value_t = 1)]
    stage: u8,
    #[command(flatten)]
    peer: PeerArgs,
}

fn vec3s(v: &[Vec<Vec3>]) -> Vec<f32> {
    v.iter().flat_map(|s| s.iter().flat_map(|p| p.to_array())).collect()
}

/// Writes the batch, the initial weights and the settings into `dir` for both sides.
fn prepare(a: &TrainBenchArgs, dir: &Path) -> Result<()> {
    let stage = match a.stage {
        1 => Stage::One,
        2 => Stage::Two,
        s => bail!("--stage {s}: expected 1 or 2"),
    };
    let size = crate::train::parse_size(&a.size)?;
    let cfg = TrainConfig { stage, size, steps: a.steps.max(1), batch: a.batch, jitter: 0.0, ..Default::default() };
    let arch = Arch::read(&a.arch).map_err(|e| anyhow!(e))?;
    let params = Params::init(&arch.config(), 0);
    cfg.check(params.config.patch).map_err(|e| anyhow!(e))?;
    let data = Dataset::load(&a.data, size, cfg.covis).map_err(|e| anyhow!(e))?;
    let batch = data.batch(&cfg, params.config.patch, 0, &Default::default()).map_err(|e| anyhow!(e))?;
    let (w, h) = size;
    let b = a.batch;
    for (k, img) in batch.images.iter().enumerate() {
        let v = img.clone().into_data().try_to_vec::<f32>().map_err(|e| anyhow!("{e:?}"))?;
        write_f32(&dir.join(format!("img{}.npy", k + 1)), &[b, 3, h, w], &v)?;
    }
    let t = &batch.targets;
    for k in 0..2 {
        let pts: Vec<Vec<Vec3>> = t.iter().map(|s| s.pts[k].clone()).collect();
        write_f32(&dir.join(format!("gt{}.npy", k + 1)), &[b, h, w, 3], &vec3s(&pts))?;
        let valid: Vec<f32> = t.iter().flat_map(|s| s.valid[k].iter().map(|&v| v as u8 as f32)).collect();
        write_f32(&dir.join(format!("valid{}.npy", k + 1)), &[b, h, w], &valid)?;
        let n: Vec<Vec<Vec3>> = t.iter().map(|s| s.normals_in1[k].clone()).collect();
        write_f32(&dir.join(format!("n_in1_{}.npy", k + 1)), &[b, h, w, 3], &vec3s(&n))?;
        let n: Vec<Vec<Vec3>> = t.iter().map(|s| s.normals[k].clone()).collect();
        write_f32(&dir.join(format!("n_own_{}.npy", k + 1)), &[b, h, w, 3], &vec3s(&n))?;
    }
    let m: Vec<f32> = t
        .iter()
        .enumerate()
        .flat_map(|(s, p)| {
            p.matches.idx1.iter().zip(&p.matches.idx2).flat_map(move |(i, j)| [s as f32, *i as f32, *j as f32])
        })
        .collect();
    write_f32(&dir.join("matches.npy"), &[m.len() / 3, 3], &m)?;
    let trainer = Trainer::new(params.clone(), cfg.clone(), Default::default()).map_err(|e| anyhow!(e))?;
    let lrs: Vec<f32> = (0..cfg.steps).map(|s| trainer.lr_at(s)).collect();
    params.save(&dir.join("init.safetensors"))?;
    let c = &params.config;
    let settings = json!({
        "train": cfg,
        "model": dens3r_train::arch::config_json(c),
        "enc_heads": c.enc_heads,
        "dec_heads": c.dec_heads,
        "lrs": lrs,
        "weight_decay": cfg.weight_decay,
        "weights": cfg.stage.weights(),
        "alpha": cfg.alpha,
        "match_temperature": cfg.match_temperature,
        "match_alpha": cfg.match_alpha,
        "clip": cfg.clip,
    });
    std::fs::write(dir.join("bench.json"), serde_json::to_string_pretty(&settings)?)?;
    std::fs::write(dir.join("model.json"), serde_json::to_string_pretty(&settings["model"])?)?;
    Ok(())
}

fn read(dir: &Path, name: &str) -> Result<(Vec<usize>, Vec<f32>)> {
    Ok(read_f32(&dir.join(format!("{name}.npy")))?)
}

/// (internal) the Rust side: reads what [`prepare`] wrote and times the steps.
pub fn run_train(dir: &Path) -> Result<()> {
    crate::keep_freed_memory();
    let settings: Value = serde_json::from_str(&std::fs::read_to_string(dir.join("bench.json"))?)?;
    let cfg: TrainConfig = serde_json::from_value(settings["train"].clone())?;
    let w = Weights::from_safetensors(&dir.join("init.safetensors"))?;
    let heads = heads_from_config(&dir.join("model.json")).map_err(|e| anyhow!(e))?;
    let params = Params::from_weights(&w, &ModelConfig::from_weights(&w, heads)?)?;
    let device = burn::tensor::Device::flex();
    let (shape, _) = read(dir, "img1")?;
    let (b, h, w) = (shape[0], shape[2], shape[3]);
    let images = [read(dir, "img1")?, read(dir, "img2")?]
        .map(|(_, v)| burn::tensor::Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [b, 3, h, w]), &device));
    let split3 = |v: &[f32]| -> Vec<Vec<Vec3>> {
        v.chunks(h * w * 3).map(|s| s.chunks(3).map(|p| Vec3::new(p[0], p[1], p[2])).collect()).collect()
    };
    // Per view: points in view 1's frame, normals in view 1's frame, normals in its own.
    let mut per: Vec<[Vec<Vec<Vec3>>; 3]> = Vec::new();
    for k in 1..=2 {
        per.push([
            split3(&read(dir, &format!("gt{k}"))?.1),
            split3(&read(dir, &format!("n_in1_{k}"))?.1),
            split3(&read(dir, &format!("n_own_{k}"))?.1),
        ]);
    }
    let valid: Vec<Vec<Vec<bool>>> = (1..=2)
        .map(|k| {
            read(dir, &format!("valid{k}"))
                .map(|(_, v)| v.chunks(h * w).map(|s| s.iter().map(|x| *x > 0.5).collect()).collect())
        })
        .collect::<Result<_>>()?;
    let (_, m) = read(dir, "matches")?;
    let targets = (0..b)
        .map(|s| {
            let mut matches = Matches::default();
            for r in m.chunks(3).filter(|r| r[0] as usize == s) {
                matches.idx1.push(r[1] as u32);
                matches.idx2.push(r[2] as u32);
            }
            let two = |i: usize| [per[0][i][s].clone(), per[1][i][s].clone()];
            PairTarget {
                size: (h, w),
                pts: two(0),
                pts_own: two(0),
                valid: [valid[0][s].clone(), valid[1][s].clone()],
                normals_in1: two(1),
                normals: two(2),
                matches,
            }
        })
        .collect();
    let batch = Batch { images, targets, style: Vec::new() };
    let mut trainer =
        Trainer::new(params, cfg.clone(), burn::tensor::Device::autodiff(device)).map_err(|e| anyhow!(e))?;
    let mut steps = Vec::new();
    for _ in 0..cfg.steps {
        let t0 = Instant::now();
        let line = trainer.train_step(&batch).map_err(|e| anyhow!(e))?;
        let mut v = serde_json::to_value(&line.terms)?;
        v["grad_norm"] = json!(line.grad_norm);
        v["seconds"] = json!(t0.elapsed().as_secs_f64());
        steps.push(v);
    }
    println!("{}", json!({ "steps": steps, "peak_rss_mb": peak_rss_mb() }));
    Ok(())
}

fn fastest(v: &Value) -> f64 {
    v["steps"]
        .as_array()
        .map_or(f64::NAN, |s| s.iter().filter_map(|x| x["seconds"].as_f64()).fold(f64::INFINITY, f64::min))
}

fn losses(v: &Value) -> Vec<f64> {
    v["steps"].as_array().map_or(Vec::new(), |s| s.iter().filter_map(|x| x["loss"].as_f64()).collect())
}

/// `dens3r bench train`.
pub fn train(a: TrainBenchArgs) -> Result<()> {
    let threads = a.peer.threads();
    let tmp = tempfile::tempdir()?;
    let dir = a.peer.workdir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    prepare(&a, &dir)?;
    let exe = std::env::current_exe()?;
    let rust = child_json(
        Command::new(&exe).args(["bench", "run-train"]).arg(&dir).env("RAYON_NUM_THREADS", threads.to_string()),
        "Rust",
    )?;
    let python = bench_python(a.peer.python.clone());
    let torch_ok = Command::new(&python)
        .args(["-c", "import torch, safetensors, numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    let torch = if torch_ok {
        Some(child_json(
            Command::new(&python)
                .arg("bench/torch_dens3r_train.py")
                .arg(&dir)
                .args(["--threads", &threads.to_string()])
                .env("OMP_NUM_THREADS", threads.to_string()),
            "PyTorch",
        )?)
    } else {
        eprintln!(
            "note: {} has no torch/safetensors/numpy: run scripts/bench-setup.sh for the PyTorch peer; Rust only",
            python.display()
        );
        None
    };
    println!(
        "training step, {} at {}, batch {} pairs, stage {}, {} steps on one batch, fastest step, {threads} threads",
        a.arch.display(),
        a.size,
        a.batch,
        a.stage,
        a.steps
    );
    let (rs, rm) = (fastest(&rust), rust["peak_rss_mb"].as_f64().unwrap_or(f64::NAN));
    let (ts, tm) =
        torch.as_ref().map_or((f64::NAN, f64::NAN), |t| (fastest(t), t["peak_rss_mb"].as_f64().unwrap_or(f64::NAN)));
    println!("{:>10} {:>10} {:>11} {:>10} {:>10}", "rust s", "torch s", "torch/rust", "rust MB", "torch MB");
    println!("{rs:>10.2} {ts:>10.2} {:>10.2}x {rm:>10.0} {tm:>10.0}", ts / rs);
    let (rl, tl) = (losses(&rust), torch.as_ref().map(losses).unwrap_or_default());
    for (k, r) in rl.iter().enumerate() {
        let t = tl.get(k).copied().unwrap_or(f64::NAN);
        println!("  step {k}: loss rust {r:.6}  torch {t:.6}  |diff| {:.2e}", (r - t).abs());
    }
    let terms = |v: &Value| v["steps"][0].clone();
    println!("  step 0 terms: rust {}", terms(&rust));
    if let Some(t) = &torch {
        println!("  step 0 terms: torch {}", terms(t));
    }
    Ok(())
}
