//! Times the backbone's building blocks on the flex backend (development aid).
use burn::tensor::{Device, Distribution, Tensor};
use dens3r_backbone::ops::{Conv, Linear};
use std::time::Instant;

#[global_allocator]
static ALLOC: dens3r_backbone::cpu::alloc::BlockCache = dens3r_backbone::cpu::alloc::BlockCache;

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
    let lin = Linear::new(w.clone(), None);
    let f = 2.0 * 768.0 * 1024.0 * 4096.0;
    time("linear 768x1024x4096 (seam)", f, || lin.forward(x.clone()).to_data());
    let x2 = x.clone().reshape([768, 1024]);
    let wt = Tensor::<2>::from_data(w.clone().transpose().to_data(), &d);
    time("matmul 2-D 768x1024x4096 (burn)", f, || x2.clone().matmul(wt.clone()).to_data());
    let img = Tensor::<4>::random([1, 256, 96, 128], Distribution::Normal(0.0, 1.0), &d);
    let conv = Conv::new(Tensor::random([256, 256, 3, 3], Distribution::Normal(0.0, 0.02), &d), None, 1, 1);
    time("conv3x3 256->256 @ 96x128", 2.0 * 96.0 * 128.0 * 256.0 * 256.0 * 9.0, || conv.forward(img.clone()).to_data());
    let q = Tensor::<4>::random([1, 16, 768, 64], Distribution::Normal(0.0, 1.0), &d);
    time("attention 16x768x64", 4.0 * 16.0 * 768.0 * 768.0 * 64.0, || {
        dens3r_backbone::ops::sdpa(q.clone(), q.clone(), q.clone(), false).to_data()
    });
    let a = Tensor::<4>::random([1, 256, 96, 128], Distribution::Normal(0.0, 1.0), &d);
    time("upsample2x 256 @ 96x128", 0.0, || dens3r_backbone::ops::upsample2x(a.clone()).to_data());
    let a2 = Tensor::<4>::random([1, 128, 192, 256], Distribution::Normal(0.0, 1.0), &d);
    time("upsample2x 128 @ 192x256", 0.0, || dens3r_backbone::ops::upsample2x(a2.clone()).to_data());
    let a3 = Tensor::<4>::random([1, 256, 192, 256], Distribution::Normal(0.0, 1.0), &d);
    let c1 = Conv::new(Tensor::random([256, 256, 1, 1], Distribution::Normal(0.0, 0.02), &d), None, 1, 0);
    time("conv1x1 256->256 @ 192x256", 2.0 * 192.0 * 256.0 * 256.0 * 256.0, || c1.forward(a3.clone()).to_data());
    let a4 = Tensor::<4>::random([1, 128, 384, 512], Distribution::Normal(0.0, 1.0), &d);
    let c2 = Conv::new(Tensor::random([32, 128, 3, 3], Distribution::Normal(0.0, 0.02), &d), None, 1, 1);
    time("conv3x3 128->32 @ 384x512", 2.0 * 384.0 * 512.0 * 128.0 * 32.0 * 9.0, || c2.forward(a4.clone()).to_data());
    time("relu 128 @ 384x512", 0.0, || dens3r_backbone::ops::relu(a4.clone()).to_data());
    time("add 256 @ 96x128", 0.0, || (a.clone() + a.clone()).to_data());
    let c3 = Conv::new(Tensor::random([128, 256, 3, 3], Distribution::Normal(0.0, 0.02), &d), None, 1, 1);
    time("conv3x3 256->128 @ 192x256", 2.0 * 192.0 * 256.0 * 128.0 * 256.0 * 9.0, || c3.forward(a3.clone()).to_data());
    let a5 = Tensor::<4>::random([1, 96, 24, 32], Distribution::Normal(0.0, 1.0), &d);
    let ct = dens3r_backbone::ops::ConvTranspose {
        weight: Tensor::random([96, 96, 4, 4], Distribution::Normal(0.0, 0.02), &d),
        bias: Tensor::zeros([96], &d),
        stride: 4,
    };
    time("convT4 96 @ 24x32", 2.0 * 768.0 * 96.0 * 96.0 * 16.0, || ct.forward(a5.clone()).to_data());
    let a6 = Tensor::<4>::random([1, 768, 12, 16], Distribution::Normal(0.0, 1.0), &d);
    let cd = Conv::new(Tensor::random([768, 768, 3, 3], Distribution::Normal(0.0, 0.02), &d), None, 2, 1);
    time("conv3x3 s2 768 @ 24x32", 2.0 * 192.0 * 768.0 * 768.0 * 9.0, || cd.forward(a6.clone()).to_data());
    let ln =
        dens3r_backbone::ops::LayerNorm { gamma: Tensor::ones([1024], &d), beta: Tensor::zeros([1024], &d), eps: 1e-6 };
    time("layernorm 768x1024", 768.0 * 1024.0 * 8.0, || ln.forward(x.clone()).to_data());
    let hdn = Tensor::<3>::random([1, 768, 4096], Distribution::Normal(0.0, 1.0), &d);
    time("gelu 768x4096", 0.0, || dens3r_backbone::ops::gelu(hdn.clone()).to_data());
    time("add 768x1024", 0.0, || (x.clone() + x.clone()).to_data());
    let pos = dens3r_backbone::ops::grid_positions(24, 32);
    let rope = dens3r_backbone::ops::Rope::new(&pos, 64, 100.0, dens3r_backbone::config::RopeScaling::Interpolated, &d);
    time("rope 16x768x64", 0.0, || rope.apply(q.clone()).to_data());
    let qkv = Tensor::<3>::random([1, 768, 3072], Distribution::Normal(0.0, 1.0), &d);
    time("split heads + swap 768x3072", 0.0, || {
        qkv.clone()
            .reshape([1, 768, 3, 16, 64])
            .permute([2, 0, 3, 1, 4])
            .narrow(0, 0, 1)
            .reshape([1, 16, 768, 64])
            .to_data()
    });
}
