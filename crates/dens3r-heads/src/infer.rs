//! Inference with saved heads: one backbone pass per image feeds every head
//! (`dens3r predict --head`), and the files the outputs are written to.

use crate::features::{to_vec, FeatureMaps};
use crate::head::{Head, Task};
use crate::train::argmax_channels;
use crate::HeadsError;
use burn::tensor::Device;
use image::RgbImage;
use std::path::Path;

/// A head's per-pixel output at the backbone input's size, row-major.
#[derive(Debug, Clone, PartialEq)]
pub enum HeadOutput {
    /// Class ids (argmax of the logits).
    Labels(Vec<u16>),
    /// Depth, `exp` of the head's log-depth (up to scale for SILog heads, and up to scale and
    /// shift of log-depth for affine-invariant ones).
    Depth(Vec<f32>),
}

/// Checks that `head` (read from `path`) can run on features of the backbone `id` with layer
/// widths `dims`: the same backbone it was trained on, and layers that exist with its widths.
pub fn check_head(path: &Path, head: &Head, id: &str, dims: &[usize]) -> Result<(), HeadsError> {
    let c = &head.config;
    if c.backbone != id {
        return Err(HeadsError::file(
            path,
            format!(
                "the head was trained on features of backbone {:?}, but this backbone is {id:?}; give the \
                 backbone it was trained with (same weights file and layers)",
                c.backbone
            ),
        ));
    }
    for (&l, &d) in c.layers.iter().zip(&c.in_dims) {
        if dims.get(l) != Some(&d) {
            return Err(HeadsError::file(
                path,
                format!("the head reads layer {l} with {d} channels; the backbone gives {dims:?}"),
            ));
        }
    }
    Ok(())
}

/// Runs `head` on one image's features; the output covers `grid * patch` pixels.
pub fn infer(head: &Head, features: &FeatureMaps, device: &Device) -> HeadOutput {
    let p = head.config.patch;
    let (h, w) = (features.grid.0 * p, features.grid.1 * p);
    let out = to_vec(head.predict(features, (h, w), device));
    match &head.config.task {
        Task::Seg { classes } => HeadOutput::Labels(argmax_channels(&out, classes.len(), h * w)),
        Task::Depth => HeadOutput::Depth(out.into_iter().map(f32::exp).collect()),
    }
}

/// The PASCAL VOC colour of class `i` (bit-interleaved, as VOC and ADE20K palettes are made).
pub fn palette(i: u16) -> [u8; 3] {
    let mut c = [0u8; 3];
    let mut id = i;
    for shift in (0..8).rev() {
        for (ch, v) in c.iter_mut().enumerate() {
            *v |= (((id >> ch) & 1) as u8) << shift;
        }
        id >>= 3;
    }
    c
}

/// Writes class ids as a label PNG (atomically): 8-bit palette indices with the VOC colours
/// when every id is below 256 (what VOC-style tools and [`crate::data::read_label_png`] read),
/// else 16-bit grey ([`dens3r_scene::write_id_png`]).
pub fn write_label_png(path: &Path, ids: &[u16], width: u32, height: u32) -> Result<(), HeadsError> {
    if ids.iter().any(|&v| v > 255) {
        return Ok(dens3r_scene::write_id_png(path, ids, width, height)?);
    }
    let err = |e: png::EncodingError| HeadsError::file(path, format!("cannot encode ({e})"));
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, width, height);
        enc.set_color(png::ColorType::Indexed);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_palette((0..256).flat_map(|i| palette(i as u16)).collect::<Vec<u8>>());
        let mut w = enc.write_header().map_err(err)?;
        w.write_image_data(&ids.iter().map(|&v| v as u8).collect::<Vec<u8>>()).map_err(err)?;
        w.finish().map_err(err)?;
    }
    Ok(dens3r_io::write_atomic(path, |w| std::io::Write::write_all(w, &bytes))?)
}

/// The image with each pixel's class colour blended in at one half, for viewing.
pub fn overlay(image: &RgbImage, ids: &[u16]) -> RgbImage {
    let mut out = image.clone();
    for (px, &id) in out.pixels_mut().zip(ids) {
        let c = palette(id);
        for k in 0..3 {
            px[k] = ((px[k] as u16 + c[k] as u16) / 2) as u8;
        }
    }
    out
}

/// Writes one image's head output where `dens3r predict --head` puts it: `heads_dir/NAME.png`
/// (labels, [`write_label_png`]) or `heads_dir/NAME.npy` (depth, float32 H x W), and the picture
/// `viz` (labels over `rgb`, or depth on [`dens3r_scene::viz::depth_viz`]'s ramp). `out` covers
/// `rgb`'s pixels.
pub fn write_head_output(
    heads_dir: &Path,
    viz: &Path,
    name: &str,
    out: &HeadOutput,
    rgb: &RgbImage,
) -> Result<(), HeadsError> {
    let (w, h) = (rgb.width(), rgb.height());
    match out {
        HeadOutput::Labels(l) => {
            write_label_png(&heads_dir.join(format!("{name}.png")), l, w, h)?;
            dens3r_scene::write_rgb_png(viz, &overlay(rgb, l))?;
        }
        HeadOutput::Depth(d) => {
            let path = heads_dir.join(format!("{name}.npy"));
            dens3r_scene::npy::write_f32(&path, &[h as usize, w as usize], d)?;
            let r = dens3r_geom::Raster::from_vec(w as usize, h as usize, d.clone())
                .map_err(|e| HeadsError::file(&path, e.to_string()))?;
            dens3r_scene::write_rgb_png(viz, &dens3r_scene::viz::depth_viz(&r))?;
        }
    }
    Ok(())
}
