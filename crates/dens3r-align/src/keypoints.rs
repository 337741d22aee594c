//! Classical keypoint matches, independent of the network: SIFT keypoints and descriptors
//! (crate `sift-features`, OpenCV-compatible) as RootSIFT, matched by mutual nearest
//! neighbours with Lowe's ratio test. `reconstruct` uses them to place pairs by their epipolar
//! geometry ([`crate::epipolar`]) when the network's own descriptors do not match.

use glam::DVec2;
use image::RgbImage;

/// One image's keypoints: positions (pixels, `(0, 0)` = the first pixel's centre, OpenCV's
/// convention) and unit-length RootSIFT descriptors, `DIM` per keypoint.
#[derive(Debug, Clone, Default)]
pub struct Keypoints {
    /// Keypoint positions, pixels.
    pub xy: Vec<DVec2>,
    /// `xy.len() * DIM` descriptor values, each descriptor of unit length.
    pub desc: Vec<f32>,
}

/// Descriptor length.
pub const DIM: usize = 128;

impl Keypoints {
    /// How many keypoints.
    pub fn len(&self) -> usize {
        self.xy.len()
    }
    /// True without keypoints.
    pub fn is_empty(&self) -> bool {
        self.xy.is_empty()
    }
}

/// SIFT keypoints of `img` (at most `max`, the strongest), with RootSIFT descriptors (L1
/// normalised, square-rooted: Euclidean distance between them compares as the Hellinger
/// kernel, which matches better than raw SIFT).
pub fn detect(img: &RgbImage, max: usize) -> Keypoints {
    detect_with_gain(img, max, 1.0)
}

/// [`detect`] with the difference-of-Gaussians scaled by `gain` before extrema are kept:
/// `gain` 2 halves the contrast threshold (OpenCV's 0.04 over 3 scales) to COLMAP's peak
/// threshold (0.02 / 3), which finds keypoints on the weak texture of walls and floors. The
/// descriptors are unchanged (they are normalised).
pub fn detect_with_gain(img: &RgbImage, max: usize, gain: f32) -> Keypoints {
    let gray = image::imageops::grayscale(img);
    let mut pre = sift_features::precompute_images::<sift_features::ImageprocProcessing>(&gray);
    if gain != 1.0 {
        pre.dog.iter_mut().for_each(|d| d.mapv_inplace(|v| v * gain));
    }
    let r = sift_features::sift_with_precomputed(&pre, Some(max));
    let mut out = Keypoints { xy: Vec::with_capacity(r.keypoints.len()), desc: Vec::new() };
    for (k, kp) in r.keypoints.iter().enumerate() {
        let d = r.descriptors.row(k);
        let l1: f32 = d.iter().map(|&v| v as f32).sum();
        if l1 <= 0.0 || !kp.x.is_finite() || !kp.y.is_finite() {
            continue;
        }
        out.xy.push(DVec2::new(kp.x as f64, kp.y as f64));
        out.desc.extend(d.iter().map(|&v| (v as f32 / l1).sqrt()));
    }
    out
}

/// Mutual nearest-neighbour matches `(index in a, index in b)` that pass Lowe's ratio test
/// (nearest distance under `ratio` times the second nearest, both ways).
pub fn match_mutual(a: &Keypoints, b: &Keypoints, ratio: f32) -> Vec<(usize, usize)> {
    if a.is_empty() || b.is_empty() {
        return Vec::new();
    }
    // Squared distances of unit vectors: 2 - 2 a.b; keep the two best both ways.
    let mut best_a = vec![(f32::INFINITY, f32::INFINITY, usize::MAX); a.len()];
    let mut best_b = vec![(f32::INFINITY, f32::INFINITY, usize::MAX); b.len()];
    let (n, m) = (a.len(), b.len());
    let mut dots = vec![0f32; n * m];
    crate::matching::dots_abt(&a.desc, &b.desc, DIM, &mut dots);
    for i in 0..n {
        for (j, &dot) in dots[i * m..(i + 1) * m].iter().enumerate() {
            let d = (2.0 - 2.0 * dot).max(0.0);
            for (slot, other) in [(&mut best_a[i], j), (&mut best_b[j], i)] {
                if d < slot.0 {
                    *slot = (d, slot.0, other);
                } else if d < slot.1 {
                    slot.1 = d;
                }
            }
        }
    }
    let r2 = ratio * ratio;
    best_a
        .iter()
        .enumerate()
        .filter(|&(i, &(d1, d2, j))| {
            j != usize::MAX && best_b[j].2 == i && d1 < r2 * d2 && best_b[j].0 < r2 * best_b[j].1
        })
        .map(|(i, &(_, _, j))| (i, j))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn photo(name: &str) -> RgbImage {
        let path = format!("{}/../../data-samples/photos/{name}", env!("CARGO_MANIFEST_DIR"));
        image::open(&path).expect("a bundled photo").to_rgb8()
    }

    /// The fraction of matches that land where the known warp puts them (within `tol` px).
    fn agreeing(a: &Keypoints, b: &Keypoints, m: &[(usize, usize)], warp: impl Fn(DVec2) -> DVec2, tol: f64) -> f64 {
        m.iter().filter(|&&(i, j)| (warp(a.xy[i]) - b.xy[j]).length() < tol).count() as f64 / m.len().max(1) as f64
    }

    /// Two overlapping crops of a real photo (scikit-image's chelsea), the second also shrunk to
    /// 3/4: the matches are many, and nearly all of them are where the crop offset and the
    /// scale put them.
    #[test]
    fn matches_follow_a_known_crop_and_scale() {
        let img = photo("chelsea.png");
        let (w, h) = (img.width() - 60, img.height() - 40);
        let a_img = image::imageops::crop_imm(&img, 0, 0, w, h).to_image();
        let b_img = image::imageops::crop_imm(&img, 37, 21, w, h).to_image();
        let (a, b) = (detect(&a_img, 4000), detect(&b_img, 4000));
        let m = match_mutual(&a, &b, 0.8);
        let shift = |p: DVec2| p - DVec2::new(37.0, 21.0);
        let ok = agreeing(&a, &b, &m, shift, 1.0);
        assert!(m.len() > 100 && ok > 0.95, "{} matches, {:.3} where the crop puts them", m.len(), ok);

        let small = image::imageops::resize(&b_img, w * 3 / 4, h * 3 / 4, image::imageops::FilterType::Triangle);
        let s = detect(&small, 4000);
        let m = match_mutual(&a, &s, 0.8);
        // Pixel centres: x_small + 0.5 = (x + 0.5) * 3/4.
        let scaled = |p: DVec2| (shift(p) + 0.5) * 0.75 - 0.5;
        let ok = agreeing(&a, &s, &m, scaled, 1.5);
        assert!(m.len() > 50 && ok > 0.9, "{} matches, {:.3} where crop and scale put them", m.len(), ok);
    }

    /// Unrelated photos (the cat and scikit-image's coffee cup) give few matches, and an empty
    /// set none.
    #[test]
    fn unrelated_images_barely_match() {
        let (a, b) = (detect(&photo("chelsea.png"), 4000), detect(&photo("coffee.png"), 4000));
        let m = match_mutual(&a, &b, 0.8);
        assert!(a.len() > 200 && m.len() * 20 < a.len(), "{} matches of {} keypoints", m.len(), a.len());
        assert!(match_mutual(&a, &Keypoints::default(), 0.8).is_empty());
    }
}
