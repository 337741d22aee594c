//! Validation metrics: confusion-matrix mIoU and pixel accuracy; AbsRel and delta < 1.25
//! accumulated over images from dens3r-geom's depth metrics.

use dens3r_geom::metrics::{depth_metrics, DepthAlign};
use dens3r_geom::Raster;

/// A `K x K` confusion matrix (rows = ground truth).
#[derive(Debug, Clone)]
pub struct Confusion {
    /// Classes.
    pub k: usize,
    /// Counts, `k * k`.
    pub counts: Vec<u64>,
}

impl Confusion {
    /// Empty matrix for `k` classes.
    pub fn new(k: usize) -> Self {
        Self { k, counts: vec![0; k * k] }
    }
    /// Adds predicted vs ground-truth ids (ground truth >= k, e.g. 255, is skipped).
    pub fn add(&mut self, pred: &[u16], gt: &[u16]) {
        for (&p, &g) in pred.iter().zip(gt) {
            if (g as usize) < self.k && (p as usize) < self.k {
                self.counts[g as usize * self.k + p as usize] += 1;
            }
        }
    }
    /// IoU of class `c`; `None` when it is absent from the ground truth.
    pub fn iou(&self, c: usize) -> Option<f64> {
        let tp = self.counts[c * self.k + c] as f64;
        let row: u64 = self.counts[c * self.k..(c + 1) * self.k].iter().sum();
        let col: u64 = (0..self.k).map(|r| self.counts[r * self.k + c]).sum();
        (row > 0).then(|| tp / (row as f64 + col as f64 - tp))
    }
    /// `(name, IoU)` of each class present in the ground truth, in id order (`names` by id).
    pub fn class_ious(&self, names: &[String]) -> Vec<(String, f64)> {
        (0..self.k).filter_map(|c| self.iou(c).map(|v| (names[c].clone(), v))).collect()
    }
    /// Mean IoU over the classes present in the ground truth.
    pub fn miou(&self) -> f64 {
        let ious: Vec<f64> = (0..self.k).filter_map(|c| self.iou(c)).collect();
        if ious.is_empty() {
            0.0
        } else {
            ious.iter().sum::<f64>() / ious.len() as f64
        }
    }
    /// Fraction of labelled pixels predicted right.
    pub fn pixel_accuracy(&self) -> f64 {
        let tp: u64 = (0..self.k).map(|c| self.counts[c * self.k + c]).sum();
        let all: u64 = self.counts.iter().sum();
        if all == 0 {
            0.0
        } else {
            tp as f64 / all as f64
        }
    }
}

/// AbsRel and delta < 1.25 over images, pixel-weighted; each image is scored by
/// [`dens3r_geom::metrics::depth_metrics`] (pixels valid in both maps, optional alignment).
#[derive(Debug, Clone, Default)]
pub struct DepthStats {
    abs_rel: f64,
    delta1: f64,
    n: u64,
}

impl DepthStats {
    /// Adds one `w x h` image: `DepthAlign::None` for metric predictions, `ScaleShift` for
    /// relative (affine-invariant) ones. An image without valid pixels adds nothing.
    pub fn add(&mut self, pred: Vec<f32>, gt: &[f32], w: usize, h: usize, align: DepthAlign) {
        let (Ok(p), Ok(g)) = (Raster::from_vec(w, h, pred), Raster::from_vec(w, h, gt.to_vec())) else {
            return;
        };
        if let Ok(m) = depth_metrics(&p, &g, None, align) {
            self.abs_rel += m.abs_rel * m.count as f64;
            self.delta1 += m.delta[0] * m.count as f64;
            self.n += m.count as u64;
        }
    }
    /// AbsRel.
    pub fn abs_rel(&self) -> f64 {
        self.abs_rel / self.n.max(1) as f64
    }
    /// delta < 1.25.
    pub fn delta1(&self) -> f64 {
        self.delta1 / self.n.max(1) as f64
    }
}
