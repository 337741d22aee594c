//! Monocular prediction (an image paired with itself, spec section 2 "Single image"), mapped
//! back to the un-rotated network-input frame, in our conventions.

use crate::model::Dens3r;
use crate::preprocess::{rotate_map_clockwise, unrotate_vector, PrepInfo, Prepared};
use burn::tensor::Tensor;
use dens3r_geom::{NormalConvention, Raster, Vec3};
use image::RgbImage;

/// What one image yields, at network-input resolution, in the image's own orientation.
#[derive(Debug, Clone)]
pub struct MonoPrediction {
    /// The network input as RGB (rotated back if the image was portrait).
    pub rgb: RgbImage,
    /// Pointmap in the OpenCV camera frame (model units).
    pub points: Raster<Vec3>,
    /// z of `points`.
    pub depth: Raster<f32>,
    /// Unit normals, OpenCV camera frame, facing the camera.
    pub normals: Option<Raster<Vec3>>,
    /// Confidence (`1 + exp(x)`).
    pub conf: Option<Raster<f32>>,
    /// How the image was preprocessed.
    pub info: PrepInfo,
}

fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.to_data().try_to_vec::<f32>().expect("float tensor")
}

/// Runs the self-pair and reads view 1 (`pred1`), as the official pipeline does.
pub fn predict_mono(model: &Dens3r, prep: &Prepared) -> MonoPrediction {
    let x = prep.tensor(model.device());
    let pred = model.forward(x.clone(), x);
    let v = &pred.views[0];
    let [_, h, w, _] = v.pts3d.dims();
    let rotated = prep.info.rotated;
    let vec_map = |flat: Vec<f32>, to_cv: &dyn Fn([f32; 3]) -> [f32; 3]| -> Raster<Vec3> {
        let (flat, hh, ww) = if rotated { rotate_map_clockwise(&flat, h, w, 3) } else { (flat, h, w) };
        let v: Vec<Vec3> = flat
            .chunks_exact(3)
            .map(|c| {
                let p = to_cv([c[0], c[1], c[2]]);
                Vec3::from_array(if rotated { unrotate_vector(p) } else { p })
            })
            .collect();
        Raster::from_vec(ww, hh, v).expect("sizes follow the tensor")
    };
    let scalar_map = |flat: Vec<f32>| -> Raster<f32> {
        let (flat, hh, ww) = if rotated { rotate_map_clockwise(&flat, h, w, 1) } else { (flat, h, w) };
        Raster::from_vec(ww, hh, flat).expect("sizes follow the tensor")
    };
    let points = vec_map(values(&v.pts3d), &|p| p);
    let raw = NormalConvention::Dens3rRaw;
    let normals = v.normal.as_ref().map(|n| vec_map(values(n), &|c| raw.to_opencv(Vec3::from_array(c)).to_array()));
    let conf = v.conf.as_ref().map(|c| scalar_map(values(c)));
    let depth = points.map(|p| if p.is_finite() && p.z > 0.0 { p.z } else { 0.0 });
    let rgb = if rotated { image::imageops::rotate90(&prep.rgb) } else { prep.rgb.clone() };
    MonoPrediction { rgb, points, depth, normals, conf, info: prep.info.clone() }
}
