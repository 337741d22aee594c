//! Single-image and pair prediction (spec section 2 "Single image" and 3.2), mapped back to
//! the un-rotated image frame, optionally at the original resolution, in our conventions.

use crate::model::{Dens3r, Features, HeadOutputs, Predictions, ViewFeatures, ViewPrediction};
use crate::preprocess::{rescale_to_original, rotate_map_clockwise, unrotate_vector, PrepInfo, Prepared};
use burn::tensor::Tensor;
use dens3r_geom::{NormalConvention, Raster, Vec3};
use image::RgbImage;

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
