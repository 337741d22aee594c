//! Times the backbone's building blocks on the flex backend (development aid).
use burn::tensor::{Device, Distribution, Tensor};
use dens3r_backbone::ops::{Conv, Linear};
use std::time::Instant;

fn time<T>(name: &str, flops: f64, mut f: impl FnMut() -> T) {
    let _ = f();
    let t = Instant::now();
    let n = 3;
    for _ in 0..n {
        let _ = f();
    }
    let s = t.elapsed().as_secs_f64() / n as f64;
    println!("{name:<40} {:>8.2} ms {:>8.1} GFLOP/s", s * 1e3, flops / s / 1e9);
}

fn main() {
    let d = Device::default();
    let x = Tensor::<3>::random([1, 768, 1024], Distribution::Normal(0.0, 1.0), &d);
    let w = Tensor::<2>::random([4096, 1024], Distribution::Normal(0.0, 0.02), &d);
    let lazy = Linear { weight: w.clone().transpose(), bias: None };
    let dense = Linear { weight: Tensor::from_data(w.clone().transpose().to_data(), &d), bias: None };
    let f = 2.0 * 768.0 * 1024.0 * 4096.0;
    time("linear 768x1024x4096 (transposed view)", f, || lazy.forward(x.clone()).to_data());
    time("linear 768x1024x4096 (contiguous)", f, || dense.forward(x.clone()).to_data());
    let x2 = x.clone().reshape([768, 1024]);
    let wt = dense.weight.clone();
    time("matmul 2-D 768x1024x4096", f, || x2.clone().matmul(wt.clone()).to_data());
    let img = Tensor::<4>::random([1, 256, 96, 128], Distribution::Normal(0.0, 1.0), &d);
    let conv = Conv::new(Tensor::random([256, 256, 3, 3], Distribution::Normal(0.0, 0.02), &d), None, 1, 1);
    time("conv3x3 256->256 @ 96x128", 2.0 * 96.0 * 128.0 * 256.0 * 256.0 * 9.0, || conv.forward(img.clone()).to_data());
    let q = Tensor::<4>::random([1, 16, 768, 64], Distribution::Normal(0.0, 1.0), &d);
    time("attention 16x768x64", 4.0 * 16.0 * 768.0 * 768.0 * 64.0, || {
        dens3r_backbone::ops::sdpa(q.clone(), q.clone(), q.clone()).to_data()
    });
    let ln =
        dens3r_backbone::ops::LayerNorm { gamma: Tensor::ones([1024], &d), beta: Tensor::zeros([1024], &d), eps: 1e-6 };
    time("layernorm 768x1024", 768.0 * 1024.0 * 8.0, || ln.forward(x.clone()).to_data());
}
