use std::time::Instant;
#[global_allocator]
static ALLOC: dens3r_backbone::cpu::alloc::BlockCache = dens3r_backbone::cpu::alloc::BlockCache;
fn main() {
    let (cin, cout, h, w) = (128usize, 32usize, 384usize, 512usize);
    let wt: Vec<f32> = (0..cout * cin * 9).map(|i| ((i * 7919) % 1000) as f32 / 1e4 - 0.05).collect();
    let x: Vec<f32> = (0..cin * h * w).map(|i| ((i * 31) % 997) as f32 / 997.0 - 0.5).collect();
    let k = dens3r_backbone::cpu::winograd::WinogradKernel::new(&wt, cout, cin);
    for _ in 0..4 {
        let t = Instant::now();
        let y = k.forward(&x, h, w, None);
        println!("winograd 128->32 @384x512 {:.1} ms ({})", t.elapsed().as_secs_f64() * 1e3, y.len());
    }
    let taps = dens3r_backbone::cpu::conv::taps_from_weight(&wt, cout, cin);
    for _ in 0..3 {
        let t = Instant::now();
        let y = dens3r_backbone::cpu::conv::conv3x3_shifted(&x, &taps, None, cin, cout, h, w);
        println!("shifted {:.1} ms ({})", t.elapsed().as_secs_f64() * 1e3, y.len());
    }
    let small: Vec<f32> = (0..cin * h / 2 * w / 2).map(|i| ((i * 31) % 997) as f32 / 997.0 - 0.5).collect();
    for _ in 0..3 {
        let t = Instant::now();
        let y = dens3r_backbone::cpu::resample::upsample2x(&small, cin, h / 2, w / 2);
        println!("upsample {:.1} ms ({})", t.elapsed().as_secs_f64() * 1e3, y.len());
    }
}
