//! The matching window's inner loop: a source image sampled bilinearly at the window's
//! positions under a homography, and the weighted sums NCC needs. AVX2 + FMA where the CPU has
//! them (8 samples a step, the four neighbours by gathers), else the same in scalar code.

use crate::image::Grey;
use glam::Vec3;

/// Window offsets and weights are padded to a multiple of this (padding weighs 0).
pub const LANES: usize = 8;

/// `(sum w v, sum w v^2, sum wr v)` over the window, where `v` is `img` sampled at
/// `H (x + du, y + dv, 1)`, `H`'s centre column `h0` and first two columns `c0`, `c1`.
/// All slices have the same length, a multiple of [`LANES`].
#[inline]
#[allow(clippy::too_many_arguments)]
pub fn window_sums(
    img: &Grey,
    h0: Vec3,
    c0: Vec3,
    c1: Vec3,
    du: &[f32],
    dv: &[f32],
    w: &[f32],
    wr: &[f32],
) -> [f32; 3] {
    debug_assert!(
        du.len().is_multiple_of(LANES) && dv.len() == du.len() && w.len() == du.len() && wr.len() == du.len()
    );
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA (checked above); the slices' lengths are equal
            // multiples of 8 (asserted by the caller's construction).
            return unsafe { avx2::window_sums(img, h0, c0, c1, du, dv, w, wr) };
        }
    }
    scalar(img, h0, c0, c1, du, dv, w, wr)
}

#[allow(clippy::too_many_arguments)]
fn scalar(img: &Grey, h0: Vec3, c0: Vec3, c1: Vec3, du: &[f32], dv: &[f32], w: &[f32], wr: &[f32]) -> [f32; 3] {
    let (mut s_ws, mut s_wss, mut s_wrs) = (0.0f32, 0.0f32, 0.0f32);
    for i in 0..du.len() {
        let (a, b) = (du[i], dv[i]);
        let q = h0 + c0 * a + c1 * b;
        let inv = 1.0 / q.z;
        let v = img.sample(q.x * inv, q.y * inv);
        s_ws += w[i] * v;
        s_wss += w[i] * v * v;
        s_wrs += wr[i] * v;
    }
    [s_ws, s_wss, s_wrs]
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn window_sums(
        img: &Grey,
        h0: Vec3,
        c0: Vec3,
        c1: Vec3,
        du: &[f32],
        dv: &[f32],
        w: &[f32],
        wr: &[f32],
    ) -> [f32; 3] {
        let (data, width, umax, vmax) = img.raw();
        let base = data.as_ptr();
        let set = |x: f32| _mm256_set1_ps(x);
        let (h0x, h0y, h0z) = (set(h0.x), set(h0.y), set(h0.z));
        let (c0x, c0y, c0z) = (set(c0.x), set(c0.y), set(c0.z));
        let (c1x, c1y, c1z) = (set(c1.x), set(c1.y), set(c1.z));
        let (zero, umax, vmax) = (_mm256_setzero_ps(), set(umax), set(vmax));
        let wi = _mm256_set1_epi32(width as i32);
        let one = _mm256_set1_epi32(1);
        let (mut acc_ws, mut acc_wss, mut acc_wrs) = (zero, zero, zero);
        let mut i = 0;
        while i < du.len() {
            let a = _mm256_loadu_ps(du.as_ptr().add(i));
            let b = _mm256_loadu_ps(dv.as_ptr().add(i));
            let qx = _mm256_fmadd_ps(c1x, b, _mm256_fmadd_ps(c0x, a, h0x));
            let qy = _mm256_fmadd_ps(c1y, b, _mm256_fmadd_ps(c0y, a, h0y));
            let qz = _mm256_fmadd_ps(c1z, b, _mm256_fmadd_ps(c0z, a, h0z));
            let inv = _mm256_div_ps(_mm256_set1_ps(1.0), qz);
            // max(x, 0) gives 0 for NaN (the second operand), so every index is in bounds.
            let u = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(qx, inv), zero), umax);
            let v = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(qy, inv), zero), vmax);
            let x0 = _mm256_cvttps_epi32(u);
            let y0 = _mm256_cvttps_epi32(v);
            let fx = _mm256_sub_ps(u, _mm256_cvtepi32_ps(x0));
            let fy = _mm256_sub_ps(v, _mm256_cvtepi32_ps(y0));
            let idx = _mm256_add_epi32(_mm256_mullo_epi32(y0, wi), x0);
            let idx_b = _mm256_add_epi32(idx, wi);
            let p00 = _mm256_i32gather_ps::<4>(base, idx);
            let p01 = _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(idx, one));
            let p10 = _mm256_i32gather_ps::<4>(base, idx_b);
            let p11 = _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(idx_b, one));
            let top = _mm256_fmadd_ps(fx, _mm256_sub_ps(p01, p00), p00);
            let bottom = _mm256_fmadd_ps(fx, _mm256_sub_ps(p11, p10), p10);
            let val = _mm256_fmadd_ps(fy, _mm256_sub_ps(bottom, top), top);
            let ww = _mm256_loadu_ps(w.as_ptr().add(i));
            let wv = _mm256_mul_ps(ww, val);
            acc_ws = _mm256_add_ps(acc_ws, wv);
            acc_wss = _mm256_fmadd_ps(wv, val, acc_wss);
            acc_wrs = _mm256_fmadd_ps(_mm256_loadu_ps(wr.as_ptr().add(i)), val, acc_wrs);
            i += LANES;
        }
        [hsum(acc_ws), hsum(acc_wss), hsum(acc_wrs)]
    }

    #[target_feature(enable = "avx2,fma")]
    unsafe fn hsum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        let s = _mm_add_ss(s, _mm_shuffle_ps::<0x55>(s, s));
        _mm_cvtss_f32(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_vector_kernel_matches_the_scalar_loop() {
        let (w, h) = (37, 23);
        let img = Grey::from_vec(w, h, (0..w * h).map(|i| ((i * 7919) % 101) as f32 / 100.0).collect());
        let n = 40;
        let du: Vec<f32> = (0..n).map(|i| (i % 7) as f32 - 3.0).collect();
        let dv: Vec<f32> = (0..n).map(|i| (i / 7) as f32 - 3.0).collect();
        let wt: Vec<f32> = (0..n).map(|i| if i < 36 { 0.5 + (i % 3) as f32 * 0.2 } else { 0.0 }).collect();
        let wr: Vec<f32> = (0..n).map(|i| if i < 36 { (i % 5) as f32 * 0.1 - 0.2 } else { 0.0 }).collect();
        // A homography with perspective, sampling partly outside the image (clamped).
        let h0 = Vec3::new(30.0, 12.0, 1.1);
        let c0 = Vec3::new(1.1, 0.1, 0.002);
        let c1 = Vec3::new(-0.2, 0.9, 0.001);
        let fast = window_sums(&img, h0, c0, c1, &du, &dv, &wt, &wr);
        let slow = scalar(&img, h0, c0, c1, &du, &dv, &wt, &wr);
        for k in 0..3 {
            assert!((fast[k] - slow[k]).abs() <= 1e-4 * slow[k].abs().max(1.0), "{fast:?} vs {slow:?}");
        }
    }
}
