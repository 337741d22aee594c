//! The optimisation shared by dens3r's trainers (heads on frozen features, the network
//! itself): one warm-up + cosine learning-rate schedule and one AdamW, on plain host buffers
//! (the parameters live on the host between steps, so the update needs no tensor library).

/// Linear warm-up over the first `warmup` fraction of `total` steps (at least one step), then
/// cosine decay to zero at the last step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WarmupCosine {
    /// Peak learning rate.
    pub lr: f32,
    /// Fraction of the steps spent warming up.
    pub warmup: f32,
    /// Steps in all.
    pub total: usize,
}

impl WarmupCosine {
    /// The learning rate of 0-based step `step`.
    pub fn at(&self, step: usize) -> f32 {
        let warm = ((self.warmup * self.total as f32) as usize).max(1);
        if step < warm {
            return self.lr * (step + 1) as f32 / warm as f32;
        }
        let t = (step - warm) as f32 / (self.total - warm).max(1) as f32;
        self.lr * 0.5 * (1.0 + (std::f32::consts::PI * t.min(1.0)).cos())
    }
}

/// AdamW: Adam's bias-corrected moments with decoupled weight decay (Loshchilov & Hutter),
/// as PyTorch's `torch.optim.AdamW` updates (`p -= lr * wd * p`, then the Adam step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamW {
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator epsilon.
    pub eps: f32,
    /// Decoupled weight decay (applied where the caller says a tensor decays).
    pub weight_decay: f32,
}

impl Default for AdamW {
    fn default() -> Self {
        Self { beta1: 0.9, beta2: 0.999, eps: 1e-8, weight_decay: 0.0 }
    }
}

impl AdamW {
    /// One update of `values` (with moments `m`, `v`) by the gradient `grad * scale` at 0-based
    /// step `step` and learning rate `lr`; `decay` applies the weight decay.
    #[allow(clippy::too_many_arguments)]
    pub fn update(
        &self,
        step: usize,
        lr: f32,
        values: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        grad: &[f32],
        scale: f32,
        decay: bool,
    ) {
        let (b1, b2) = (self.beta1, self.beta2);
        let t = (step + 1) as i32;
        let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        let wd = self.weight_decay;
        for j in 0..values.len() {
            let g = grad[j] * scale;
            m[j] = b1 * m[j] + (1.0 - b1) * g;
            v[j] = b2 * v[j] + (1.0 - b2) * g * g;
            if decay {
                values[j] -= lr * wd * values[j];
            }
            values[j] -= lr * (m[j] / c1) / ((v[j] / c2).sqrt() + self.eps);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Warm-up rises linearly to the peak, the cosine passes half the peak halfway through
    /// the decay and ends at zero, never rising after the warm-up.
    #[test]
    fn schedule_shape() {
        // 11 warm-up steps (0.1 * 111, floored), 100 decay steps.
        let s = WarmupCosine { lr: 1e-3, warmup: 0.1, total: 111 };
        assert!((s.at(0) - 1e-3 / 11.0).abs() < 1e-9 && (s.at(10) - 1e-3).abs() < 1e-9);
        assert!((s.at(11 + 50) - 5e-4).abs() < 1e-8, "{}", s.at(61));
        assert!(s.at(111).abs() < 1e-9 && s.at(110) < 1e-6);
        assert!((11..111).all(|k| s.at(k + 1) <= s.at(k)));
        assert_eq!(WarmupCosine { lr: 1.0, warmup: 0.0, total: 1 }.at(0), 1.0, "at least one warm-up step");
    }

    /// Adam's first step moves every coordinate by `lr` against its gradient's sign whatever
    /// the gradient's size; weight decay shrinks by `lr * wd` first; on a quadratic the
    /// iterates settle at the minimum.
    #[test]
    fn adamw_first_step_and_convergence() {
        let opt = AdamW { weight_decay: 0.5, ..Default::default() };
        let (mut x, mut m, mut v) = (vec![1.0f32, 1.0, -2.0], vec![0.0; 3], vec![0.0; 3]);
        opt.update(0, 0.01, &mut x, &mut m, &mut v, &[1e-3, -50.0, 2.0], 1.0, false);
        let want = [0.99, 1.01, -2.01];
        assert!(x.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5), "{x:?}");
        let (mut y, mut m, mut v) = (vec![2.0f32], vec![0.0], vec![0.0]);
        opt.update(0, 0.01, &mut y, &mut m, &mut v, &[1.0], 1.0, true);
        assert!((y[0] - (2.0 * (1.0 - 0.01 * 0.5) - 0.01)).abs() < 1e-6, "{y:?}");
        // f(x) = (x - 3)^2 from 0, no decay.
        let opt = AdamW::default();
        let (mut x, mut m, mut v) = (vec![0.0f32], vec![0.0], vec![0.0]);
        let s = WarmupCosine { lr: 0.1, warmup: 0.0, total: 2000 };
        for k in 0..2000 {
            let g = [2.0 * (x[0] - 3.0)];
            opt.update(k, s.at(k), &mut x, &mut m, &mut v, &g, 1.0, false);
        }
        assert!((x[0] - 3.0).abs() < 1e-3, "{}", x[0]);
    }
}
