//! Single-image and pair prediction (spec section 2 "Single image" and 3.2), mapped back to
//! the un-rotated image frame, optionally at the original resolution, in our conventions.

use crate::model::{Dens3r, Features, HeadOutputs, Predictions, ViewFeatures, ViewPrediction};
use crate::preprocess::{preprocess, rescale_to_original, rotate_map_clockwise, unrotate_vector, PrepInfo, Prepared};
use crate::BackboneError;
use burn::tensor::Tensor;
use dens3r_geom::{NormalConvention, Raster, Vec3};
use image::{DynamicImage, RgbImage};

/// Resolution of the returned maps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Resolution {
    /// The network input (what the official code saves).
    #[default]
    Network,
    /// The original image size, through `rescale_to_orig` (edge padding + nearest neighbour).
    Original,
}

/// What one view yields, in the image's own orientation.
#[derive(Debug, Clone)]
pub struct ViewMaps {
    /// The network input as RGB (rotated back if the image was portrait); at
    /// [`Resolution::Original`] it is resampled the same way as the maps, so callers that
    /// have the original image may use that instead.
    pub rgb: RgbImage,
    /// Pointmap in the OpenCV frame of camera `frame` (model units).
    pub points: Raster<Vec3>,
    /// z of `points`: a depth map when `frame` is this view's own camera.
    pub depth: Raster<f32>,
    /// Unit normals in this view's OpenCV camera frame, facing the camera.
    pub normals: Option<Raster<Vec3>>,
    /// Confidence (`1 + exp(x)`).
    pub conf: Option<Raster<f32>>,
    /// Matching descriptors (MASt3R / Dens3R descriptor head), unit norm per pixel.
    pub desc: Option<DescriptorMap>,
    /// Descriptor confidence (the model's own, else a copy of `conf`).
    pub desc_conf: Option<Raster<f32>>,
    /// Index of the camera (0 = first view of the pair) whose frame `points` are in.
    pub frame: usize,
    /// How the image was preprocessed.
    pub info: PrepInfo,
}

/// A dense descriptor map: `dim` floats per pixel, row-major over `width x height`.
#[derive(Debug, Clone, PartialEq)]
pub struct DescriptorMap {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Floats per pixel (24 for Dens3R and MASt3R).
    pub dim: usize,
    /// `width * height * dim` values.
    pub data: Vec<f32>,
}

/// The single-image result (view 1 of the self-pair).
pub type MonoPrediction = ViewMaps;

fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.to_data().convert::<f32>().try_to_vec::<f32>().expect("float tensor")
}

/// An `(H, W, C)` network-frame map in the image's own orientation (rotated back if the image
/// was portrait) and at the requested resolution; returns it with its `(H, W)`. The same
/// mapping as the predicted maps, for maps of other heads run on the same input.
pub fn to_image_grid<T: Copy>(
    flat: Vec<T>,
    c: usize,
    (h, w): (usize, usize),
    info: &PrepInfo,
    res: Resolution,
) -> (Vec<T>, usize, usize) {
    let (flat, hh, ww) = if info.rotated { rotate_map_clockwise(&flat, h, w, c) } else { (flat, h, w) };
    match res {
        Resolution::Network => (flat, hh, ww),
        Resolution::Original => rescale_to_original(&flat, info, c),
    }
}

/// Maps one view's raw predictions back: the portrait rotation of this view's pixel grid,
/// then the resolution (the official order), then the rotation of the vectors' frame (`frame_rotated`: the frame
/// camera's image was rotated).
fn view_maps(v: &ViewPrediction, prep: &Prepared, frame: usize, frame_rotated: bool, res: Resolution) -> ViewMaps {
    let [_, h, w, _] = v.pts3d.dims();
    let rotated = prep.info.rotated;
    let grid = |flat: Vec<f32>, c: usize| to_image_grid(flat, c, (h, w), &prep.info, res);
    let vec_map = |flat: Vec<f32>, to_cv: &dyn Fn([f32; 3]) -> [f32; 3], vec_rotated: bool| -> Raster<Vec3> {
        let (flat, hh, ww) = grid(flat, 3);
        let v: Vec<Vec3> = flat
            .chunks_exact(3)
            .map(|c| {
                let p = to_cv([c[0], c[1], c[2]]);
                Vec3::from_array(if vec_rotated { unrotate_vector(p) } else { p })
            })
            .collect();
        Raster::from_vec(ww, hh, v).expect("sizes follow the tensor")
    };
    let scalar_map = |flat: Vec<f32>| -> Raster<f32> {
        let (flat, hh, ww) = grid(flat, 1);
        Raster::from_vec(ww, hh, flat).expect("sizes follow the tensor")
    };
    let points = vec_map(values(&v.pts3d), &|p| p, frame_rotated);
    let raw = NormalConvention::Dens3rRaw;
    let normals =
        v.normal.as_ref().map(|n| vec_map(values(n), &|c| raw.to_opencv(Vec3::from_array(c)).to_array(), rotated));
    let conf = v.conf.as_ref().map(|c| scalar_map(values(c)));
    let desc = v.desc.as_ref().map(|d| {
        let dim = d.dims()[3];
        let (data, height, width) = grid(values(d), dim);
        DescriptorMap { width, height, dim, data }
    });
    let desc_conf = v.desc_conf.as_ref().map(|c| scalar_map(values(c)));
    let depth = points.map(|p| if p.is_finite() && p.z > 0.0 { p.z } else { 0.0 });
    let (rgb, _, _) = to_image_grid(prep.rgb.as_raw().clone(), 3, (h, w), &prep.info, res);
    let rgb = RgbImage::from_raw(points.width() as u32, points.height() as u32, rgb).expect("sizes follow the maps");
    ViewMaps { rgb, points, depth, normals, conf, desc, desc_conf, frame, info: prep.info.clone() }
}

/// Runs the self-pair and reads view 1 (`pred1`), as the official pipeline does, with the
/// optional outputs in `want` (the descriptor head costs about as much as the point head: ask
/// for it only when descriptors are used).
pub fn predict_mono(model: &Dens3r, prep: &Prepared, res: Resolution, want: HeadOutputs) -> MonoPrediction {
    predict_mono_features(model, prep, res, want).0
}

/// [`predict_mono`] that also returns view 1's backbone features (network frame), so trained
/// heads can run on the same pass.
pub fn predict_mono_features(
    model: &Dens3r,
    prep: &Prepared,
    res: Resolution,
    want: HeadOutputs,
) -> (MonoPrediction, ViewFeatures) {
    let f = model.encode_self(prep.tensor(model.device()));
    let [v, _] = f.views;
    let pred = model.mono_heads_with(&v, want);
    (view_maps(&pred, prep, 0, prep.info.rotated, res), v)
}

/// Runs the pair `(first, second)`: both pointmaps in the first camera's frame (`pred1`,
/// `pred2.pts3d_in_other_view`), each view's normals in its own camera frame.
pub fn predict_pair(model: &Dens3r, first: &Prepared, second: &Prepared, res: Resolution) -> [ViewMaps; 2] {
    predict_pair_encoded(model, (first, &encode(model, first)), (second, &encode(model, second)), res)
}

/// An image's encoder tokens and patch grid: the siamese encoder's output, the same in every
/// pair the image is in.
#[derive(Debug, Clone)]
pub struct Encoded {
    tokens: Tensor<3>,
    grid: (usize, usize),
}

impl Encoded {
    /// The image as one global descriptor for retrieval (which photos to pair): its encoder
    /// tokens, each scaled to unit length, averaged (what the image holds overall) and
    /// generalised-mean pooled with exponent 3 per channel (its strongest responses, as GeM
    /// pooling does), the two concatenated.
    pub fn global_descriptor(&self) -> Vec<f32> {
        let [_, t, c] = self.tokens.dims();
        let data = values(&self.tokens);
        let mut mean = vec![0f64; c];
        let mut gem = vec![0f64; c];
        for tok in data.chunks_exact(c).take(t) {
            let norm = tok.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            for ((m, g), &v) in mean.iter_mut().zip(&mut gem).zip(tok) {
                let u = (v / norm) as f64;
                *m += u;
                *g += u.abs().powi(3);
            }
        }
        let t = t.max(1) as f64;
        mean.iter().map(|m| m / t).chain(gem.iter().map(|g| (g / t).cbrt())).map(|v| v as f32).collect()
    }
}

/// Runs the encoder on one preprocessed image.
pub fn encode(model: &Dens3r, prep: &Prepared) -> Encoded {
    let (tokens, grid) = model.encode_image(prep.tensor(model.device()));
    Encoded { tokens, grid }
}

/// [`predict_pair`] from encoder outputs made once per image ([`encode`]): only the decoder
/// and heads run per pair. Equal to [`predict_pair`].
pub fn predict_pair_encoded(
    model: &Dens3r,
    (first, e1): (&Prepared, &Encoded),
    (second, e2): (&Prepared, &Encoded),
    res: Resolution,
) -> [ViewMaps; 2] {
    predict_pair_features(model, &decode_pair(model, e1, e2), first, second, res)
}

/// The decoder on two encoded images: the pair's features.
pub fn decode_pair(model: &Dens3r, e1: &Encoded, e2: &Encoded) -> Features {
    model.decode(e1.tokens.clone(), e1.grid, e2.tokens.clone(), e2.grid)
}

/// The features of the pair the other way round, when the network's one decoder is shared by
/// both views: each view's stream then runs the same blocks on the same inputs in either
/// order, so `decode(b, a)` is `decode(a, b)` with its views swapped, exactly. `None` for a
/// network with two decoders.
pub fn swapped_features(model: &Dens3r, f: &Features) -> Option<Features> {
    model.config.shared_decoder.then(|| Features { views: [f.views[1].clone(), f.views[0].clone()] })
}

/// The heads on a pair's features ([`decode_pair`]) into maps: [`predict_pair_encoded`]
/// without the decoder.
pub fn predict_pair_features(
    model: &Dens3r,
    features: &Features,
    first: &Prepared,
    second: &Prepared,
    res: Resolution,
) -> [ViewMaps; 2] {
    pair_maps(&model.heads(features), first, second, res)
}

/// A pair's head outputs into maps (view 1 then view 2).
pub fn pair_maps(pred: &Predictions, first: &Prepared, second: &Prepared, res: Resolution) -> [ViewMaps; 2] {
    let r = first.info.rotated;
    [view_maps(&pred.views[0], first, 0, r, res), view_maps(&pred.views[1], second, 0, r, res)]
}

/// The extra passes a single image's prediction averages in (test-time augmentation): what a
/// model's config (`"tta_scales"`, `"tta_mirror"`) or `predict`'s options ask for.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TestTimePasses {
    /// Long sides of the network input of each extra pass.
    pub sizes: Vec<u32>,
    /// They see the photo mirrored left-right.
    pub mirrored: bool,
}

impl TestTimePasses {
    /// The photo prepared for each extra pass (mirrored once, when they are), as
    /// [`preprocess`] with `rotate_portrait`.
    pub fn prepare(&self, img: &DynamicImage, rotate_portrait: bool) -> Result<Vec<Prepared>, BackboneError> {
        if self.sizes.is_empty() {
            return Ok(Vec::new());
        }
        let flipped = self.mirrored.then(|| img.fliph());
        let img = flipped.as_ref().unwrap_or(img);
        self.sizes.iter().map(|&s| preprocess(img, s, rotate_portrait)).collect()
    }

    /// `primary` (at `res`) with the passes over `extra` ([`Self::prepare`]) run and averaged
    /// in ([`merge_passes`]).
    pub fn merge(
        &self,
        model: &Dens3r,
        primary: MonoPrediction,
        res: Resolution,
        extra: &[Prepared],
        want: HeadOutputs,
    ) -> MonoPrediction {
        let passes: Vec<Pass> = (extra.iter())
            .map(|e| Pass { prediction: predict_mono(model, e, Resolution::Network, want), mirrored: self.mirrored })
            .collect();
        merge_passes(primary, res, &passes)
    }
}

/// An extra network pass that [`merge_passes`] averages in (test-time augmentation).
#[derive(Debug, Clone)]
pub struct Pass {
    /// Its single-image prediction, at [`Resolution::Network`].
    pub prediction: MonoPrediction,
    /// It saw the photo mirrored left-right (`DynamicImage::fliph`): its maps are read
    /// mirrored back and its normals' x negated.
    pub mirrored: bool,
}

/// A single-image prediction averaged over several network passes (test-time augmentation):
/// `primary` at its own resolution, each of `others` a pass over the same photo at another
/// size, or mirrored. Each other prediction is read at the primary's pixels through the
/// photo's coordinates (bilinear), its depth scaled to the primary's median; the depth becomes
/// the geometric mean of all, the points move along the primary's rays to it (so the focal
/// they give stays the primary's), and the normals are the normalised sum. Confidence,
/// descriptors and colours stay the primary's.
pub fn merge_passes(mut primary: MonoPrediction, primary_res: Resolution, others: &[Pass]) -> MonoPrediction {
    if others.is_empty() {
        return primary;
    }
    let (w, h) = (primary.depth.width(), primary.depth.height());
    let valid = |z: f32| z.is_finite() && z > 0.0;
    let median = |d: &Raster<f32>| {
        let mut v: Vec<f64> = d.data().iter().filter(|&&z| valid(z)).map(|&z| f64::from(z)).collect();
        dens3r_geom::focal::median(&mut v)
    };
    let Some(m0) = median(&primary.depth) else { return primary };
    // Sums of log depth and of normals, and how many predictions each pixel has.
    let mut log_sum: Vec<f64> =
        primary.depth.data().iter().map(|&z| if valid(z) { f64::from(z).ln() } else { 0.0 }).collect();
    let mut count: Vec<u32> = primary.depth.data().iter().map(|&z| u32::from(valid(z))).collect();
    let mut normal_sum: Option<Vec<Vec3>> = primary.normals.as_ref().map(|n| n.data().to_vec());
    for pass in others {
        let o = &pass.prediction;
        let Some(mo) = median(&o.depth) else { continue };
        let scale = m0 / mo;
        // The photo's width: a mirrored pass's x is measured from the other side.
        let photo_w = oriented_geometry(&o.info).2 .0;
        for y in 0..h {
            for x in 0..w {
                let (xo, yo) = photo_coords(&primary.info, primary_res, (x as f64, y as f64));
                let xo = if pass.mirrored { photo_w - 1.0 - xo } else { xo };
                let (xn, yn) = network_coords(&o.info, (xo, yo));
                let i = y * w + x;
                if let Some(z) = bilinear(&o.depth, (xn, yn), |&z| valid(z).then_some(f64::from(z))) {
                    if valid(primary.depth.data()[i]) {
                        log_sum[i] += (z * scale).ln();
                        count[i] += 1;
                    }
                }
                if let (Some(sum), Some(n)) = (normal_sum.as_mut(), &o.normals) {
                    if let Some(v) = bilinear3(n, (xn, yn)) {
                        sum[i] += if pass.mirrored { Vec3::new(-v.x, v.y, v.z) } else { v };
                    }
                }
            }
        }
    }
    let old = primary.depth.clone();
    primary.depth = Raster::from_vec(
        w,
        h,
        old.data()
            .iter()
            .zip(&log_sum)
            .zip(&count)
            .map(|((&z, &s), &c)| if c > 0 { (s / f64::from(c)).exp() as f32 } else { z })
            .collect(),
    )
    .expect("same size");
    let pts: Vec<Vec3> = primary
        .points
        .data()
        .iter()
        .zip(old.data().iter().zip(primary.depth.data()))
        .map(|(p, (&z0, &z))| {
            if valid(z0) {
                // Along the ray, with the depth exactly its z.
                let q = *p * (z / z0);
                Vec3::new(q.x, q.y, z)
            } else {
                *p
            }
        })
        .collect();
    primary.points = Raster::from_vec(w, h, pts).expect("same size");
    if let Some(sum) = normal_sum {
        let n: Vec<Vec3> = sum.into_iter().map(|v| v.normalize_or_zero()).collect();
        primary.normals = Some(Raster::from_vec(w, h, n).expect("same size"));
    }
    primary
}

/// The resized image's size, the crop's offset and the photo's size, in the photo's own
/// orientation ([`PrepInfo::oriented`]).
fn oriented_geometry(info: &PrepInfo) -> ((f64, f64), (f64, f64), (f64, f64)) {
    let ((rw, rh), (x0, y0), _) = info.oriented();
    let o = info.original;
    ((f64::from(rw), f64::from(rh)), (f64::from(x0), f64::from(y0)), (f64::from(o.0), f64::from(o.1)))
}

/// The photo's pixel coordinates of pixel `(x, y)` of a map at `res`.
fn photo_coords(info: &PrepInfo, res: Resolution, (x, y): (f64, f64)) -> (f64, f64) {
    match res {
        Resolution::Original => (x, y),
        Resolution::Network => {
            let ((rw, rh), (x0, y0), (ow, oh)) = oriented_geometry(info);
            ((x + x0 + 0.5) * ow / rw - 0.5, (y + y0 + 0.5) * oh / rh - 0.5)
        }
    }
}

/// The network-resolution map coordinates (photo orientation) of the photo's pixel `(x, y)`.
fn network_coords(info: &PrepInfo, (x, y): (f64, f64)) -> (f64, f64) {
    let ((rw, rh), (x0, y0), (ow, oh)) = oriented_geometry(info);
    ((x + 0.5) * rw / ow - 0.5 - x0, (y + 0.5) * rh / oh - 0.5 - y0)
}

/// Bilinear sample of `map` at `(x, y)` (clamped to its edges) of the values `read` accepts;
/// `None` when any of the four neighbours is not accepted.
fn bilinear<T>(map: &Raster<T>, (x, y): (f64, f64), read: impl Fn(&T) -> Option<f64>) -> Option<f64> {
    let (w, h) = (map.width(), map.height());
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let at = |xx: usize, yy: usize| read(&map.data()[yy * w + xx]);
    let top = at(x0, y0)? * (1.0 - fx) + at(x1, y0)? * fx;
    let bottom = at(x0, y1)? * (1.0 - fx) + at(x1, y1)? * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

/// [`bilinear`] of a vector map, component by component.
fn bilinear3(map: &Raster<Vec3>, p: (f64, f64)) -> Option<Vec3> {
    let c = |k: usize| bilinear(map, p, |v: &Vec3| v.is_finite().then_some(f64::from(v[k])));
    Some(Vec3::new(c(0)? as f32, c(1)? as f32, c(2)? as f32))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preprocess::preprocess;

    /// The photo <-> network-map coordinates agree with the official `rescale_to_orig`
    /// (nearest neighbour) that `Resolution::Original` writes: landscape and a portrait photo
    /// turned to landscape, at two sizes.
    #[test]
    fn map_coordinates_follow_the_official_rescaling() {
        for ((w, h), rotate, size) in
            [((741, 500), true, 512), ((741, 500), true, 384), ((500, 741), true, 384), ((500, 741), false, 320)]
        {
            let img = image::DynamicImage::ImageRgb8(RgbImage::new(w, h));
            let info = preprocess(&img, size, rotate).unwrap().info;
            let (iw, ih) = info.input_size();
            let (mw, mh) = if info.rotated { (ih as usize, iw as usize) } else { (iw as usize, ih as usize) };
            // A network map (photo orientation) holding its own pixel coordinates, at the
            // photo's size through the official rescaling.
            let idx: Vec<f32> = (0..mw * mh).flat_map(|i| [(i % mw) as f32, (i / mw) as f32]).collect();
            let (up, oh, ow) = rescale_to_original(&idx, &PrepInfo { rotated: false, ..oriented(&info) }, 2);
            assert_eq!((ow, oh), (w as usize, h as usize));
            let mut worst = 0.0f64;
            for y in 0..oh {
                for x in 0..ow {
                    let (xn, yn) = network_coords(&info, (x as f64, y as f64));
                    let i = 2 * (y * ow + x);
                    // Nearest neighbour picks a pixel within one of the exact position (less at
                    // the padded edges, which the clamp keeps).
                    let (ex, ey) = (xn.clamp(0.0, (mw - 1) as f64), yn.clamp(0.0, (mh - 1) as f64));
                    worst = worst.max((ex - f64::from(up[i])).abs()).max((ey - f64::from(up[i + 1])).abs());
                    // And back: the network map's pixel through `photo_coords`.
                    let (px, py) = photo_coords(&info, Resolution::Network, (xn, yn));
                    assert!((px - x as f64).abs() < 1e-9 && (py - y as f64).abs() < 1e-9);
                }
            }
            assert!(worst <= 1.0, "{w}x{h} at {size}: {worst} pixels off");
        }
    }

    /// The photo-orientation geometry of `info` as an unrotated `PrepInfo`.
    fn oriented(info: &PrepInfo) -> PrepInfo {
        let (resized, (x0, y0), (iw, ih)) = info.oriented();
        PrepInfo { original: info.original, rotated: false, resized, crop: (x0, y0, x0 + iw, y0 + ih) }
    }

    fn maps(info: &PrepInfo, depth: impl Fn(usize, usize) -> f32, normal: Vec3) -> MonoPrediction {
        let (w, h) = info.oriented().2;
        let (w, h) = (w as usize, h as usize);
        let z: Vec<f32> = (0..w * h).map(|i| depth(i % w, i / w)).collect();
        ViewMaps {
            rgb: RgbImage::new(w as u32, h as u32),
            points: Raster::from_vec(w, h, z.iter().map(|&z| Vec3::new(0.1 * z, 0.0, z)).collect()).unwrap(),
            depth: Raster::from_vec(w, h, z).unwrap(),
            normals: Some(Raster::from_vec(w, h, vec![normal; w * h]).unwrap()),
            conf: None,
            desc: None,
            desc_conf: None,
            frame: 0,
            info: info.clone(),
        }
    }

    /// Merging: a pass at another size whose depth is the same surface at twice the scale
    /// changes nothing but the normals (the normalised sum); with itself, nothing at all;
    /// without others, the prediction as it was.
    #[test]
    fn merging_scales_averages_depth_and_normals() {
        let img = image::DynamicImage::ImageRgb8(RgbImage::new(741, 500));
        let (a, b) = (preprocess(&img, 512, true).unwrap().info, preprocess(&img, 384, true).unwrap().info);
        // A depth that is a function of the photo's coordinates (a tilted plane's 1/z is
        // linear in the pixel), so each map samples the same surface.
        let surface = |info: &PrepInfo, k: f32| {
            let info = info.clone();
            move |x: usize, y: usize| {
                let (px, py) = photo_coords(&info, Resolution::Network, (x as f64, y as f64));
                k / (1.0 + 0.0004 * px as f32 + 0.0008 * py as f32)
            }
        };
        let up = Vec3::new(0.0, 0.0, -1.0);
        let side = Vec3::new(1.0, 0.0, -1.0).normalize();
        let primary = maps(&a, surface(&a, 1.0), up);
        let pass = |prediction, mirrored| Pass { prediction, mirrored };
        let merged =
            merge_passes(primary.clone(), Resolution::Network, &[pass(maps(&b, surface(&b, 2.0), side), false)]);
        let worst =
            merged.depth.data().iter().zip(primary.depth.data()).map(|(m, p)| (m / p - 1.0).abs()).fold(0.0, f32::max);
        // The two maps' medians differ by their sampling of the surface, a fraction of a
        // percent; the bilinear read of a 1/z surface by less.
        assert!(worst < 3e-3, "depth moved by {worst}");
        let want = (up + side).normalize();
        assert!(merged.normals.as_ref().unwrap().data().iter().all(|n| n.angle_between(want) < 1e-4));
        for (p, z) in merged.points.data().iter().zip(merged.depth.data()) {
            assert!((p.z - z).abs() < 1e-5 * z && (p.x - 0.1 * z).abs() < 1e-5 * z, "points leave their rays");
        }
        let same = merge_passes(primary.clone(), Resolution::Network, &[pass(primary.clone(), false)]);
        assert!(same.depth.data().iter().zip(primary.depth.data()).all(|(s, p)| (s - p).abs() <= 1e-6 * p));
        let alone = merge_passes(primary.clone(), Resolution::Network, &[]);
        assert_eq!(alone.depth.data(), primary.depth.data());
    }

    /// A pass over the mirrored photo: its maps are the surface seen mirrored (depth at the
    /// mirrored column, normals with x negated); merged as mirrored, it lands on the primary's
    /// pixels (depth unchanged, normals the sum of the two unmirrored ones); merged as if it
    /// were not mirrored, it does not. Landscape, and portrait turned to landscape or kept.
    #[test]
    fn merging_a_mirrored_pass_reads_it_mirrored_back() {
        for ((w, h), rotate) in [((741, 500), true), ((500, 741), true), ((500, 741), false)] {
            let img = image::DynamicImage::ImageRgb8(RgbImage::new(w, h));
            let a = preprocess(&img, 512, rotate).unwrap().info;
            let b = preprocess(&img.fliph(), 384, rotate).unwrap().info;
            let plane = |px: f64, py: f64| 1.0 / (1.0 + 0.0004 * px as f32 + 0.0008 * py as f32);
            // Maps whose depth is `depth` of the photo coordinates of each map pixel.
            let seen = |info: &PrepInfo, depth: &dyn Fn(f64, f64) -> f32, normal| {
                let i = info.clone();
                maps(
                    info,
                    |x, y| {
                        let (px, py) = photo_coords(&i, Resolution::Network, (x as f64, y as f64));
                        depth(px, py)
                    },
                    normal,
                )
            };
            let primary = seen(&a, &plane, Vec3::new(0.0, 0.0, -1.0));
            // The mirrored photo's pixel (px, py) is the photo's (w - 1 - px, py).
            let last = f64::from(w - 1);
            let mirrored = seen(&b, &|px, py| 2.0 * plane(last - px, py), Vec3::new(-1.0, 0.0, -1.0).normalize());
            let merged = merge_passes(
                primary.clone(),
                Resolution::Network,
                &[Pass { prediction: mirrored.clone(), mirrored: true }],
            );
            let moved = |m: &MonoPrediction| {
                m.depth.data().iter().zip(primary.depth.data()).map(|(m, p)| (m / p - 1.0).abs()).fold(0.0, f32::max)
            };
            assert!(moved(&merged) < 3e-3, "{w}x{h}: depth moved by {}", moved(&merged));
            let want = (Vec3::new(0.0, 0.0, -1.0) + Vec3::new(1.0, 0.0, -1.0).normalize()).normalize();
            assert!(merged.normals.as_ref().unwrap().data().iter().all(|n| n.angle_between(want) < 1e-4));
            // Read as an unmirrored pass, the tilt comes out the other way round.
            let wrong =
                merge_passes(primary.clone(), Resolution::Network, &[Pass { prediction: mirrored, mirrored: false }]);
            assert!(
                moved(&wrong) > 0.05,
                "{w}x{h}: a mirrored pass read unmirrored moved the depth by only {}",
                moved(&wrong)
            );
        }
    }
}
