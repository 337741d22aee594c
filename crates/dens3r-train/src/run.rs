//! A whole training run into a folder: `ckpt/` (parameters, moments, state; rerunning with
//! the same folder resumes), `log.jsonl` (one object per step, the total under `loss`),
//! `loss.png` (the curve) and, at the end, `model.safetensors` + `model.json` (official key
//! names and constructor keywords, read by `--weights W --config W.json`).

use crate::arch::config_json;
use crate::train::{Dataset, LogLine, TrainConfig, Trainer};
use crate::TrainError;
use burn::tensor::Device;
use dens3r_backbone::Params;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Files of a run folder.
pub struct RunPaths {
    /// Checkpoint folder.
    pub ckpt: PathBuf,
    /// JSONL log.
    pub log: PathBuf,
    /// Loss-curve picture.
    pub curve: PathBuf,
    /// Final weights.
    pub model: PathBuf,
    /// Their `config.json`.
    pub model_config: PathBuf,
}

impl RunPaths {
    /// The files under `dir`.
    pub fn new(dir: &Path) -> Self {
        Self {
            ckpt: dir.join("ckpt"),
            log: dir.join("log.jsonl"),
            curve: dir.join("loss.png"),
            model: dir.join("model.safetensors"),
            model_config: dir.join("model.json"),
        }
    }
}

/// Held-out scenes scored during a run.
pub struct Validation<'a> {
    /// The held-out pairs.
    pub data: &'a Dataset,
    /// Steps between validations (and after the last step).
    pub every: usize,
    /// Fixed batches per validation.
    pub batches: usize,
}

/// Runs (or resumes) training of `params` on `data` into `dir`, scoring `val` (if any) every
/// `val.every` steps into the log; `progress(step, total, line)` is called after each step.
/// Returns the trainer at the end.
pub fn run(
    dir: &Path,
    params: Params,
    data: &Dataset,
    config: &TrainConfig,
    device: Device,
    val: Option<&Validation>,
    progress: &mut dyn FnMut(usize, usize, &LogLine),
) -> Result<Trainer, TrainError> {
    let paths = RunPaths::new(dir);
    std::fs::create_dir_all(dir).map_err(|e| TrainError::file(dir, format!("cannot create ({e})")))?;
    let mut trainer = match Trainer::resume(&paths.ckpt, &params, config, device.clone())? {
        Some(t) => t,
        None => Trainer::new(params, config.clone(), device.clone())?,
    };
    // The log keeps exactly the steps the checkpoint holds (a killed run may have logged more).
    let mut lines = read_log(&paths.log)?;
    lines.truncate(trainer.step);
    write_log(&paths.log, &lines)?;
    let mut log = std::fs::OpenOptions::new()
        .append(true)
        .open(&paths.log)
        .map_err(|e| TrainError::file(&paths.log, format!("cannot append ({e})")))?;
    while trainer.step < config.steps {
        let batch = data.batch(config, trainer.params.config.patch, trainer.step, &device)?;
        let mut line = trainer.train_step(&batch)?;
        if let Some(v) = val.filter(|v| trainer.step.is_multiple_of(v.every.max(1)) || trainer.step == config.steps) {
            line.val = Some(crate::train::validate(&trainer.params, v.data, config, v.batches)?);
        }
        writeln!(log, "{}", serde_json::to_string(&line)?)
            .map_err(|e| TrainError::file(&paths.log, format!("cannot write ({e})")))?;
        progress(trainer.step, config.steps, &line);
        lines.push(line);
        if trainer.step.is_multiple_of(config.checkpoint_every) || trainer.step == config.steps {
            log.flush()?;
            trainer.save(&paths.ckpt)?;
            write_curve(&paths.curve, &lines)?;
        }
    }
    trainer.params.save(&paths.model)?;
    let cfg = serde_json::to_string_pretty(&config_json(&trainer.params.config))?;
    dens3r_io::write_atomic(&paths.model_config, |w| w.write_all(cfg.as_bytes()))?;
    write_curve(&paths.curve, &lines)?;
    Ok(trainer)
}

/// Loads a phase's training data and held-out data (if any) at its size.
pub type PhaseData<'a> = dyn FnMut((usize, usize)) -> Result<(Dataset, Option<Dataset>), TrainError> + 'a;

/// One resolution of a coarse-to-fine run: its settings (size, steps, learning rate) and the
/// run folder it trains into.
pub struct Phase {
    /// The phase's settings.
    pub config: TrainConfig,
    /// Its run folder (see [`run`]).
    pub dir: PathBuf,
}

/// Coarse to fine in one call (Dens3R trains at 512 then 1024): each phase trains from the
/// previous one's final weights, at its own size, into its own folder. A rerun passes
/// finished phases through (they resume at their last step) and resumes the unfinished one.
/// `load(size)` gives a phase's training data and held-out data at its size;
/// `progress(phase, step, total, line)` is called after each step.
#[allow(clippy::too_many_arguments)]
pub fn run_phases(
    phases: &[Phase],
    params: Params,
    load: &mut PhaseData,
    val_every: usize,
    val_batches: usize,
    device: Device,
    progress: &mut dyn FnMut(usize, usize, usize, &LogLine),
) -> Result<Trainer, TrainError> {
    let mut params = params;
    let mut last = None;
    for (k, phase) in phases.iter().enumerate() {
        let (data, held_out) = load(phase.config.size)?;
        let val = held_out.as_ref().map(|d| Validation { data: d, every: val_every, batches: val_batches });
        let t = run(&phase.dir, params, &data, &phase.config, device.clone(), val.as_ref(), &mut |s, n, l| {
            progress(k, s, n, l)
        })?;
        params = t.params.clone();
        last = Some(t);
    }
    last.ok_or_else(|| TrainError::invalid("no training phase given"))
}

/// The log's lines (none when absent).
pub fn read_log(path: &Path) -> Result<Vec<LogLine>, TrainError> {
    if !path.is_file() {
        return Ok(Vec::new());
    }
    let text = std::fs::read_to_string(path).map_err(|e| TrainError::file(path, format!("{e}")))?;
    // A line cut by a kill is dropped; everything before it parses.
    Ok(text.lines().map_while(|l| serde_json::from_str(l).ok()).collect())
}

fn write_log(path: &Path, lines: &[LogLine]) -> Result<(), TrainError> {
    let mut text = String::new();
    for l in lines {
        text += &serde_json::to_string(l)?;
        text.push('\n');
    }
    dens3r_io::write_atomic(path, |w| w.write_all(text.as_bytes()))?;
    Ok(())
}

/// The total loss per step as a PNG line plot (log scale, 640x360; red), held-out losses as
/// blue squares.
pub fn write_curve(path: &Path, lines: &[LogLine]) -> Result<(), TrainError> {
    let (w, h) = (640u32, 360u32);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let vals: Vec<f32> = lines.iter().map(|l| l.terms.loss).filter(|v| v.is_finite()).collect();
    if vals.len() >= 2 {
        // Losses can be negative (the -alpha ln c terms): plot ln(loss - min + 1e-3).
        let lo = vals.iter().copied().fold(f32::INFINITY, f32::min);
        let y: Vec<f32> = vals.iter().map(|v| (v - lo + 1e-3).ln()).collect();
        let (ymin, ymax) = y.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| (a.min(*v), b.max(*v)));
        let span = (ymax - ymin).max(1e-6);
        let (m, pw, ph) = (20.0, (w - 40) as f32, (h - 40) as f32);
        let at = |i: usize| {
            let x = m + pw * i as f32 / (y.len() - 1) as f32;
            let yy = m + ph * (1.0 - (y[i] - ymin) / span);
            (x, yy)
        };
        for i in 1..y.len() {
            let ((x0, y0), (x1, y1)) = (at(i - 1), at(i));
            let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
            for k in 0..=n {
                let t = k as f32 / n as f32;
                let (x, yy) = (x0 + (x1 - x0) * t, y0 + (y1 - y0) * t);
                img.put_pixel((x as u32).min(w - 1), (yy as u32).min(h - 1), image::Rgb([200, 40, 40]));
            }
        }
        // Held-out losses as blue squares on the same scale.
        for (i, l) in lines.iter().enumerate() {
            let Some(v) = l.val.as_ref().map(|v| v.loss).filter(|v| v.is_finite()) else { continue };
            let yv = ((v - lo).max(0.0) + 1e-3).ln();
            let x = m + pw * i as f32 / (lines.len() - 1).max(1) as f32;
            let yy = m + ph * (1.0 - ((yv - ymin) / span).clamp(0.0, 1.0));
            for dx in -2i32..=2 {
                for dy in -2i32..=2 {
                    let (px, py) = ((x as i32 + dx).clamp(0, w as i32 - 1), (yy as i32 + dy).clamp(0, h as i32 - 1));
                    img.put_pixel(px as u32, py as u32, image::Rgb([40, 80, 220]));
                }
            }
        }
        for x in 20..w - 20 {
            img.put_pixel(x, h - 20, image::Rgb([0, 0, 0]));
        }
        for yy in 20..h - 20 {
            img.put_pixel(20, yy, image::Rgb([0, 0, 0]));
        }
    }
    dens3r_io::write_atomic(path, |f| img.write_to(f, image::ImageFormat::Png).map_err(std::io::Error::other))
        .map_err(|e| TrainError::file(path, format!("{e}")))
}
