//! The optimisation shared by dens3r's trainers (heads on frozen features, the network itself,
//! the neural SDF) and its global alignment: one learning-rate schedule (linear warm-up, then a
//! cosine or linear decay) and one Adam(W), on plain host buffers in f32 or f64 (the
//! parameters live on the host between steps, so the update needs no tensor library).

use num_traits::Float;
use rayon::prelude::*;

/// How the learning rate falls after the warm-up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decay {
    /// `end + (peak - end) (1 + cos(pi t)) / 2`.
    Cosine,
    /// `peak + (end - peak) t`.
    Linear,
}

/// Linear warm-up over the first `warmup_steps` steps to `peak` (`peak (step + 1) /
/// warmup_steps`), then a decay to `end` at step `total`, `t` going from 0 after the warm-up
/// to 1 at the end (and held there past it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Schedule<F> {
    /// Peak learning rate.
    pub peak: F,
    /// Learning rate at the end.
    pub end: F,
    /// Warm-up steps (0: none).
    pub warmup_steps: usize,
    /// Steps in all.
    pub total: usize,
    /// Shape of the decay.
    pub decay: Decay,
}

impl<F: Float> Schedule<F> {
    /// The learning rate of 0-based step `step`.
    pub fn at(&self, step: usize) -> F {
        let f = |x: usize| F::from(x).expect("a step count");
        let warm = self.warmup_steps;
        if step < warm {
            return self.peak * f(step + 1) / f(warm);
        }
        let t = (f(step - warm) / f(self.total.saturating_sub(warm).max(1))).min(F::one());
        match self.decay {
            Decay::Cosine => {
                let pi = F::from(std::f64::consts::PI).expect("pi");
                let half = F::from(0.5).expect("0.5");
                self.end + (self.peak - self.end) * half * (F::one() + (pi * t).cos())
            }
            Decay::Linear => self.peak + (self.end - self.peak) * t,
        }
    }
}

/// Linear warm-up over the first `warmup` fraction of `total` steps (at least one step), then
/// cosine decay to zero at the last step: the trainers' [`Schedule`].
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
    /// The schedule this describes.
    pub fn schedule(&self) -> Schedule<f32> {
        let warmup_steps = ((self.warmup * self.total as f32) as usize).max(1);
        Schedule { peak: self.lr, end: 0.0, warmup_steps, total: self.total, decay: Decay::Cosine }
    }

    /// The learning rate of 0-based step `step`.
    pub fn at(&self, step: usize) -> f32 {
        self.schedule().at(step)
    }
}

/// Where one update stands: its 0-based step, its learning rate and the factor the gradient is
/// multiplied by first (1: none; a loss scale to undo, or a mean over a batch).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct At<F> {
    /// 0-based step (the bias corrections use `step + 1`).
    pub step: usize,
    /// Learning rate.
    pub lr: F,
    /// Factor applied to the gradient.
    pub grad_scale: F,
}

impl<F: Float> At<F> {
    /// Step `step` at learning rate `lr`, the gradient as it is.
    pub fn new(step: usize, lr: F) -> Self {
        Self { step, lr, grad_scale: F::one() }
    }

    /// The same with the gradient multiplied by `grad_scale`.
    pub fn scaled(self, grad_scale: F) -> Self {
        Self { grad_scale, ..self }
    }
}

/// Global L2 norm of a step's gradients (`None`: a tensor without one): per-tensor sums in
/// parallel, added in tensor order, so every run gives the same bits.
pub fn global_norm(grads: &[Option<Vec<f32>>]) -> f64 {
    use rayon::prelude::*;
    let sums: Vec<f64> = grads
        .par_iter()
        .map(|g| g.as_ref().map_or(0.0, |g| g.iter().map(|&x| f64::from(x) * f64::from(x)).sum()))
        .collect();
    sums.iter().sum::<f64>().sqrt()
}

/// Runs `f` on each shard of a step, as many side by side as rayon has threads, and hands the
/// results to `take` in shard order (so sums over them do not depend on the thread count, and
/// no more shards are alive at once than run). The first error `take` returns stops it: no
/// further shards run.
pub fn side_by_side<T: Sync, R: Send, E>(
    shards: &[T],
    f: impl Fn(&T) -> R + Sync,
    mut take: impl FnMut(R) -> Result<(), E>,
) -> Result<(), E> {
    use rayon::prelude::*;
    for part in shards.chunks(rayon::current_num_threads().max(1)) {
        let done: Vec<R> = part.par_iter().map(&f).collect();
        done.into_iter().try_for_each(&mut take)?;
    }
    Ok(())
}

/// Adds one shard's gradients (`None`: a tensor without one) into a batch's running sum,
/// tensor by tensor; a tensor with a gradient in only some shards gets theirs. Shards added in
/// a fixed order give the same bits however many ran at once.
pub fn add_gradients(sum: &mut [Option<Vec<f32>>], shard: Vec<Option<Vec<f32>>>) {
    use rayon::prelude::*;
    assert_eq!(sum.len(), shard.len(), "gradient lists of different networks");
    sum.par_iter_mut().zip(shard).for_each(|(acc, g)| match (acc.as_mut(), g) {
        (Some(a), Some(g)) => a.iter_mut().zip(g).for_each(|(a, b)| *a += b),
        (None, g) => *acc = g,
        (Some(_), None) => {}
    });
}

/// The factor that brings a gradient of global norm `norm` down to `max` (as PyTorch's
/// `clip_grad_norm_`): 1 when it is within, when there is no limit, or when the norm is not
/// finite (left to show in the loss).
pub fn clip_scale(norm: f64, max: Option<f32>) -> f32 {
    match max {
        Some(m) if norm.is_finite() && norm > f64::from(m) => (f64::from(m) / norm) as f32,
        _ => 1.0,
    }
}

/// Adam(W): Adam's bias-corrected moments with decoupled weight decay (Loshchilov & Hutter),
/// as PyTorch's `torch.optim.AdamW` updates (`p -= lr * wd * p`, then the Adam step); with
/// `weight_decay` 0 it is Adam.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamW<F = f32> {
    /// First-moment decay.
    pub beta1: F,
    /// Second-moment decay.
    pub beta2: F,
    /// Denominator epsilon.
    pub eps: F,
    /// Decoupled weight decay (applied where the caller says a tensor decays).
    pub weight_decay: F,
}

impl<F: Float> Default for AdamW<F> {
    fn default() -> Self {
        let c = |x: f64| F::from(x).expect("a constant");
        Self { beta1: c(0.9), beta2: c(0.999), eps: c(1e-8), weight_decay: F::zero() }
    }
}

impl<F: Float + Send + Sync> AdamW<F> {
    /// The bias corrections `(1 - beta1^t, 1 - beta2^t)` of 0-based step `step` (`t = step +
    /// 1`), for updates done elsewhere (a device's tensors).
    pub fn bias_corrections(&self, step: usize) -> (F, F) {
        let t = step as i32 + 1;
        (F::one() - self.beta1.powi(t), F::one() - self.beta2.powi(t))
    }

    /// Updates the moments `m`, `v` by the gradient at `at` and writes each coordinate's step
    /// (to subtract, learning rate included) into `out`; for parameters not updated by
    /// subtraction (rotations on their manifold).
    pub fn steps(&self, at: At<F>, m: &mut [F], v: &mut [F], grad: &[F], out: &mut [F]) {
        let c = self.bias_corrections(at.step);
        for j in 0..grad.len() {
            out[j] = self.moment_step(c, at.lr, &mut m[j], &mut v[j], grad[j] * at.grad_scale);
        }
    }

    /// One coordinate: its moments updated by gradient `g`, and its Adam step.
    #[inline]
    fn moment_step(&self, (c1, c2): (F, F), lr: F, m: &mut F, v: &mut F, g: F) -> F {
        let (b1, b2) = (self.beta1, self.beta2);
        *m = b1 * *m + (F::one() - b1) * g;
        *v = b2 * *v + (F::one() - b2) * g * g;
        lr * (*m / c1) / ((*v / c2).sqrt() + self.eps)
    }

    /// One update of `values` (with moments `m`, `v`) by the gradient `grad` at `at`; `decay`
    /// applies the weight decay.
    pub fn update(&self, at: At<F>, values: &mut [F], m: &mut [F], v: &mut [F], grad: &[F], decay: bool) {
        let c = self.bias_corrections(at.step);
        let wd = self.weight_decay;
        for j in 0..values.len() {
            let s = self.moment_step(c, at.lr, &mut m[j], &mut v[j], grad[j] * at.grad_scale);
            if decay {
                values[j] = values[j] - at.lr * wd * values[j];
            }
            values[j] = values[j] - s;
        }
    }

    /// [`AdamW::update`] over rayon's threads, in blocks (the same numbers: each coordinate is
    /// updated alone); for large buffers such as a hash-grid table.
    pub fn update_par(&self, at: At<F>, values: &mut [F], m: &mut [F], v: &mut [F], grad: &[F], decay: bool) {
        const BLOCK: usize = 1 << 14;
        values
            .par_chunks_mut(BLOCK)
            .zip(m.par_chunks_mut(BLOCK))
            .zip(v.par_chunks_mut(BLOCK))
            .zip(grad.par_chunks(BLOCK))
            .for_each(|(((x, m), v), g)| self.update(at, x, m, v, g, decay));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn side_by_side_hands_results_over_in_order_and_stops_at_the_first_error() {
        // Two threads: shards run in pairs; shard 3 fails, so the pair holding it is the last
        // to run (shards 4-9 never start) and `take` sees 0..=3 in order.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let ran = std::sync::atomic::AtomicUsize::new(0);
        let mut seen = Vec::new();
        let shards: Vec<usize> = (0..10).collect();
        let out = pool.install(|| {
            side_by_side(
                &shards,
                |&i| {
                    ran.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    i * 10
                },
                |r| {
                    seen.push(r);
                    if r == 30 {
                        Err(r)
                    } else {
                        Ok(())
                    }
                },
            )
        });
        assert_eq!(out, Err(30));
        assert_eq!(seen, [0, 10, 20, 30]);
        assert_eq!(ran.into_inner(), 4);
        let all = pool.install(|| side_by_side(&shards, |&i| i, |_| Ok::<(), ()>(())));
        assert_eq!(all, Ok(()));
    }

    #[test]
    fn clipping_scales_long_gradients_down_to_the_limit_only() {
        // A gradient of norm 5 against a limit of 1: scaled by 1/5; within it or unlimited: as is.
        assert_eq!(clip_scale(5.0, Some(1.0)), 0.2);
        assert_eq!(clip_scale(0.5, Some(1.0)), 1.0);
        assert_eq!(clip_scale(5.0, None), 1.0);
        assert_eq!(clip_scale(f64::NAN, Some(1.0)), 1.0);
        // Tensors (3, 4) and (12) with one absent: norm 13.
        assert_eq!(global_norm(&[Some(vec![3.0, 4.0]), None, Some(vec![12.0])]), 13.0);
    }

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
        opt.update(At::new(0, 0.01), &mut x, &mut m, &mut v, &[1e-3, -50.0, 2.0], false);
        let want = [0.99, 1.01, -2.01];
        assert!(x.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5), "{x:?}");
        let (mut y, mut m, mut v) = (vec![2.0f32], vec![0.0], vec![0.0]);
        opt.update(At::new(0, 0.01), &mut y, &mut m, &mut v, &[1.0], true);
        assert!((y[0] - (2.0 * (1.0 - 0.01 * 0.5) - 0.01)).abs() < 1e-6, "{y:?}");
        // f(x) = (x - 3)^2 from 0, no decay.
        let opt = AdamW::default();
        let (mut x, mut m, mut v) = (vec![0.0f32], vec![0.0], vec![0.0]);
        let s = WarmupCosine { lr: 0.1, warmup: 0.0, total: 2000 };
        for k in 0..2000 {
            let g = [2.0 * (x[0] - 3.0)];
            opt.update(At::new(k, s.at(k)), &mut x, &mut m, &mut v, &g, false);
        }
        assert!((x[0] - 3.0).abs() < 1e-3, "{}", x[0]);
    }

    /// The f64 schedule of global alignment: no warm-up, linear or cosine from the peak to the
    /// end, held at the end past the last step.
    #[test]
    fn linear_and_cosine_decays() {
        let lin = Schedule { peak: 0.01f64, end: 1e-6, warmup_steps: 0, total: 300, decay: Decay::Linear };
        assert_eq!(lin.at(0), 0.01);
        assert!((lin.at(150) - (0.01 + 1e-6) / 2.0).abs() < 1e-15);
        assert!((lin.at(300) - 1e-6).abs() < 1e-15 && lin.at(1000) == lin.at(300));
        let cos = Schedule { decay: Decay::Cosine, ..lin };
        assert_eq!(cos.at(0), 0.01);
        assert!((cos.at(150) - (0.01 + 1e-6) / 2.0).abs() < 1e-15);
        assert!((cos.at(75) - (1e-6 + (0.01 - 1e-6) * (1.0 + 0.5f64.sqrt()) / 2.0)).abs() < 1e-15);
        assert!((cos.at(300) - 1e-6).abs() < 1e-18);
    }

    /// `steps` gives what `update` subtracts, and the parallel update is the serial one, bit
    /// for bit.
    #[test]
    fn steps_and_parallel_update_agree_with_update() {
        let n = 100_003;
        let g: Vec<f32> = (0..n).map(|i| ((i as f32) * 0.618).sin()).collect();
        let x0: Vec<f32> = (0..n).map(|i| ((i as f32) * 0.377).cos()).collect();
        let opt = AdamW::<f32> { weight_decay: 0.1, ..Default::default() };
        let run = |par: bool| {
            let (mut x, mut m, mut v) = (x0.clone(), vec![0.1f32; n], vec![0.2f32; n]);
            for step in 0..3 {
                if par {
                    opt.update_par(At::new(step, 1e-3).scaled(0.5), &mut x, &mut m, &mut v, &g, true);
                } else {
                    opt.update(At::new(step, 1e-3).scaled(0.5), &mut x, &mut m, &mut v, &g, true);
                }
            }
            x
        };
        assert!(run(true).iter().zip(run(false)).all(|(a, b)| a.to_bits() == b.to_bits()));
        let opt = AdamW::<f64>::default();
        let g: Vec<f64> = vec![0.3, -2.0, 1e-4];
        let (mut x, mut m, mut v) = (vec![1.0f64, 2.0, 3.0], vec![0.0; 3], vec![0.0; 3]);
        opt.update(At::new(0, 0.01), &mut x, &mut m, &mut v, &g, false);
        let (mut m2, mut v2, mut out) = (vec![0.0; 3], vec![0.0; 3], vec![0.0; 3]);
        opt.steps(At::new(0, 0.01), &mut m2, &mut v2, &g, &mut out);
        assert_eq!(x, vec![1.0 - out[0], 2.0 - out[1], 3.0 - out[2]]);
        assert_eq!((m, v), (m2, v2));
    }
}
