//! What a training run is asked to do: iterations, batch sizes, learning rate, loss weights
//! and depth supervision (recorded in checkpoints, so a resumed run checks it matches).

use crate::OptionError;
use serde::{Deserialize, Serialize};

/// How observed depth supervises the rendered distance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DepthMode {
    /// Depth is metric in the scene's frame (rendered scenes, aligned `dens3r reconstruct`
    /// output): L1 against it.
    Metric,
    /// Depth is known up to a per-image scale and shift (monocular predictions): MonoSDF's
    /// least-squares fit of the observed to the rendered distances per image and batch.
    ScaleShift,
    /// No depth term (colour, normals and eikonal only).
    Off,
}

/// Training options. Loss weights are in the normalised frame (the surface spans about 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainOptions {
    /// Iterations.
    pub iters: usize,
    /// Rays per batch.
    pub rays: usize,
    /// Frames the rays of one batch come from.
    pub frames_per_batch: usize,
    /// Samples per ray, inside occupied cells.
    pub samples: usize,
    /// Random points per batch for the eikonal term.
    pub eikonal_points: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Linear warm-up iterations.
    pub warmup: usize,
    /// Depth supervision.
    pub depth_mode: DepthMode,
    /// Depth L1 weight.
    pub w_depth: f32,
    /// Normal weight (L1 and angular terms each); 0 turns normals off.
    pub w_normal: f32,
    /// Eikonal weight.
    pub w_eikonal: f32,
    /// Opacity weight (rays with depth should end on the surface).
    pub w_opacity: f32,
    /// Colour L1 weight (needs a colour field).
    pub w_color: f32,
    /// Grid levels active at the start (coarse-to-fine); the rest unlock over the first 40%.
    pub start_levels: usize,
    /// Iterations spent fitting the TSDF of the scene before rendering (0 = no TSDF start).
    pub init_tsdf_iters: usize,
    /// Seed of everything random.
    pub seed: u64,
}

impl Default for TrainOptions {
    fn default() -> Self {
        Self {
            iters: 1000,
            rays: 1024,
            frames_per_batch: 4,
            samples: 32,
            eikonal_points: 1024,
            lr: 1e-2,
            warmup: 100,
            depth_mode: DepthMode::Metric,
            w_depth: 1.0,
            w_normal: 0.1,
            w_eikonal: 0.1,
            w_opacity: 0.1,
            w_color: 0.1,
            start_levels: 4,
            init_tsdf_iters: 0,
            seed: 0,
        }
    }
}

impl TrainOptions {
    /// Checks the numbers are usable.
    pub fn check(&self) -> Result<(), OptionError> {
        if self.rays == 0 || self.samples < 4 || self.frames_per_batch == 0 {
            return Err(OptionError(format!(
                "need rays > 0, samples >= 4 and frames per batch > 0 (got {}, {}, {})",
                self.rays, self.samples, self.frames_per_batch
            )));
        }
        if !(self.lr > 0.0 && self.lr < 1.0) {
            return Err(OptionError(format!("learning rate {} must be in (0, 1)", self.lr)));
        }
        let w = [self.w_depth, self.w_normal, self.w_eikonal, self.w_opacity, self.w_color];
        if w.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(OptionError(format!("loss weights must be finite and >= 0, got {w:?}")));
        }
        Ok(())
    }
}
