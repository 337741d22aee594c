//! Writing the page: `index.html`, its script and data under `viewer/`, each file atomic (the
//! callers write it inside their output transaction, so a failed run leaves none of it).

use crate::cloud::{bounds, cloud};
use crate::decimate::decimate;
use crate::pictures::{fit, jpeg_data_url};
use crate::{assets, VIEWER_BUNDLED};
use base64::Engine;
use dens3r_geom::{PinholeCamera, Raster};
use dens3r_io::{write_atomic, IoError};
use dens3r_mesh::TriMesh;
use dens3r_scene::viz::{conf_viz, depth_viz, normal_viz};
use dens3r_scene::{write_rgb_png, SceneError};
use glam::Vec3;
use image::RgbImage;
use rayon::prelude::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// One view: its camera (OpenCV, camera-to-world) and maps at the maps' size.
#[derive(Debug, Clone)]
pub struct View<'a> {
    /// Frame name.
    pub name: &'a str,
    /// Camera of the maps' pixels.
    pub camera: PinholeCamera,
    /// Colours at the maps' size.
    pub rgb: &'a RgbImage,
    /// z-depth (<= 0 or NaN: none).
    pub depth: &'a Raster<f32>,
    /// Confidence, where the network gave one.
    pub conf: Option<&'a Raster<f32>>,
    /// Normals, OpenCV camera frame, facing the camera.
    pub normals: Option<&'a Raster<Vec3>>,
    /// Object mask: only its pixels go into the point cloud.
    pub mask: Option<&'a Raster<bool>>,
    /// The photo as the output holds it, relative to the page; `None`: the page keeps a copy.
    pub photo: Option<String>,
}

/// A match picture the output holds (path relative to the page).
#[derive(Debug, Clone, PartialEq)]
pub struct MatchPicture {
    /// First view's name.
    pub a: String,
    /// Second view's name.
    pub b: String,
    /// The picture, relative to the page.
    pub path: String,
}

/// What the page shows.
#[derive(Debug, Clone, Default)]
pub struct Page<'a> {
    /// Heading (the output folder's name, say).
    pub title: String,
    /// Views with cameras and maps.
    pub views: Vec<View<'a>>,
    /// The fused mesh, decimated for the page.
    pub mesh: Option<&'a TriMesh>,
    /// The run's summary (`summary.json`), shown as a table.
    pub summary: Option<Value>,
    /// Scores against a ground truth, where known, by kind (`dens3r eval` adds them later
    /// through [`add_scores`]).
    pub scores: Option<Value>,
    /// Match pictures.
    pub matches: Vec<MatchPicture>,
    /// The confidence threshold the slider starts at (the fusion's).
    pub min_conf: f32,
}

/// Sizes of what goes into the page.
#[derive(Debug, Clone, PartialEq)]
pub struct PageOptions {
    /// Points in the cloud at most.
    pub max_points: usize,
    /// Mesh triangles at most (vertex clustering above).
    pub max_triangles: usize,
    /// Longer side of the frustums' photo thumbnails, pixels.
    pub thumb_px: u32,
    /// Longer side of the per-view pictures, pixels.
    pub picture_px: u32,
}

impl Default for PageOptions {
    fn default() -> Self {
        Self { max_points: 300_000, max_triangles: 250_000, thumb_px: 192, picture_px: 384 }
    }
}

/// What was written.
#[derive(Debug, Clone, PartialEq)]
pub struct PageSummary {
    /// `index.html` where it was written.
    pub index: PathBuf,
    /// Points in the page's cloud.
    pub points: usize,
    /// Triangles of the page's mesh.
    pub triangles: usize,
    /// Whether the 3-D view is in this build.
    pub bundled: bool,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> IoError + '_ {
    move |e| IoError::new(path, e.to_string())
}

fn write_text(path: &Path, text: &str) -> Result<(), IoError> {
    write_atomic(path, |w| std::io::Write::write_all(w, text.as_bytes()))
}

/// Base64 of the little-endian bytes of `values` (each `N` bytes), gathered in one buffer.
fn b64<T, const N: usize>(values: &[T], bytes: impl Fn(&T) -> [u8; N]) -> String {
    let mut buf = Vec::with_capacity(values.len() * N);
    values.iter().for_each(|v| buf.extend_from_slice(&bytes(v)));
    base64::engine::general_purpose::STANDARD.encode(buf)
}

fn f32s(v: &[Vec3]) -> String {
    b64(v, |p| {
        let [x, y, z] = p.to_array().map(f32::to_le_bytes);
        [x[0], x[1], x[2], x[3], y[0], y[1], y[2], y[3], z[0], z[1], z[2], z[3]]
    })
}

/// Writes the page into `dir` (`index.html` and `viewer/`).
pub fn write_page(dir: &Path, page: &Page, opts: &PageOptions) -> Result<PageSummary, SceneError> {
    let viewer = dir.join("viewer");
    std::fs::create_dir_all(viewer.join("views")).map_err(io(&viewer))?;
    // Each view's pictures are independent (and most of the page's time).
    let views: Vec<Value> =
        page.views.par_iter().enumerate().map(|(k, v)| view_json(&viewer, k, v, opts)).collect::<Result<_, _>>()?;
    let pts = cloud(&page.views, opts.max_points);
    let centres: Vec<_> = page.views.iter().map(|v| v.camera.center()).collect();
    let (centre, radius) = bounds(&pts.positions, &centres);
    let mesh = page.mesh.map(|m| decimate(m, opts.max_triangles));
    let points = json!({
        "count": pts.positions.len(),
        "positions": f32s(&pts.positions),
        "colors": b64(&pts.colors, |c| *c),
        "conf": b64(&pts.conf, |c| c.to_le_bytes()),
        // About the samples' spacing, so the surface reads as closed; never zero.
        "point_size": (pts.spacing * 1.5).max(radius * 1e-4),
    });
    let mesh_json = mesh.as_ref().map(|m| {
        json!({
            "vertices": m.positions.len(),
            "triangles": m.indices.len(),
            "positions": f32s(&m.positions),
            "indices": b64(&m.indices, |t| {
                let [a, b, c] = t.map(u32::to_le_bytes);
                [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3], c[0], c[1], c[2], c[3]]
            }),
            "colors": m.colors.as_ref().map(|c| b64(c, |c| *c)),
        })
    });
    let data = json!({
        "title": page.title,
        "views": views,
        "points": points,
        "mesh": mesh_json,
        "summary": page.summary,
        "matches": page.matches.iter().map(|m| json!({"a": m.a, "b": m.b, "path": url_path(&m.path)})).collect::<Vec<_>>(),
        "min_conf": page.min_conf,
        "bounds": {"center": centre.to_array(), "radius": radius},
        "frustum_depth": frustum_depth(&centres, radius),
    });
    let script = format!("window.DENS3R_SCENE = {};\n", serde_json::to_string(&data).expect("plain JSON values"));
    write_text(&dir.join(SCENE_JS), &script)?;
    write_text(&dir.join(SCORES_JS), &scores_script(page.scores.as_ref().unwrap_or(&Value::Null)))?;
    write_text(&dir.join(APP_JS), assets::APP_JS)?;
    write_text(&dir.join(THREE_LICENSE), assets::THREE_LICENSE)?;
    let html = assets::INDEX_HTML
        .replace("<title>dens3r</title>", &format!("<title>{} - dens3r</title>", escape(&page.title)));
    let index = dir.join(INDEX_HTML);
    write_text(&index, &html)?;
    Ok(PageSummary {
        index,
        points: pts.positions.len(),
        triangles: mesh.map_or(0, |m| m.indices.len()),
        bundled: VIEWER_BUNDLED,
    })
}

/// One view's camera and pictures (written under `viewer/views/`, numbered: names may hold
/// characters a URL would need escaped).
fn view_json(viewer: &Path, k: usize, v: &View, opts: &PageOptions) -> Result<Value, SceneError> {
    let mut pictures = serde_json::Map::new();
    if let Some(p) = &v.photo {
        pictures.insert("photo".into(), json!(url_path(p)));
    }
    let mut put = |kind: &str, img: RgbImage| -> Result<(), SceneError> {
        let file = format!("{k:04}_{kind}.png");
        write_rgb_png(&viewer.join("views").join(&file), &fit(&img, opts.picture_px))?;
        pictures.insert(kind.into(), json!(format!("viewer/views/{file}")));
        Ok(())
    };
    if v.photo.is_none() {
        put("photo", v.rgb.clone())?;
    }
    put("depth", depth_viz(v.depth))?;
    if let Some(n) = v.normals {
        put("normals", normal_viz(n))?;
    }
    if let Some(c) = v.conf {
        put("conf", conf_viz(c))?;
    }
    let k_ = &v.camera.intrinsics;
    let m = v.camera.cam_to_world;
    let rows: Vec<f64> = (0..4).flat_map(|r| (0..4).map(move |c| m.col(c)[r])).collect();
    Ok(json!({
        "name": v.name,
        "width": v.camera.width, "height": v.camera.height,
        "fx": k_.fx, "fy": k_.fy, "cx": k_.cx, "cy": k_.cy,
        "c2w": rows,
        "thumb": jpeg_data_url(&fit(v.rgb, opts.thumb_px), 80),
        "pictures": pictures,
    }))
}

/// Frustum depth: a third of the median distance between neighbouring cameras, capped at a
/// tenth of the scene's radius.
fn frustum_depth(centres: &[glam::DVec3], radius: f32) -> f32 {
    let mut nearest: Vec<f64> = centres
        .iter()
        .enumerate()
        .filter_map(|(i, a)| {
            centres.iter().enumerate().filter(|(j, _)| *j != i).map(|(_, b)| a.distance(*b)).min_by(f64::total_cmp)
        })
        .filter(|d| *d > 0.0)
        .collect();
    nearest.sort_by(f64::total_cmp);
    let cap = radius * 0.1;
    nearest.get(nearest.len() / 2).map_or(cap, |d| ((*d / 3.0) as f32).min(cap))
}

/// A page's heading for the output folder `dest`: its name.
pub fn title_of(dest: &Path) -> String {
    dest.file_name().map_or_else(|| dest.display().to_string(), |n| n.to_string_lossy().into_owned())
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// A relative path as a URL path: bytes other than letters, digits, `-._~/` percent-encoded
/// (a `#` or `?` in a photo's name would otherwise end the path).
pub fn url_path(p: &str) -> String {
    use percent_encoding::{utf8_percent_encode, NON_ALPHANUMERIC};
    const KEEP: &percent_encoding::AsciiSet =
        &NON_ALPHANUMERIC.remove(b'-').remove(b'.').remove(b'_').remove(b'~').remove(b'/');
    utf8_percent_encode(p, KEEP).to_string()
}

/// The page that shows `pred` (a scene folder or a mesh an output folder holds): the folder
/// itself or its parent, where dens3r wrote a page (its list of outputs names the scores
/// file, unchanged since, so a file of anyone else's is never touched).
pub fn page_of(pred: &Path) -> Option<PathBuf> {
    let dir = if pred.is_dir() { Some(pred) } else { None };
    let ours = |d: &Path| dens3r_io::output::Manifest::read(d).ok().flatten().is_some_and(|m| m.owns(d, SCORES_JS));
    dir.into_iter()
        .chain(pred.parent())
        .map(|d| if d.as_os_str().is_empty() { Path::new(".") } else { d })
        .find(|d| ours(d))
        .map(Path::to_path_buf)
}

/// Adds `scores` under `kind` (e.g. `"cameras"`) to the page that shows `pred`, if there is
/// one (`viewer/scores.js`, rewritten atomically and its new content recorded in the output
/// list, so a later run still knows it as dens3r's; the other kinds kept); returns the page.
pub fn add_scores(pred: &Path, kind: &str, scores: Value) -> Result<Option<PathBuf>, IoError> {
    let Some(dir) = page_of(pred) else { return Ok(None) };
    let path = dir.join(SCORES_JS);
    let old = std::fs::read_to_string(&path).map_err(io(&path))?;
    let mut all = old
        .trim()
        .strip_prefix(SCORES_PREFIX)
        .and_then(|s| serde_json::from_str::<Value>(s.trim_end_matches(';')).ok())
        .filter(Value::is_object)
        .unwrap_or_else(|| json!({}));
    all[kind] = scores;
    if !dens3r_io::output::rewrite_own(&dir, SCORES_JS, scores_script(&all).as_bytes())? {
        return Ok(None);
    }
    Ok(Some(dir.join(INDEX_HTML)))
}

/// The page, in its folder.
pub const INDEX_HTML: &str = "index.html";
/// The bundled viewer.
pub const APP_JS: &str = "viewer/app.js";
/// The page's data.
pub const SCENE_JS: &str = "viewer/scene.js";
/// Scores, rewritten by [`add_scores`].
pub const SCORES_JS: &str = "viewer/scores.js";
/// three.js's licence.
pub const THREE_LICENSE: &str = "viewer/THREE-LICENSE.txt";
const SCORES_PREFIX: &str = "window.DENS3R_SCORES = ";

fn scores_script(scores: &Value) -> String {
    format!("{SCORES_PREFIX}{};\n", serde_json::to_string(scores).expect("plain JSON values"))
}
