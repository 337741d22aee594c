//! Validation metrics: confusion-matrix mIoU and pixel accuracy; AbsRel and delta < 1.25, with
//! the least-squares scale-and-shift alignment used for relative (affine-invariant) depth.

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
    /// Mean IoU over the classes present in the ground truth or the predictions.
    pub fn miou(&self) -> f64 {
        let mut sum = 0.0;
        let mut n = 0;
        for c in 0..self.k {
            let tp = self.counts[c * self.k + c] as f64;
            let row: u64 = self.counts[c * self.k..(c + 1) * self.k].iter().sum();
            let col: u64 = (0..self.k).map(|r| self.counts[r * self.k + c]).sum();
            let union = row as f64 + col as f64 - tp;
            if row > 0 {
                sum += tp / union;
                n += 1;
            }
        }
        if n == 0 {
            0.0
        } else {
            sum / n as f64
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

/// Sums for AbsRel (`mean |p - g| / g`) and delta1 (`max(p/g, g/p) < 1.25`) over valid pixels.
#[derive(Debug, Clone, Default)]
pub struct DepthStats {
    abs_rel: f64,
    delta1: f64,
    n: u64,
}

impl DepthStats {
    /// Adds predicted vs ground-truth depths (ground truth finite and > 0 counts).
    pub fn add(&mut self, pred: &[f32], gt: &[f32]) {
        for (&p, &g) in pred.iter().zip(gt) {
            if g.is_finite() && g > 0.0 && p.is_finite() && p > 0.0 {
                let (p, g) = (p as f64, g as f64);
                self.abs_rel += (p - g).abs() / g;
                self.delta1 += ((p / g).max(g / p) < 1.25) as u8 as f64;
                self.n += 1;
            }
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

/// `s * pred + t` with the least-squares scale and shift over valid pixels (ground truth finite
/// and > 0): how a relative (affine-invariant) depth prediction is scored. Unchanged when fewer
/// than two pixels are valid or the prediction is constant on them.
pub fn align_affine(pred: &[f32], gt: &[f32]) -> Vec<f32> {
    let (mut n, mut sp, mut sg, mut spp, mut spg) = (0f64, 0f64, 0f64, 0f64, 0f64);
    for (&p, &g) in pred.iter().zip(gt) {
        if g.is_finite() && g > 0.0 && p.is_finite() {
            let (p, g) = (p as f64, g as f64);
            n += 1.0;
            sp += p;
            sg += g;
            spp += p * p;
            spg += p * g;
        }
    }
    let det = n * spp - sp * sp;
    if n < 2.0 || det.abs() <= 1e-12 * n * spp.max(1e-300) {
        return pred.to_vec();
    }
    let s = (n * spg - sp * sg) / det;
    let t = (spp * sg - sp * spg) / det;
    pred.iter().map(|&p| (s * p as f64 + t) as f32).collect()
}
