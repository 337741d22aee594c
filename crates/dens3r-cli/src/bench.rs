//! `dens3r bench backbone`: full-size Dens3R (random weights) one pair forward, Rust vs a
//! PyTorch module written from the spec (`bench/torch_dens3r.py`), same weights, same input,
//! same thread count, each in its own process so peak memory is its own. Two different
//! seeded images make the pair; each side runs the forward `--repeat` times and reports the
//! fastest (this 2-core VM's timings drift by 20% from run to run). `--gpu` runs both sides
//! on the GPU (ours as `--gpu` picks it, PyTorch on CUDA) and reports peak device memory;
//! `--precision` adds a row per float precision.

use crate::bench_fusion::FusionArgs;
use crate::bench_peer::{bench_python, child_json, peak_rss_mb, PeerArgs};
use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use dens3r_backbone::Precision;
use dens3r_backbone::{Dens3r, ModelConfig, Tensor, TensorData, Weights};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Rust vs PyTorch on the full-size Dens3R with random weights.
    Backbone(BackboneArgs),
    /// Rust vs Open3D TSDF fusion on rendered scenes (time, memory, mesh accuracy).
    Fusion(FusionArgs),
    /// Rust vs PyTorch training steps of a small Dens3R on the same batch (time, memory, losses).
    Train(crate::bench_train::TrainBenchArgs),
    /// (internal) time Rust training steps on a batch written by `bench train`.
    #[command(hide = true)]
    RunTrain { dir: PathBuf },
    /// `reconstruct`'s cameras vs COLMAP's on rendered walkthroughs and orbits (registered
    /// views, rotation, baseline and focal errors, reprojection error, time, memory).
    Sfm(crate::bench_sfm::SfmBenchArgs),
    /// Multi-view stereo on rendered textured scenes with their true meshes: the network-only
    /// path, MVS without and with the prior, and the truth's depth through the same fusion.
    Mvs(crate::bench_mvs::MvsBenchArgs),
    /// `reconstruct` on walkthroughs of 25 to 300 views (time per stage, peak RSS, camera
    /// error, the pair graph against the truth's co-visibility).
    Scale(crate::bench_scale::ScaleBenchArgs),
    /// Neural SDF vs TSDF fusion on a noisy object orbit, with the no-normals ablation.
    Nsdf(crate::bench_nsdf::NsdfBenchArgs),
    /// (internal) fuse one scene and print timings as JSON.
    #[command(hide = true)]
    RunFuse {
        scene: PathBuf,
        voxel: f32,
        out: PathBuf,
        #[arg(long)]
        gpu: bool,
    },
    /// (internal) write random full-size weights.
    #[command(hide = true)]
    MakeWeights { out: PathBuf },
    /// (internal) time one Rust forward.
    #[command(hide = true)]
    RunRust {
        weights: PathBuf,
        width: usize,
        height: usize,
        dir: PathBuf,
        repeat: usize,
        #[arg(long)]
        config: Option<PathBuf>,
        #[arg(long)]
        gpu: bool,
        #[arg(long, default_value_t = Precision::F32)]
        precision: Precision,
    },
}

#[derive(Args)]
pub struct BackboneArgs {
    /// Input sizes, WIDTHxHEIGHT (comma separated).
    #[arg(long, default_value = "512x384,1024x768")]
    sizes: String,
    #[command(flatten)]
    peer: PeerArgs,
    /// Forward passes per side; the fastest is reported.
    #[arg(long, default_value_t = 2)]
    repeat: usize,
    /// Time this checkpoint instead of random full-size weights: a file, a Hugging Face
    /// folder, or `dens3r-s` (the bundled default model); both sides read an f32 copy.
    #[arg(long)]
    weights: Option<String>,
    /// Head counts of --weights (as `predict --config`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Both sides on the GPU: ours as `--gpu` picks it (CUDA when built with `cuda`, else
    /// wgpu), PyTorch on CUDA; memory columns are then each side's peak device memory.
    #[arg(long)]
    gpu: bool,
    /// Precisions to time, comma separated (f32, f16, bf16): each row runs both sides in one.
    #[arg(long, value_delimiter = ',', default_value = "f32")]
    precision: Vec<Precision>,
}

pub fn run(c: BenchCommand) -> Result<()> {
    match c {
        BenchCommand::Backbone(a) => backbone(a),
        BenchCommand::Fusion(a) => crate::bench_fusion::fusion(a),
        BenchCommand::Nsdf(a) => crate::bench_nsdf::run(a),
        BenchCommand::Sfm(a) => crate::bench_sfm::run(a),
        BenchCommand::Mvs(a) => crate::bench_mvs::run(a),
        BenchCommand::Scale(a) => crate::bench_scale::run(a),
        BenchCommand::Train(a) => crate::bench_train::train(a),
        BenchCommand::RunTrain { dir } => crate::bench_train::run_train(&dir),
        BenchCommand::RunFuse { scene, voxel, out, gpu } => crate::bench_fusion::run_fuse(&scene, voxel, &out, gpu),
        BenchCommand::MakeWeights { out } => {
            let w = Weights::synthetic(7, 0.02);
            // Checks that the weights load (on the CPU: burn's default device is the first GPU backend).
            Dens3r::load(&w, ModelConfig::dens3r_full(), &burn::tensor::Device::flex())?;
            w.save_safetensors(&out)?;
            Ok(())
        }
        BenchCommand::RunRust { weights, width, height, dir, repeat, config, gpu, precision } => {
            let device = dens3r_backbone::device::network_device_at(gpu, precision)?;
            run_rust(&weights, config.as_deref(), (width, height), &dir, repeat, &device)
        }
    }
}

/// A seeded input in [-1, 1], `(1, 3, H, W)`.
fn seeded_image(width: usize, height: usize, seed: u64) -> Vec<f32> {
    let mut state = seed;
    (0..3 * width * height)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        })
        .collect()
}

/// Times our forward on `device` (in its precision) and prints one JSON line: seconds, peak RSS,
/// on a GPU the memory its allocator holds after the passes (its pools keep their pages, so
/// that is the peak reserved), and the per-stage profile.
fn run_rust(
    weights: &Path,
    config: Option<&Path>,
    (width, height): (usize, usize),
    dir: &Path,
    repeat: usize,
    device: &dens3r_backbone::Device,
) -> Result<()> {
    let gpu = dens3r_backbone::device::is_gpu(device);
    let t0 = Instant::now();
    let (model, _) = dens3r_backbone::verify::load_model(weights, config, device).map_err(anyhow::Error::msg)?;
    let load_s = t0.elapsed().as_secs_f64();
    // Two different images, shared with the PyTorch side through img1.npy / img2.npy.
    let mut inputs = Vec::new();
    for (i, seed) in [(1, 0x1234_5678_9abc_def1u64), (2, 0x0fed_cba9_8765_4321)] {
        let img = seeded_image(width, height, seed);
        dens3r_scene::npy::write_f32(&dir.join(format!("img{i}.npy")), &[1, 3, height, width], &img)?;
        inputs.push(Tensor::<4>::from_data(TensorData::new(img, [1, 3, height, width]), device));
    }
    let (x1, x2) = (inputs[0].clone(), inputs[1].clone());
    let mut times = Vec::new();
    let mut pts = Vec::new();
    // On a GPU the first pass compiles and tunes kernels: one more pass, not timed.
    for pass in 0..repeat.max(1) + usize::from(gpu) {
        let t0 = Instant::now();
        let pred = model.forward(x1.clone(), x2.clone());
        pts =
            pred.views[0].pts3d.to_data().convert::<f32>().try_to_vec::<f32>().map_err(|e| anyhow::anyhow!("{e:?}"))?;
        if pass >= usize::from(gpu) {
            times.push(t0.elapsed().as_secs_f64());
        }
    }
    let seconds = times.iter().copied().fold(f64::INFINITY, f64::min);
    // Single-image prediction: the official code runs the self-pair; we run forward_mono.
    let mut mono = f64::INFINITY;
    for _ in 0..repeat.max(1) {
        let t0 = Instant::now();
        let _ = model.forward_mono(x1.clone()).pts3d.to_data();
        mono = mono.min(t0.elapsed().as_secs_f64());
    }
    dens3r_scene::npy::write_f32(&dir.join("pts3d.npy"), &[height, width, 3], &pts)?;
    // Peak memory of the timed passes, before the profile's extra ones.
    let rss = peak_rss_mb();
    let device_mb = device.memory_pool_usage().filter(|_| gpu).map(|u| u.bytes_reserved as f64 / (1u64 << 20) as f64);
    let stages = profile(&model, x1, x2);
    println!(
        "{}",
        serde_json::json!({"seconds": seconds, "mono_seconds": mono, "all_seconds": times, "load_seconds": load_s,
            "peak_rss_mb": rss, "device_mb": device_mb, "device_name": dens3r_backbone::device::gpu_name(device),
            "stages": stages})
    );
    Ok(())
}

/// The profile's stages, in forward order: (key, what it covers). The PyTorch peer
/// (`bench/torch_dens3r.py --profile`) times and counts the same stages.
const STAGES: [(&str, &str); 5] = [
    ("encoder", "encoder, both views"),
    ("decoder", "decoder (embed, blocks, norm), both views"),
    ("pointmap", "pointmap DPT + pts3d / conf, both views"),
    ("normal", "normal DPT + normalisation, both views"),
    ("desc", "descriptor MLP + pixel shuffle, both views"),
];

/// Seconds per stage of one pair forward ([`STAGES`]), each stage forced to finish before the
/// next starts; a head's time is the difference of head passes with and without it.
/// Printed beside PyTorch's by `bench backbone`.
fn profile(model: &Dens3r, x1: Tensor<4>, x2: Tensor<4>) -> serde_json::Value {
    use dens3r_backbone::HeadOutputs;
    let timed = |f: &mut dyn FnMut()| {
        let t = Instant::now();
        f();
        t.elapsed().as_secs_f64()
    };
    let mut enc = None;
    let encoder = timed(&mut || {
        let [(e1, g1), (e2, g2)] = model.encode_images(x1.clone(), x2.clone());
        let _ = (e1.to_data(), e2.to_data());
        enc = Some((e1, g1, e2, g2));
    });
    let (e1, g1, e2, g2) = enc.expect("set above");
    let mut feats = None;
    let decoder = timed(&mut || {
        let f = model.decode(e1.clone(), g1, e2.clone(), g2);
        for v in &f.views {
            let _ = v.dec.last().map(|t| t.to_data());
        }
        feats = Some(f);
    });
    let f = feats.expect("set above");
    // Fastest of two passes: the first pass of a head set can pay for allocations the
    // timed forwards had warm, which would shift time between the differenced stages.
    let heads = |want: HeadOutputs| {
        let pass = || {
            timed(&mut || {
                let p = model.heads_with(&f, want);
                for v in &p.views {
                    let _ = v.pts3d.to_data();
                    let _ = v.normal.as_ref().map(|n| n.to_data());
                    let _ = v.desc.as_ref().map(|d| d.to_data());
                }
            })
        };
        pass().min(pass())
    };
    let pointmap = heads(HeadOutputs { normal: false, desc: false });
    let with_normal = heads(HeadOutputs { normal: true, desc: false });
    let all = heads(HeadOutputs::ALL);
    let secs = [encoder, decoder, pointmap, (with_normal - pointmap).max(0.0), (all - with_normal).max(0.0)];
    STAGES.iter().zip(secs).map(|((k, _), s)| (k.to_string(), serde_json::json!(s))).collect()
}

/// `WxH,WxH,...`, each side a positive multiple of 16.
fn parse_sizes(sizes: &str) -> Result<Vec<(usize, usize)>> {
    sizes
        .split(',')
        .map(|s| {
            let (w, h) = s.trim().split_once('x').with_context(|| format!("size '{s}' is not WIDTHxHEIGHT"))?;
            let (w, h): (usize, usize) = (w.parse()?, h.parse()?);
            if !w.is_multiple_of(16) || !h.is_multiple_of(16) || w == 0 || h == 0 {
                bail!("size {w}x{h}: both sides must be positive multiples of 16");
            }
            Ok((w, h))
        })
        .collect()
}

/// The weights both sides read (f32, written under the work folder), their head counts, a
/// description, and the frozen DINOv2 encoder's own file when the network has one (the Rust
/// side is pointed at it).
struct BenchWeights {
    weights: PathBuf,
    heads: (usize, usize),
    what: String,
    dinov2: Option<PathBuf>,
}

fn bench_weights(a: &BackboneArgs, dir: &Path, exe: &Path) -> Result<BenchWeights> {
    let mut dinov2: Option<PathBuf> = None;
    let (weights, heads, what) = match &a.weights {
        None => {
            let weights = dir.join("dens3r_full_random.safetensors");
            eprintln!("writing random full-size Dens3R weights to {} ...", weights.display());
            let st = Command::new(exe).args(["bench", "make-weights"]).arg(&weights).status()?;
            if !st.success() {
                bail!("could not make the benchmark weights");
            }
            (
                weights,
                (16, 12),
                "full-size Dens3R (ViT-L/16 encoder, 12-block ViT-B decoder, DPT 256), random weights".to_string(),
            )
        }
        Some(w) => {
            let given = (w != dens3r_backbone::default_model::NAME).then(|| PathBuf::from(w));
            let (file, config) = crate::model_args::resolve_model(given.as_deref(), a.config.as_deref())?;
            let model = crate::model_args::load_network(&file, config.as_deref(), false, Precision::F32)?;
            dinov2 = model.dinov2().map(|d| d.path.clone());
            let c = &model.config;
            let what = format!(
                "{} ({}x{} encoder, {}x{} decoder), trained weights",
                file.display(),
                c.enc_depth,
                c.enc_dim,
                c.dec_depth,
                c.dec_dim
            );
            let weights = dir.join("bench_weights_f32.safetensors");
            Weights::from_safetensors(&file)?.save_safetensors(&weights)?;
            (weights, (c.enc_heads, c.dec_heads), what)
        }
    };
    Ok(BenchWeights { weights, heads, what, dinov2 })
}

fn backbone(a: BackboneArgs) -> Result<()> {
    let threads = a.peer.threads();
    let sizes = parse_sizes(&a.sizes)?;
    let tmp = tempfile::tempdir()?;
    let dir = a.peer.workdir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    std::fs::create_dir_all(&dir)?;
    let exe = std::env::current_exe()?;
    let bw = bench_weights(&a, &dir, &exe)?;
    let heads_json = dir.join("bench_heads.json");
    let heads = serde_json::json!({"enc_num_heads": bw.heads.0, "dec_num_heads": bw.heads.1});
    std::fs::write(&heads_json, heads.to_string())?;
    let python = bench_python(a.peer.python.clone());
    let torch_ok = torch_peer_ready(&a, &python, bw.dinov2.is_some());
    print_backbone_header(&a, &bw.what, threads);
    let mut profiles = Vec::new();
    let mut gpu_names = Vec::new();
    let ctx = BackboneRun { a: &a, exe: &exe, dir: &dir, weights: &bw, heads_json: &heads_json, threads };
    for (w, h) in sizes {
        for &precision in &a.precision {
            let peer = torch_ok.then_some(python.as_path());
            profiles.push(backbone_row(&ctx, (w, h), precision, peer, &mut gpu_names)?);
        }
    }
    print_backbone_notes(&a, gpu_names);
    for (size, rust, torch) in profiles {
        print_profile(&size, &rust, &torch, a.gpu);
    }
    Ok(())
}

/// Whether the PyTorch peer can run (with --gpu: sees CUDA); says why not in one note.
fn torch_peer_ready(a: &BackboneArgs, python: &Path, dinov2: bool) -> bool {
    let probe = if a.gpu {
        "import torch, safetensors, numpy; assert torch.cuda.is_available()"
    } else {
        "import torch, safetensors, numpy"
    };
    let torch_ok = !dinov2 && Command::new(python).args(["-c", probe]).output().is_ok_and(|o| o.status.success());
    if dinov2 {
        eprintln!("note: bench/torch_dens3r.py has no DINOv2 encoder: Rust only for this network");
    } else if !torch_ok && a.gpu {
        eprintln!("note: {}'s torch sees no CUDA device: Rust only (no GPU peer to compare with)", python.display());
    } else if !torch_ok {
        eprintln!(
            "note: {} has no torch/safetensors/numpy: run scripts/bench-setup.sh for the PyTorch peer; Rust only",
            python.display()
        );
    }
    torch_ok
}

fn print_backbone_header(a: &BackboneArgs, what: &str, threads: usize) {
    let mem = if a.gpu { "dev MB" } else { "MB" };
    println!(
        "{what}, fastest of {}, {}",
        a.repeat,
        if a.gpu { "GPU".to_string() } else { format!("{threads} threads") }
    );
    println!(
        "  rust s / torch s: one pair forward of two images; mono s: Rust single-image prediction (forward_mono),"
    );
    println!("  torch/mono: the official single-image cost (the self-pair, = torch s) over it");
    if a.gpu {
        println!(
            "  dev MB: peak device memory (ours: what the allocator holds after the passes; PyTorch: max reserved)"
        );
    }
    println!(
        "{:<10} {:>5} {:>9} {:>9} {:>11} {:>9} {:>9} {:>10} {:>10} {:>11}",
        "size",
        "prec",
        "rust s",
        "torch s",
        "torch/rust",
        "mono s",
        "torch/mono",
        format!("rust {mem}"),
        format!("torch {mem}"),
        "max |diff|"
    );
}

/// What every row of `bench backbone` shares.
struct BackboneRun<'a> {
    a: &'a BackboneArgs,
    exe: &'a Path,
    dir: &'a Path,
    weights: &'a BenchWeights,
    heads_json: &'a Path,
    threads: usize,
}

/// One size and precision: ours in a child process, then the PyTorch peer (when `python`),
/// printed as a row; returns the two stage profiles.
fn backbone_row(
    ctx: &BackboneRun,
    (w, h): (usize, usize),
    precision: Precision,
    python: Option<&Path>,
    gpu_names: &mut Vec<String>,
) -> Result<(String, serde_json::Value, serde_json::Value)> {
    let (a, bw) = (ctx.a, ctx.weights);
    let r = child_json(
        Command::new(ctx.exe)
            .args(["bench", "run-rust"])
            .arg(&bw.weights)
            .args([w.to_string(), h.to_string()])
            .arg(ctx.dir)
            .arg(a.repeat.to_string())
            .arg("--config")
            .arg(ctx.heads_json)
            .args(["--precision", &precision.to_string()])
            .args(a.gpu.then_some("--gpu"))
            .envs(bw.dinov2.iter().map(|p| (dens3r_backbone::verify::DINOV2_ENV, p)))
            .env("RAYON_NUM_THREADS", ctx.threads.to_string()),
        "Rust",
    )?;
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let (rs, mono) = (num(&r["seconds"]), num(&r["mono_seconds"]));
    let rm = num(if a.gpu { &r["device_mb"] } else { &r["peak_rss_mb"] });
    if let Some(n) = r["device_name"].as_str() {
        gpu_names.push(format!("ours: {n}"));
    }
    let peer =
        TorchRun { size: (w, h), threads: ctx.threads, heads: bw.heads, repeat: a.repeat, gpu: a.gpu, precision };
    let t = match python {
        Some(py) => Some(torch_forward(py, &bw.weights, &peer, ctx.dir)?),
        None => None,
    };
    let tn = |k: &str| t.as_ref().map_or(f64::NAN, |t| num(&t[k]));
    let ts = tn("seconds");
    if let Some(n) = t.as_ref().and_then(|t| t["device_name"].as_str()) {
        gpu_names.push(format!("PyTorch: {n}"));
    }
    println!(
        "{:<10} {:>5} {:>9} {:>9} {:>11} {:>9} {:>9} {:>10} {:>10} {:>11}",
        format!("{w}x{h}"),
        precision.to_string(),
        cell(rs, 2),
        cell(ts, 2),
        ratio(ts / rs),
        cell(mono, 2),
        ratio(ts / mono),
        cell(rm, 0),
        cell(tn(if a.gpu { "peak_device_mb" } else { "peak_rss_mb" }), 0),
        sci(tn("max_abs_diff_pts3d"))
    );
    let tp = t.as_ref().map_or(serde_json::Value::Null, |t| t["profile"].clone());
    Ok((format!("{w}x{h} {precision}"), r["stages"].clone(), tp))
}

/// What the table's reader needs to know: bf16 on this CPU, the GPUs, lavapipe.
fn print_backbone_notes(a: &BackboneArgs, mut gpu_names: Vec<String>) {
    if !a.gpu && a.precision.contains(&Precision::BF16) {
        let how = if dens3r_backbone::cpu::bf16::native() {
            "on this CPU's AVX-512 BF16 (VDPBF16PS)"
        } else {
            "this CPU has no AVX-512 BF16, so through the f32 kernel: no faster"
        };
        println!(
            "  bf16 on the CPU: ours takes {} in bf16 (operands rounded, sums in f32; the rest f32; {how}), \
             PyTorch runs the whole model in bf16",
            dens3r_backbone::device::CPU_BF16_SCOPE
        );
    }
    gpu_names.sort();
    gpu_names.dedup();
    for n in &gpu_names {
        println!("  GPU {n}");
    }
    if gpu_names.iter().any(|n| n.contains("llvmpipe")) {
        println!("  note: llvmpipe is lavapipe, Mesa's Vulkan driver on the CPU: these timings are not a GPU's speed");
    }
}

/// The per-stage table: FLOPs (counted on the PyTorch side, 2 per multiply-add of matmuls,
/// convolutions and attention), each side's seconds and counted FLOPs per second (for the
/// Rust side an effective rate: its Winograd convolutions do fewer multiplies than counted).
fn print_profile(size: &str, rust: &serde_json::Value, torch: &serde_json::Value, gpu: bool) {
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let gemm = num(&torch["gemm_flops_per_s"]) / 1e9;
    println!("\nprofile {size}, one pair forward, stages run one after another (fastest of --repeat on each side)");
    println!("  GFLOP: counted by PyTorch's FlopCounterMode; GFLOP/s = GFLOP / seconds (Rust's Winograd 3x3");
    println!("  convolutions do fewer multiplies than counted, so its rate there is effective, not achieved)");
    let (n, what) = if gpu { (8192, "this GPU") } else { (2048, "this machine") };
    if gemm.is_finite() {
        println!("  {what}: GEMM {n}^3 in PyTorch at this precision {gemm:.0} GFLOP/s (same run)");
    } else {
        println!("  no PyTorch peer in this run: its FLOPs, times and GEMM rate are left out (-)");
    }
    println!("{:<44} {:>8} {:>8} {:>8} {:>8} {:>8}", "stage", "GFLOP", "rust s", "GFLOP/s", "torch s", "GFLOP/s");
    let row = |what: &str, f: f64, rs: f64, ts: f64| {
        println!(
            "{what:<44} {:>8} {:>8} {:>8} {:>8} {:>8}",
            cell(f, 1),
            cell(rs, 2),
            cell(f / rs, 0),
            cell(ts, 2),
            cell(f / ts, 0)
        );
    };
    let (mut tf, mut tr, mut tt) = (0.0, 0.0, 0.0);
    for (key, what) in STAGES {
        let (f, rs, ts) = (num(&torch["flops"][key]) / 1e9, num(&rust[key]), num(&torch["seconds"][key]));
        (tf, tr, tt) = (tf + f, tr + rs, tt + ts);
        row(what, f, rs, ts);
    }
    row("total", tf, tr, tt);
    // What the counted work allows: every FLOP at the large GEMM's rate.
    let floor = tf / gemm;
    if floor.is_finite() {
        println!(
            "  bound: every counted FLOP at that GEMM rate takes {floor:.2} s, {:.2}x PyTorch's {tt:.2} s: no faster \
             at this precision on {what} without less work (Rust is at {:.2}x, {:.0}% of the bound's rate)",
            tt / floor,
            tt / tr,
            100.0 * floor / tr
        );
    }
}

/// `show(v)`, or `-` when `v` was not measured (NaN).
fn or_dash(v: f64, show: impl Fn(f64) -> String) -> String {
    if v.is_finite() {
        show(v)
    } else {
        "-".into()
    }
}

/// `v` with `prec` decimals.
fn cell(v: f64, prec: usize) -> String {
    or_dash(v, |v| format!("{v:.prec$}"))
}

/// A ratio as `1.23x`.
fn ratio(v: f64) -> String {
    or_dash(v, |v| format!("{v:.2}x"))
}

/// Scientific notation.
fn sci(v: f64) -> String {
    or_dash(v, |v| format!("{v:.2e}"))
}

/// One PyTorch run's settings.
struct TorchRun {
    size: (usize, usize),
    threads: usize,
    heads: (usize, usize),
    repeat: usize,
    gpu: bool,
    precision: Precision,
}

/// PyTorch's pair forward on `dir`'s images (`bench/torch_dens3r.py`), its JSON: seconds, peak
/// RSS (and on CUDA peak device memory) in MB, the largest |difference| to our pointmap, the
/// profile.
fn torch_forward(python: &Path, weights: &Path, run: &TorchRun, dir: &Path) -> Result<serde_json::Value> {
    let TorchRun { size: (w, h), threads, heads, repeat, gpu, precision } = *run;
    let dtype = match precision {
        Precision::F32 => "float32",
        Precision::F16 => "float16",
        Precision::BF16 => "bfloat16",
    };
    child_json(
        Command::new(python)
            .arg("bench/torch_dens3r.py")
            .arg(weights)
            .args(["--size", &format!("{w}x{h}"), "--threads", &threads.to_string()])
            .args(["--heads", &format!("{},{}", heads.0, heads.1)])
            .args(["--repeat", &repeat.to_string(), "--profile"])
            .arg("--image")
            .arg(dir.join("img1.npy"))
            .arg("--image2")
            .arg(dir.join("img2.npy"))
            .arg("--compare")
            .arg(dir.join("pts3d.npy"))
            .args(["--device", if gpu { "cuda" } else { "cpu" }, "--dtype", dtype])
            .env("OMP_NUM_THREADS", threads.to_string()),
        "PyTorch",
    )
}
