//! Pictures of a scene's layers for people to look at (`viz/` of `dens3r predict`, the pages of
//! dens3r-viewer): depth on a colour ramp, normals in the official Dens3R colours (spec 3.3),
//! confidence in grey.

use dens3r_geom::{NormalConvention, Raster};
use glam::Vec3;
use image::{Rgb, RgbImage};

/// The official normal visualisation (spec 3.3) of the Dens3R saved convention, from normals in
/// the OpenCV camera frame: R = (nx+1)/2*255, G = (ny+1)/2*255, B = -nz*127+128, cast to uint8;
/// a camera-facing wall is (127, 127, 255).
pub fn normal_viz(n: &Raster<Vec3>) -> RgbImage {
    RgbImage::from_fn(n.width() as u32, n.height() as u32, |x, y| {
        let s = NormalConvention::Dens3rSaved.from_opencv(*n.get(x as usize, y as usize));
        let c = |v: f32| v.clamp(0.0, 255.0) as u8;
        Rgb([c((s.x + 1.0) / 2.0 * 255.0), c((s.y + 1.0) / 2.0 * 255.0), c(-s.z * 127.0 + 128.0)])
    })
}

/// Depth on a Spectral-like ramp between its 2nd and 85th percentiles (spec 3.3), near red to
/// far violet; invalid pixels (0, negative, NaN) black.
pub fn depth_viz(d: &Raster<f32>) -> RgbImage {
    let (lo, hi) = ramp_ends(d.data().iter().copied().filter(|x| *x > 0.0 && x.is_finite()).collect(), 0.02, 0.85);
    const RAMP: [[f32; 3]; 5] =
        [[158.0, 1.0, 66.0], [244.0, 109.0, 67.0], [255.0, 255.0, 191.0], [102.0, 194.0, 165.0], [94.0, 79.0, 162.0]];
    RgbImage::from_fn(d.width() as u32, d.height() as u32, |x, y| {
        let z = *d.get(x as usize, y as usize);
        if z.is_nan() || z <= 0.0 {
            return Rgb([0, 0, 0]);
        }
        let t = ((z - lo) / (hi - lo)).clamp(0.0, 1.0) * 4.0;
        let (i, f) = ((t.floor() as usize).min(3), t - t.floor().min(3.0));
        Rgb(std::array::from_fn(|k| (RAMP[i][k] + (RAMP[i + 1][k] - RAMP[i][k]) * f) as u8))
    })
}

/// Confidence on a log grey ramp between its 2nd and 98th percentiles (bright: confident);
/// invalid values (NaN, 0, negative) black.
pub fn conf_viz(c: &Raster<f32>) -> RgbImage {
    let (lo, hi) =
        ramp_ends(c.data().iter().copied().filter(|x| x.is_finite() && *x > 0.0).map(f32::ln).collect(), 0.02, 0.98);
    RgbImage::from_fn(c.width() as u32, c.height() as u32, |x, y| {
        let z = *c.get(x as usize, y as usize);
        if !(z.is_finite() && z > 0.0) {
            return Rgb([0, 0, 0]);
        }
        let g = (((z.ln() - lo) / (hi - lo)).clamp(0.0, 1.0) * 235.0 + 20.0) as u8;
        Rgb([g, g, g])
    })
}

/// The `p0` and `p1` percentiles of `values` (a ramp's ends; `p1`'s kept above `p0`'s), 0 for none.
fn ramp_ends(mut values: Vec<f32>, p0: f32, p1: f32) -> (f32, f32) {
    values.sort_by(f32::total_cmp);
    let q = |p: f32| values.get(((values.len().max(1) - 1) as f32 * p) as usize).copied().unwrap_or(0.0);
    (q(p0), q(p1).max(q(p0) + 1e-6))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The spec's formulas (section 3.3, cast to uint8): a camera-facing normal (OpenCV
    /// (0, 0, -1)) is (127, 127, 255); depth at the ramp's ends takes its end colours, invalid is
    /// black.
    #[test]
    fn colours_follow_the_spec() {
        let n = Raster::filled(2, 1, Vec3::new(0.0, 0.0, -1.0));
        assert_eq!(normal_viz(&n).get_pixel(0, 0).0, [127, 127, 255]);
        let d = Raster::from_vec(101, 1, (0..101).map(|i| if i == 0 { f32::NAN } else { i as f32 }).collect()).unwrap();
        let img = depth_viz(&d);
        assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(1, 0).0, [158, 1, 66], "nearest pixel below the 2nd percentile: the near end");
        assert_eq!(img.get_pixel(100, 0).0, [94, 79, 162], "farthest, above the 85th: the far end");
        // Confidence: e^0 .. e^4 over 101 pixels; the least confident dark, the most bright.
        let c =
            Raster::from_vec(101, 1, (0..101).map(|i| if i == 0 { 0.0 } else { (i as f32 / 25.0).exp() }).collect())
                .unwrap();
        let g = conf_viz(&c);
        assert_eq!(g.get_pixel(0, 0).0, [0, 0, 0], "invalid");
        assert_eq!(g.get_pixel(1, 0).0, [20, 20, 20]);
        assert_eq!(g.get_pixel(100, 0).0, [255, 255, 255]);
        assert!(g.get_pixel(50, 0).0[0] > 120 && g.get_pixel(50, 0).0[0] < 150, "the middle of the log range mid-grey");
    }
}
