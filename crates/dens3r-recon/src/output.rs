//! Writing a [`Reconstruction`]: the scene folder, the exports other tools read, match
//! pictures, and the fused mesh.
//!
//! ```text
//! out/scene/            cameras.json, images/, depth/, normals/, conf/ (dens3r scene folder)
//! out/summary.json      what the run did, stage by stage (photos registered, pair graph, seconds)
//! out/scene/transforms.json   nerfstudio (OpenGL poses, paths relative to out/scene)
//! out/colmap/           cameras.txt, images.txt, points3D.txt (image names relative to out/scene)
//! out/matches/<a>-<b>.png     match pictures (`<a>-<b>-2.png` where two pairs' names join alike)
//! out/mesh.glb          TSDF mesh of the aligned depth
//! out/index.html        the page that shows it all (dens3r-viewer; viewer/ beside it)
//! ```

use crate::pipeline::Reconstruction;
use crate::viz::match_picture;
use crate::ReconError;
use dens3r_fusion::scene::{fuse_frames, FusionFrame, SceneFusion, SceneFusionError};
use dens3r_fusion::{extract_mesh, ExtractOptions, FusionError, TsdfParams};
use dens3r_io::output::OutputDir;
use dens3r_mesh::TriMesh;
use dens3r_scene::export::{write_colmap_binary, write_colmap_text, write_transforms_json};
use dens3r_scene::{Frame, Layer, Scene, SceneWriter};
use dens3r_viewer::{write_page, MatchPicture, Page, View};
use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Output settings.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputOptions {
    /// TSDF voxel in scene units; None: twice the pixel footprint at the median depth.
    pub voxel: Option<f32>,
    /// Truncation in voxels.
    pub trunc_voxels: f32,
    /// Pixels below this confidence are not fused (DUSt3R's demo default: 3).
    pub min_conf: f32,
    /// Stop before the voxel grid exceeds this many bytes.
    pub budget_bytes: usize,
    /// Fuse on the GPU (needs the `gpu` feature).
    pub gpu: bool,
    /// Fuse at all (otherwise only the scene and exports are written).
    pub mesh: bool,
    /// Drop mesh pieces with fewer triangles than this.
    pub min_component: usize,
    /// Match pictures for at most this many pairs (0: none).
    pub match_pictures: usize,
    /// Lines per match picture.
    pub match_lines: usize,
    /// Recorded in `cameras.json` as `generator`.
    pub generator: String,
    /// Write `index.html`, the page that shows the result (`None`: no page).
    pub page: Option<dens3r_viewer::PageOptions>,
    /// Multi-view stereo on the cameras, the network's depth and normals as its prior: its
    /// maps in `OUT/mvs/` (a scene folder with `points.ply` and `mesh.ply`), and the mesh
    /// and page from it. `None`: the mesh is the network's depth fused (`--dense network`).
    pub mvs: Option<dens3r_mvs::MvsOptions>,
}

impl Default for OutputOptions {
    fn default() -> Self {
        Self {
            voxel: None,
            trunc_voxels: 4.0,
            min_conf: crate::model::DEFAULT_MIN_CONF,
            budget_bytes: 4 << 30,
            gpu: false,
            mesh: true,
            min_component: 100,
            match_pictures: 20,
            match_lines: 150,
            generator: "dens3r reconstruct".into(),
            page: Some(dens3r_viewer::PageOptions::default()),
            mvs: None,
        }
    }
}

/// What was written.
#[derive(Debug, Clone, Default)]
pub struct OutputSummary {
    /// The scene folder.
    pub scene: PathBuf,
    /// The COLMAP text model folder.
    pub colmap: PathBuf,
    /// The mesh, when one was fused and had a surface.
    pub mesh: Option<PathBuf>,
    /// Mesh size.
    pub triangles: usize,
    /// Voxel used.
    pub voxel: f32,
    /// Seconds fusing and extracting.
    pub fuse_seconds: f64,
    /// GPU adapter used for fusion.
    pub gpu_adapter: Option<String>,
    /// Things the user should know.
    pub warnings: Vec<String>,
    /// The page (`index.html`), where written.
    pub page: Option<PathBuf>,
    /// Seconds writing the page.
    pub page_seconds: f64,
    /// What multi-view stereo did, where it ran.
    pub mvs: Option<dens3r_mvs::output::MvsSummary>,
}

/// The match pictures' files of pairs of frame names, `matches/<a>-<b>.png`, each its own:
/// names may hold '-' (`a-b` + `c` and `a` + `b-c` join alike), so a later pair whose file
/// is taken gets `-2`, `-3`, ...
pub fn match_picture_files<'a>(pairs: impl Iterator<Item = (&'a str, &'a str)>) -> Vec<String> {
    let mut taken = std::collections::HashSet::new();
    pairs
        .map(|(a, b)| {
            let stem = format!("matches/{a}-{b}");
            (1..)
                .map(|k| if k == 1 { format!("{stem}.png") } else { format!("{stem}-{k}.png") })
                .find(|f| taken.insert(f.clone()))
                .expect("a free name")
        })
        .collect()
}

/// Starts the output folder `out` of a reconstruction: its lock taken (a second run into it is
/// refused), its outputs staged; only files its output list names, unchanged since, are
/// replaced.
pub fn begin_outputs(out: &Path) -> Result<OutputDir, ReconError> {
    Ok(dens3r_scene::begin_output(out)?)
}

/// Writes everything under `out` as one transaction (staged, then moved into place; nothing
/// there but dens3r's own earlier outputs is replaced); `fuse_progress(done, total)` follows
/// fusion.
pub fn write_outputs(
    rec: &Reconstruction,
    sources: &[PathBuf],
    out: &Path,
    opts: &OutputOptions,
    fuse_progress: impl FnMut(usize, usize),
) -> Result<OutputSummary, ReconError> {
    let dir = begin_outputs(out)?;
    let summary = write_outputs_into(rec, sources, &dir, opts, fuse_progress)?;
    dir.finish()?;
    Ok(summary)
}

/// Writes everything into the staging folder of `dir` (begun by [`begin_outputs`]); the
/// summary names the files where `dir.finish()` puts them.
pub fn write_outputs_into(
    rec: &Reconstruction,
    sources: &[PathBuf],
    dir: &OutputDir,
    opts: &OutputOptions,
    mut fuse_progress: impl FnMut(usize, usize),
) -> Result<OutputSummary, ReconError> {
    let t_write = std::time::Instant::now();
    let out = dir.root();
    let scene_dir = out.join("scene");
    let mut w = SceneWriter::in_folder(&scene_dir)?;
    w.set_extra("generator", serde_json::json!(opts.generator));
    w.set_extra("units", serde_json::json!("arbitrary (up to scale)"));
    w.set_extra("alignment_loss", serde_json::json!([rec.alignment.loss.0, rec.alignment.loss.1]));
    for (k, v) in rec.alignment.views.iter().enumerate() {
        let name = &rec.names[k];
        let mut frame = Frame::new(name, &v.camera);
        if let Some(src) = rec.inputs.get(k).and_then(|&i| sources.get(i)) {
            frame.extra.insert("source".into(), serde_json::json!(src.display().to_string()));
        }
        w.add_frame(frame, &rec.rgb[k])?;
        w.write_depth(name, &v.depth)?;
        w.write_conf(name, &v.conf)?;
        if let Some(n) = &rec.normals[k] {
            w.write_normals(name, n)?;
        }
        if let Some(m) = rec.masks.get(k).and_then(Option::as_ref) {
            w.write_mask(name, m)?;
        }
    }
    w.finish()?;
    let scene = Scene::open(&scene_dir)?;
    write_transforms_json(&scene_dir.join("transforms.json"), scene.frames(), |f| scene.has(f, Layer::Depth))?;
    let colmap = out.join("colmap");
    write_colmap_text(&colmap, scene.frames(), &rec.points)?;
    write_colmap_binary(&colmap, scene.frames(), &rec.points)?;

    let mut ranked: Vec<&(usize, usize, Vec<_>)> = rec.matches.iter().filter(|m| !m.2.is_empty()).collect();
    ranked.sort_by_key(|m| std::cmp::Reverse(m.2.len()));
    let mut pictures = Vec::new();
    let ranked: Vec<_> = ranked.into_iter().take(opts.match_pictures).collect();
    let files = match_picture_files(ranked.iter().map(|m| (rec.names[m.0].as_str(), rec.names[m.1].as_str())));
    for ((a, b, ms), file) in ranked.into_iter().zip(files) {
        let img = match_picture(&rec.rgb[*a], &rec.rgb[*b], ms, opts.match_lines);
        dens3r_scene::write_rgb_png(&out.join(&file), &img)?;
        pictures.push(MatchPicture { a: rec.names[*a].clone(), b: rec.names[*b].clone(), path: file });
    }

    let dest = dir.dest();
    let mut summary = OutputSummary { scene: dest.join("scene"), colmap: dest.join("colmap"), ..Default::default() };
    let _ = colmap;
    let mut mesh = None;
    let mut mvs_scene = None;
    if let Some(mvs) = &opts.mvs {
        match dense_stage(&scene, out, opts, mvs, &mut summary, &mut fuse_progress) {
            Ok(m) => {
                mesh = Some(m);
                mvs_scene = Some(Scene::open(&out.join("mvs"))?);
            }
            Err(e) => {
                // Nothing of a failed dense stage stays in the (staged) output.
                let _ = std::fs::remove_dir_all(out.join("mvs"));
                summary.warnings.push(format!("multi-view stereo: {e}; the mesh is the network's depth fused"))
            }
        }
    }
    if opts.mesh && mesh.is_none() {
        mesh = fuse(rec, out, opts, &mut summary, &mut fuse_progress)?;
    }
    summary.mesh = summary.mesh.map(|_| dest.join("mesh.glb"));
    let write_seconds = t_write.elapsed().as_secs_f64() - summary.fuse_seconds;
    let json = run_summary(rec, &summary, write_seconds, opts.min_conf);
    let text = serde_json::to_string_pretty(&json).expect("plain JSON values");
    dens3r_io::write_atomic(&out.join("summary.json"), |w| std::io::Write::write_all(w, text.as_bytes()))?;
    if let Some(page_opts) = &opts.page {
        let t_page = Instant::now();
        let mvs_views = match &mvs_scene {
            Some(m) => Some(dens3r_viewer::scene_views::SceneViews::read(m, "mvs/")?),
            None => None,
        };
        let page = Page {
            title: dens3r_viewer::title_of(dest),
            views: match &mvs_views {
                Some(v) => v.views(),
                None => page_views(rec, &scene),
            },
            mesh: mesh.as_ref(),
            summary: Some(json),
            scores: None,
            matches: pictures,
            min_conf: opts.min_conf,
        };
        write_page(out, &page, page_opts)?;
        summary.page = Some(dest.join("index.html"));
        summary.page_seconds = t_page.elapsed().as_secs_f64();
    }
    Ok(summary)
}

/// The reconstruction's views as the page shows them (photos from the scene folder).
fn page_views<'a>(rec: &'a Reconstruction, scene: &Scene) -> Vec<View<'a>> {
    rec.alignment
        .views
        .iter()
        .enumerate()
        .map(|(k, v)| View {
            name: &rec.names[k],
            camera: v.camera,
            rgb: &rec.rgb[k],
            depth: &v.depth,
            conf: Some(&v.conf),
            normals: rec.normals[k].as_ref(),
            mask: rec.masks.get(k).and_then(Option::as_ref),
            photo: scene.frames().get(k).map(|f| format!("scene/{}", f.image)),
        })
        .collect()
}

/// `OUT/summary.json`: what the run did and how long each stage took (seconds), for tools
/// and benchmarks that read a run rather than its printout.
fn run_summary(rec: &Reconstruction, out: &OutputSummary, write_seconds: f64, rec_min_conf: f32) -> serde_json::Value {
    let s = &rec.stats;
    let mut focals: Vec<f64> = rec.alignment.views.iter().map(|v| v.camera.intrinsics.fx).collect();
    focals.dedup();
    serde_json::json!({
        "photos": s.registered + s.unregistered.len(),
        "registered": s.registered,
        "unregistered": s.unregistered,
        "cameras": if s.sfm.is_some() { "sfm" } else { "dense" },
        "graph": {
            "name": s.graph.name, "pairs": s.graph.list.len(), "ordered": s.graph.ordered,
            "list": s.graph.list.iter().map(|&(i, j)| [&s.graph.names[i], &s.graph.names[j]]).collect::<Vec<_>>(),
        },
        "network_runs": s.pairs - s.cache_hits,
        "cache_hits": s.cache_hits,
        "focals_px": focals,
        "reprojection_rms_px": s.sfm.as_ref().map(|f| f.rms_px.1),
        "points": rec.points.len(),
        "mesh_triangles": out.triangles,
        "mesh": {"voxel": out.voxel, "min_conf": if out.mvs.is_some() { serde_json::Value::Null } else { serde_json::json!(rec_min_conf) }, "from": if out.mvs.is_some() { "mvs" } else { "network" }},
        "mvs": out.mvs.as_ref().map(|m| m.to_json()),
        "seconds": {
            "retrieval": s.graph.seconds,
            "keypoints": s.keypoint_seconds,
            "cameras": s.align_seconds,
            "network": s.predict_seconds,
            "matching": s.match_seconds,
            "write": write_seconds,
            "fuse": out.fuse_seconds,
        },
        "warnings": s.warnings.iter().chain(&out.warnings).collect::<Vec<_>>(),
    })
}

/// The default voxel: twice the pixel footprint at the median depth of all views (within
/// their masks, where given).
pub fn auto_voxel(rec: &Reconstruction) -> Option<f32> {
    let mut per_view: Vec<f64> = rec
        .alignment
        .views
        .iter()
        .enumerate()
        .filter_map(|(k, v)| {
            let mask = rec.masks.get(k).and_then(Option::as_ref);
            let kept = |i: usize| mask.is_none_or(|m| m.data()[i]);
            let mut d: Vec<f64> = v
                .depth
                .data()
                .iter()
                .enumerate()
                .filter(|&(i, d)| *d > 0.0 && d.is_finite() && kept(i))
                .map(|(_, &d)| d as f64)
                .collect();
            dens3r_geom::focal::median(&mut d).map(|m| 2.0 * m / v.camera.intrinsics.fx)
        })
        .collect();
    dens3r_geom::focal::median(&mut per_view).map(|v| v as f32).filter(|v| v.is_finite() && *v > 0.0)
}

/// Multi-view stereo on the scene folder just written (its depth and normals the prior): the
/// result in `out/mvs/`, its mesh as `out/mesh.glb`.
fn dense_stage(
    scene: &Scene,
    out: &Path,
    opts: &OutputOptions,
    mvs: &dens3r_mvs::MvsOptions,
    summary: &mut OutputSummary,
    progress: &mut impl FnMut(usize, usize),
) -> Result<TriMesh, ReconError> {
    let t = Instant::now();
    let source = dens3r_mvs::scene::SceneViews::new(scene);
    let stages = |s: dens3r_mvs::Stage| match s {
        dens3r_mvs::Stage::Photometric => 0,
        dens3r_mvs::Stage::Geometric => 1,
        dens3r_mvs::Stage::Fusion => 2,
    };
    let result =
        dens3r_mvs::run_mvs(&source, None, mvs, |s, done, total| progress(stages(s) * total + done, 3 * total))
            .map_err(|e| ReconError::Other(e.to_string()))?;
    let mesh_opts = dens3r_mvs::output::MeshOptions { voxel: opts.voxel, budget_bytes: Some(opts.budget_bytes) };
    let (ms, mesh) = dens3r_mvs::output::write_mvs(&out.join("mvs"), &source, &result, &mesh_opts, &[])
        .map_err(|e| ReconError::Other(e.to_string()))?;
    if opts.mesh {
        let path = out.join("mesh.glb");
        dens3r_mesh::write_mesh(&path, &mesh).map_err(|e| ReconError::Other(e.to_string()))?;
        summary.mesh = Some(path);
        summary.triangles = mesh.indices.len();
        summary.voxel = ms.voxel;
    }
    summary.fuse_seconds = t.elapsed().as_secs_f64();
    summary.mvs = Some(ms);
    Ok(mesh)
}

/// The aligned views fused into a mesh straight from memory (what the scene folder holds,
/// without reading it back).
fn fuse(
    rec: &Reconstruction,
    out: &Path,
    opts: &OutputOptions,
    summary: &mut OutputSummary,
    progress: &mut impl FnMut(usize, usize),
) -> Result<Option<TriMesh>, ReconError> {
    let t = Instant::now();
    let Some(mut voxel) = opts.voxel.or_else(|| auto_voxel(rec)) else {
        summary.warnings.push("no valid aligned depth: no mesh".into());
        return Ok(None);
    };
    if !(voxel.is_finite() && voxel > 0.0) {
        return Err(ReconError::Other(format!("voxel {voxel} must be positive")));
    }
    // An automatic voxel that would exceed the budget (depth spread far by poor predictions)
    // is doubled, up to 6 times, with a warning; a voxel the user chose is kept and fails.
    let mut tries = if opts.voxel.is_some() { 0 } else { 6 };
    let (tsdf, fs) = loop {
        let mut params = TsdfParams::new(voxel);
        params.trunc = opts.trunc_voxels * voxel;
        params.depth_range = (voxel * 1e-3, f32::MAX);
        params.budget_bytes = Some(opts.budget_bytes);
        let fusion = SceneFusion { params, use_conf: true, min_conf: opts.min_conf, use_normals: false, gpu: opts.gpu };
        let frames = rec.alignment.views.iter().enumerate().map(|(k, v)| {
            Ok(FusionFrame {
                name: Cow::Borrowed(rec.names[k].as_str()),
                camera: v.camera,
                depth: Cow::Borrowed(&v.depth),
                mask: rec.masks.get(k).and_then(Option::as_ref).map(Cow::Borrowed),
                color: Some(Cow::Borrowed(&rec.rgb[k])),
                conf: Some(Cow::Borrowed(&v.conf)),
                normals: None,
            })
        });
        match fuse_frames("the reconstruction", frames, &fusion, &mut *progress) {
            Err(e @ SceneFusionError::Fusion(FusionError::Budget { .. })) if tries > 0 => {
                summary
                    .warnings
                    .push(format!("the automatic voxel {voxel} needs too much memory ({e}); trying {}", 2.0 * voxel));
                voxel *= 2.0;
                tries -= 1;
            }
            r => break r.map_err(|e| ReconError::Other(e.to_string()))?,
        }
    };
    let mesh = extract_mesh(tsdf.grid(), &ExtractOptions { min_component_triangles: opts.min_component, crop: None });
    summary.voxel = voxel;
    summary.gpu_adapter = fs.gpu_adapter;
    summary.fuse_seconds = t.elapsed().as_secs_f64();
    if mesh.indices.is_empty() {
        summary.warnings.push(format!(
            "the fused volume has no surface at voxel {voxel} (confidence below {} everywhere, or too few views agree); lower --min-conf or set --voxel",
            opts.min_conf
        ));
        return Ok(None);
    }
    let path = out.join("mesh.glb");
    dens3r_mesh::write_mesh(&path, &mesh).map_err(|e| ReconError::Other(e.to_string()))?;
    summary.triangles = mesh.indices.len();
    summary.mesh = Some(path);
    Ok(Some(mesh))
}

#[cfg(test)]
mod tests {
    /// Issue 77, 10: `a-b` + `c` and `a` + `b-c` both wrote `matches/a-b-c.png`.
    #[test]
    fn match_pictures_of_names_with_dashes_do_not_collide() {
        let files = super::match_picture_files([("a-b", "c"), ("a", "b-c"), ("a-b-c", "2"), ("x", "y")].into_iter());
        assert_eq!(files, ["matches/a-b-c.png", "matches/a-b-c-2.png", "matches/a-b-c-2-2.png", "matches/x-y.png"]);
    }
}
