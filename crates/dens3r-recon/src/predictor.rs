//! What runs on a pair of images: the network ([`NetworkPredictor`]) or anything else that
//! yields pointmaps (an oracle in tests, another model).

use crate::input::InputImage;
use dens3r_backbone::model::Dens3r;
use dens3r_backbone::predict::{
    decode_pair, encode, pair_maps, predict_mono, swapped_features, DescriptorMap, Encoded, Resolution, ViewMaps,
};
use dens3r_backbone::{Features, HeadOutputs, Tensor};
use dens3r_geom::{Raster, Vec3};
use std::cell::RefCell;
use std::collections::HashMap;

/// One view of a pair prediction, at the view's [`InputImage::size`].
#[derive(Debug, Clone)]
pub struct ViewOutput {
    /// Pointmap in the OpenCV frame of the pair's first camera (any similarity of it).
    pub points: Raster<Vec3>,
    /// Confidence (>= 1; `1 + exp(x)` for Dens3R).
    pub conf: Raster<f32>,
    /// Unit normals in this view's own OpenCV camera frame, facing the camera.
    pub normals: Option<Raster<Vec3>>,
    /// Matching descriptors.
    pub desc: Option<DescriptorMap>,
    /// Descriptor confidence.
    pub desc_conf: Option<Raster<f32>>,
}

/// Maps whose sizes disagree with their image or with each other (one line saying which).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct MapSizeError(pub String);

impl ViewOutput {
    /// Checks sizes against `(w, h)` and that the maps agree with each other.
    pub fn check(&self, (w, h): (usize, usize)) -> Result<(), MapSizeError> {
        let sz = |r: (usize, usize), what: &str| {
            if r != (w, h) {
                Err(MapSizeError(format!("{what} is {}x{}, expected {w}x{h}", r.0, r.1)))
            } else {
                Ok(())
            }
        };
        sz((self.points.width(), self.points.height()), "pointmap")?;
        sz((self.conf.width(), self.conf.height()), "confidence")?;
        if let Some(n) = &self.normals {
            sz((n.width(), n.height()), "normals")?;
        }
        if let Some(d) = &self.desc {
            sz((d.width, d.height), "descriptors")?;
            if d.dim == 0 || d.data.len() != w * h * d.dim {
                return Err(MapSizeError(format!("descriptors hold {} values for {w}x{h}x{}", d.data.len(), d.dim)));
            }
        }
        if let Some(c) = &self.desc_conf {
            sz((c.width(), c.height()), "descriptor confidence")?;
        }
        Ok(())
    }

    /// From the backbone's maps; a model without a confidence head gets confidence `e`
    /// (loss weight 1 under `log`).
    pub fn from_maps(m: ViewMaps) -> Self {
        let conf = m.conf.unwrap_or_else(|| Raster::filled(m.points.width(), m.points.height(), std::f32::consts::E));
        Self { points: m.points, conf, normals: m.normals, desc: m.desc, desc_conf: m.desc_conf }
    }
}

/// What a pair run is asked for beyond pointmaps, confidence and normals. A predictor may
/// return more; the pipeline asks only for what it reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Wanted {
    /// Matching descriptors and their confidence: needed only by the run a pair is matched on
    /// (one of its two orders).
    pub descriptors: bool,
}

impl Wanted {
    /// Every output.
    pub const ALL: Self = Self { descriptors: true };
}

/// Runs pairs of images.
pub trait PairPredictor {
    /// Identifies the predictor and its settings in the pair cache: outputs cached under one
    /// id are reused only by a predictor with the same id.
    fn id(&self) -> String;
    /// Predicts the ordered pair `(images[i], images[j])`: both pointmaps in camera `i`'s
    /// frame, and what `want` asks for.
    fn predict(&self, images: &[InputImage], i: usize, j: usize, want: Wanted) -> Result<[ViewOutput; 2], String>;
    /// Image `i` alone: its pointmap in its own frame, confidence and normals (the self-pair's
    /// first view, as the official pipeline reads a single image). By default the self-pair
    /// through [`PairPredictor::predict`].
    fn predict_mono(&self, images: &[InputImage], i: usize) -> Result<ViewOutput, String> {
        let [v, _] = self.predict(images, i, i, Wanted { descriptors: false })?;
        Ok(v)
    }
    /// Image `i` as one global descriptor for retrieval ([`dens3r_align::retrieval`]), or None
    /// when this predictor has none (then `--graph retrieval` cannot run on it).
    fn embed(&self, images: &[InputImage], i: usize) -> Result<Option<Vec<f32>>, String> {
        let _ = (images, i);
        Ok(None)
    }
}

/// An image's identity for the encoder cache: content hash, crop box, portrait rotation.
type ImageKey = (u64, (u32, u32, u32, u32), bool);

/// The Dens3R / DUSt3R / MASt3R network at its input resolution. Each image is encoded once
/// and its encoder tokens reused in every pair it is in (the siamese encoder's output does not
/// depend on the other view), so only the decoder and heads run per pair; with a decoder shared
/// by both views, the pair `(j, i)` asked right after `(i, j)` reuses its decoder pass with the
/// views swapped (exactly what running it gives), and the normal head's outputs (one head
/// for both views, on the same features), so only its point and descriptor heads run. The
/// descriptor head runs only when asked ([`Wanted`]): it costs about as much as the point head.
pub struct NetworkPredictor<'a> {
    model: &'a Dens3r,
    weights_id: String,
    encoded: RefCell<HashMap<ImageKey, Encoded>>,
    /// The last pair's work for the reverse pair, under that pair's key.
    pending: RefCell<Option<((ImageKey, ImageKey), Reverse)>>,
    decoded: std::cell::Cell<usize>,
}

impl<'a> NetworkPredictor<'a> {
    /// `weights_id` identifies the weights and input size in the pair cache (see [`weights_id`]).
    pub fn new(model: &'a Dens3r, weights_id: String) -> Self {
        Self {
            model,
            weights_id,
            encoded: RefCell::new(HashMap::new()),
            pending: RefCell::new(None),
            decoded: std::cell::Cell::new(0),
        }
    }

    /// Decoder passes run so far.
    pub fn decoder_passes(&self) -> usize {
        self.decoded.get()
    }

    /// Images encoded so far.
    pub fn encoded_images(&self) -> usize {
        self.encoded.borrow().len()
    }

    fn encoding(&self, im: &InputImage) -> Encoded {
        self.encoded.borrow_mut().entry(image_key(im)).or_insert_with(|| encode(self.model, &im.prep)).clone()
    }
}

impl PairPredictor for NetworkPredictor<'_> {
    fn id(&self) -> String {
        format!("dens3r-network-v1 {}", self.weights_id)
    }

    fn predict(&self, images: &[InputImage], i: usize, j: usize, want: Wanted) -> Result<[ViewOutput; 2], String> {
        let (a, b) = (&images[i], &images[j]);
        let desc = want.descriptors;
        let key = (image_key(a), image_key(b));
        let reuse = self.pending.borrow_mut().take().filter(|(k, _)| *k == key).map(|(_, r)| r);
        let pred = match reuse {
            Some(r) => {
                let mut pred = self.model.heads_with(&r.features, HeadOutputs { normal: false, desc });
                for (v, n) in pred.views.iter_mut().zip(r.normals) {
                    (v.normal, v.raw_normal) = n;
                }
                pred
            }
            None => {
                let f = decode_pair(self.model, &self.encoding(a), &self.encoding(b));
                self.decoded.set(self.decoded.get() + 1);
                let pred = self.model.heads_with(&f, HeadOutputs { normal: true, desc });
                if let Some(features) = swapped_features(self.model, &f) {
                    let n = |k: usize| (pred.views[k].normal.clone(), pred.views[k].raw_normal.clone());
                    *self.pending.borrow_mut() = Some(((key.1, key.0), Reverse { features, normals: [n(1), n(0)] }));
                }
                pred
            }
        };
        let [va, vb] = pair_maps(&pred, &a.prep, &b.prep, Resolution::Network);
        Ok([ViewOutput::from_maps(va), ViewOutput::from_maps(vb)])
    }

    /// The self-pair without its redundant half ([`predict_mono`]): one decoder view, one
    /// set of heads.
    fn predict_mono(&self, images: &[InputImage], i: usize) -> Result<ViewOutput, String> {
        let want = HeadOutputs { normal: true, desc: false };
        Ok(ViewOutput::from_maps(predict_mono(self.model, &images[i].prep, Resolution::Network, want)))
    }

    /// The pooled encoder tokens ([`Encoded::global_descriptor`]); the tokens are not kept
    /// (hundreds of photos' tokens would not fit the memory a run may take).
    fn embed(&self, images: &[InputImage], i: usize) -> Result<Option<Vec<f32>>, String> {
        let im = &images[i];
        let desc = match self.encoded.borrow().get(&image_key(im)) {
            Some(e) => e.global_descriptor(),
            None => encode(self.model, &im.prep).global_descriptor(),
        };
        Ok(Some(desc))
    }
}

/// What the reverse of a pair reuses: the swapped decoder features and each view's normals
/// (the normal head reads the same features of a view in either order).
struct Reverse {
    features: Features,
    normals: [(Option<Tensor<4>>, Option<Tensor<4>>); 2],
}

fn image_key(im: &InputImage) -> ImageKey {
    (im.hash, im.prep.info.crop, im.prep.info.rotated)
}

/// The network's id in `cache` ([`NetworkPredictor::new`]'s): its files' content
/// ([`weights_id`], remembered in the cache folder), its input size and, where not f32, its
/// precision (`precision`: "" or " f16" ...), since another size or precision gives other
/// outputs; "uncached" without a folder. The CLI and the Python module key alike, so one
/// cache serves both.
pub fn network_cache_id(
    weights: &std::path::Path,
    config: Option<&std::path::Path>,
    cache: &crate::PairCache,
    size: u32,
    precision: &str,
) -> Result<String, dens3r_io::IoError> {
    let id = match cache.dir() {
        Some(dir) => weights_id(weights, config, Some(&dir.join(".file-hashes.json")))?,
        None => "uncached".into(),
    };
    Ok(format!("{id} size {size}{precision}"))
}

/// Identifies a network in the pair cache by content: hashes of the weights, the config that
/// sets its head counts and the encoder `.onnx` a DINOv2-encoder network reads beside them,
/// so weights edited in place (whatever their modification time) or another config never
/// reuse a pair. Each file is read once: its hash is remembered in `memo` (see
/// [`dens3r_io::hash::file_hash`]).
pub fn weights_id(
    weights: &std::path::Path,
    config: Option<&std::path::Path>,
    memo: Option<&std::path::Path>,
) -> Result<String, dens3r_io::IoError> {
    let (file, folder_config) = if weights.is_dir() {
        dens3r_backbone::verify::model_folder_files(weights).map_err(|e| dens3r_io::IoError::new(&e.path, e.message))?
    } else {
        (weights.to_path_buf(), None)
    };
    let config = config.map(std::path::Path::to_path_buf).or(folder_config);
    let encoder = dens3r_backbone::verify::find_dinov2(&file, config.as_deref()).ok();
    let mut id = String::from("content");
    for f in [Some(file), config, encoder].into_iter().flatten() {
        let h = dens3r_io::hash::file_hash(&f, memo)
            .map_err(|e| dens3r_io::IoError::new(&f, format!("cannot read it to key the pair cache: {e}")))?;
        id.push_str(&format!(" {h:016x}"));
    }
    Ok(id)
}

#[cfg(test)]
mod tests {
    /// Issue 66, 2: the network's cache id follows its config (other head counts) and its
    /// weights' content, and is stable for unchanged files.
    #[test]
    fn weights_id_follows_content_and_config() {
        let dir = tempfile::tempdir().unwrap();
        let [w, c1, c2, memo] = ["w.safetensors", "a.json", "b.json", "memo.json"].map(|n| dir.path().join(n));
        std::fs::write(&w, b"weights").unwrap();
        std::fs::write(&c1, br#"{"enc_num_heads": 16, "dec_num_heads": 12}"#).unwrap();
        std::fs::write(&c2, br#"{"enc_num_heads": 8, "dec_num_heads": 12}"#).unwrap();
        let id = |c: &std::path::Path| super::weights_id(&w, Some(c), Some(&memo)).unwrap();
        let first = id(&c1);
        assert_eq!(first, id(&c1));
        assert_ne!(first, id(&c2));
        assert_ne!(first, super::weights_id(&w, None, Some(&memo)).unwrap());
        std::fs::write(&w, b"weighty").unwrap();
        assert_ne!(first, id(&c1));
    }
}
