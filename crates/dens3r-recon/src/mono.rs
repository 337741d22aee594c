//! One image's self-pair prediction as a frame of a scene folder (`dens3r predict`): the camera
//! from a known focal (EXIF, the user), else the pointmap's (or a 60-degree fallback), depth, normals and confidence layers,
//! pictures of depth and normals under `viz/`, and the coloured pointmap under `pointmaps/`.

use crate::ReconError;
use dens3r_backbone::predict::MonoPrediction;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{focal_or_fallback, DMat4, Intrinsics, PinholeCamera};
use dens3r_mesh::TriMesh;
use dens3r_scene::viz::{depth_viz, normal_viz};
use dens3r_scene::{Frame, SceneWriter};

/// The camera of a single-image prediction: identity pose, principal point at the centre, the
/// pointmap's focal, and `true`; or, when the pointmap gives no positive focal (as untrained
/// weights do), a 60-degree horizontal field of view and `false`.
pub fn mono_camera(pred: &MonoPrediction) -> (PinholeCamera, bool) {
    let (w, h) = (pred.depth.width(), pred.depth.height());
    let cam = |f: f64| PinholeCamera {
        intrinsics: Intrinsics { fx: f, fy: f, cx: w as f64 / 2.0, cy: h as f64 / 2.0 },
        width: w,
        height: h,
        cam_to_world: DMat4::IDENTITY,
    };
    match focal_or_fallback(&pred.points, w, h) {
        Ok(f) => (cam(f), true),
        Err(f) => (cam(f), false),
    }
}

/// The camera of a single-image prediction with a `known` focal (pixels of its maps) and its
/// source, else [`mono_camera`]'s; and where its focal came from.
pub fn mono_camera_known(pred: &MonoPrediction, known: Option<(f64, FocalSource)>) -> (PinholeCamera, FocalSource) {
    let (mut cam, estimated) = mono_camera(pred);
    let source = match known.filter(|(f, _)| f.is_finite() && *f > 0.0) {
        Some((f, s)) => {
            (cam.intrinsics.fx, cam.intrinsics.fy) = (f, f);
            s
        }
        None if estimated => FocalSource::Pointmap,
        None => FocalSource::Fallback,
    };
    (cam, source)
}

/// Where a frame's focal length came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FocalSource {
    /// The photo's EXIF 35 mm equivalent focal length.
    Exif,
    /// Given by the user (`--focal`).
    Given,
    /// Estimated from the predicted pointmap.
    Pointmap,
    /// The 60-degree fallback: the pointmap gave no positive focal (untrained weights).
    Fallback,
}

impl FocalSource {
    /// The name written to `cameras.json` (`focal_source`).
    pub fn as_str(self) -> &'static str {
        match self {
            FocalSource::Exif => "exif",
            FocalSource::Given => "given",
            FocalSource::Pointmap => "pointmap",
            FocalSource::Fallback => "fallback",
        }
    }
}

/// Writes `pred` as frame `name` of the scene `writer` builds (image, camera, depth, normals,
/// confidence), plus `viz/NAME_depth.png`, `viz/NAME_normal.png` and `pointmaps/NAME.ply`.
/// `known` is a focal length in pixels of the written maps with its source (EXIF, the user):
/// the camera takes it, and the coloured pointmap is the depth along that camera's rays, so
/// depth, camera and points agree. Without it the camera is [`mono_camera`]'s. The camera
/// records `focal_source` (and `focal_estimated`, true only for a pointmap focal), `source`
/// and `rotated`. Returns the focal's source.
pub fn write_mono_frame(
    writer: &mut SceneWriter,
    name: &str,
    pred: &MonoPrediction,
    known: Option<(f64, FocalSource)>,
) -> Result<FocalSource, ReconError> {
    let (cam, source) = mono_camera_known(pred, known);
    let mut frame = Frame::new(name, &cam);
    frame.extra.insert("focal_source".into(), serde_json::json!(source.as_str()));
    frame.extra.insert("focal_estimated".into(), serde_json::json!(source == FocalSource::Pointmap));
    frame.extra.insert("source".into(), serde_json::json!(pred.info.original));
    frame.extra.insert("rotated".into(), serde_json::json!(pred.info.rotated));
    writer.add_frame(frame, &pred.rgb)?;
    writer.write_depth(name, &pred.depth)?;
    let root = writer.root().to_path_buf();
    if let Some(n) = &pred.normals {
        writer.write_normals(name, n)?;
        dens3r_scene::write_rgb_png(&root.join("viz").join(format!("{name}_normal.png")), &normal_viz(n))?;
    }
    if let Some(c) = &pred.conf {
        writer.write_conf(name, c)?;
    }
    dens3r_scene::write_rgb_png(&root.join("viz").join(format!("{name}_depth.png")), &depth_viz(&pred.depth))?;
    let points = match source {
        FocalSource::Exif | FocalSource::Given => depth_to_pointmap(&pred.depth, &cam.intrinsics),
        FocalSource::Pointmap | FocalSource::Fallback => pred.points.clone(),
    };
    let finite = || points.data().iter().zip(pred.rgb.pixels()).filter(|(p, _)| p.is_finite());
    let mut cloud = TriMesh::new(finite().map(|(p, _)| *p).collect(), Vec::new());
    cloud.colors = Some(finite().map(|(_, c)| c.0).collect());
    dens3r_mesh::write_mesh(&root.join("pointmaps").join(format!("{name}.ply")), &cloud)
        .map_err(dens3r_scene::SceneError::from)?;
    Ok(source)
}
