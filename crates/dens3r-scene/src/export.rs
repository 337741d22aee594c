//! Exports of a scene's cameras (and optional 3-D tracks) for other systems:
//!
//! * **COLMAP text model** (`cameras.txt`, `images.txt`, `points3D.txt`): one `PINHOLE` camera
//!   per frame, world-to-camera quaternion and translation per image, tracks as 3-D points with
//!   their observations. COLMAP's camera frame is OpenCV's; its pixel coordinates put the
//!   centre of the top-left pixel at (0.5, 0.5), ours at (0, 0), so principal points and
//!   keypoints gain 0.5.
//! * **nerfstudio `transforms.json`**: OpenGL camera-to-world matrices (x right, y up, -z
//!   forward), per-frame intrinsics in the same +0.5 pixel convention, depth files when present.
//!
//! Every file is written atomically.

use crate::{Frame, SceneError};
use dens3r_geom::camera::{mat4_to_rows, opencv_to_opengl_pose, rigid_inverse};
use dens3r_geom::{DMat3, DVec3};
use dens3r_io::write_atomic;
use glam::DQuat;
use std::fmt::Write as _;
use std::path::Path;

/// A 3-D point seen in several frames (a match track), for `points3D.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackPoint {
    /// World position.
    pub xyz: DVec3,
    /// Colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels (COLMAP's ERROR column).
    pub error: f64,
    /// Observations: frame index and pixel (ours: pixel centres at integers).
    pub observations: Vec<(usize, (f64, f64))>,
}

fn write_text(path: &Path, text: &str) -> Result<(), SceneError> {
    Ok(write_atomic(path, |w| std::io::Write::write_all(w, text.as_bytes()))?)
}

/// Writes `cameras.txt`, `images.txt` and `points3D.txt` into `dir` (created if needed).
/// Image and camera ids are frame index + 1; point ids are track index + 1.
pub fn write_colmap_text(dir: &Path, frames: &[Frame], points: &[TrackPoint]) -> Result<(), SceneError> {
    for (t, p) in points.iter().enumerate() {
        if let Some(&(f, _)) = p.observations.iter().find(|(f, _)| *f >= frames.len()) {
            return Err(SceneError::new(
                dir,
                format!("track {t} observes frame {f}, but there are {} frames", frames.len()),
            ));
        }
    }
    // Per image, its keypoints (POINTS2D) in track order: (x, y, point id).
    let mut kps: Vec<Vec<(f64, f64, usize)>> = vec![Vec::new(); frames.len()];
    let mut track_refs: Vec<Vec<(usize, usize)>> = Vec::with_capacity(points.len());
    for (t, p) in points.iter().enumerate() {
        let mut refs = Vec::new();
        for &(f, (x, y)) in &p.observations {
            refs.push((f + 1, kps[f].len()));
            kps[f].push((x + 0.5, y + 0.5, t + 1));
        }
        track_refs.push(refs);
    }
    let mut cams = String::from(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
    );
    let _ = writeln!(cams, "# Number of cameras: {}", frames.len());
    let mut imgs = String::from(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    let _ = writeln!(imgs, "# Number of images: {}", frames.len());
    for (i, f) in frames.iter().enumerate() {
        let cam = f.camera();
        let k = cam.intrinsics;
        let _ = writeln!(
            cams,
            "{} PINHOLE {} {} {} {} {} {}",
            i + 1,
            f.width,
            f.height,
            k.fx,
            k.fy,
            k.cx + 0.5,
            k.cy + 0.5
        );
        let w2c = rigid_inverse(&cam.cam_to_world);
        let q = DQuat::from_mat3(&DMat3::from_mat4(w2c)).normalize();
        let q = if q.w < 0.0 { -q } else { q };
        let t = w2c.w_axis.truncate();
        let _ =
            writeln!(imgs, "{} {} {} {} {} {} {} {} {} {}", i + 1, q.w, q.x, q.y, q.z, t.x, t.y, t.z, i + 1, f.image);
        let line: Vec<String> = kps[i].iter().map(|(x, y, id)| format!("{x} {y} {id}")).collect();
        let _ = writeln!(imgs, "{}", line.join(" "));
    }
    let mut pts = String::from(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
    );
    let _ = writeln!(pts, "# Number of points: {}", points.len());
    for (t, p) in points.iter().enumerate() {
        let track: Vec<String> = track_refs[t].iter().map(|(im, idx)| format!("{im} {idx}")).collect();
        let _ = writeln!(
            pts,
            "{} {} {} {} {} {} {} {} {}",
            t + 1,
            p.xyz.x,
            p.xyz.y,
            p.xyz.z,
            p.rgb[0],
            p.rgb[1],
            p.rgb[2],
            p.error,
            track.join(" ")
        );
    }
    write_text(&dir.join("cameras.txt"), &cams)?;
    write_text(&dir.join("images.txt"), &imgs)?;
    write_text(&dir.join("points3D.txt"), &pts)
}

/// Writes nerfstudio's `transforms.json` for the frames of a scene folder at `path` (file
/// paths relative to the scene root, which should be the JSON's folder).
pub fn write_transforms_json(
    path: &Path,
    frames: &[Frame],
    with_depth: impl Fn(&Frame) -> bool,
) -> Result<(), SceneError> {
    let list: Vec<serde_json::Value> = frames
        .iter()
        .map(|f| {
            let cam = f.camera();
            let k = cam.intrinsics;
            let mut j = serde_json::json!({
                "file_path": f.image,
                "transform_matrix": mat4_to_rows(&opencv_to_opengl_pose(&cam.cam_to_world)),
                "fl_x": k.fx,
                "fl_y": k.fy,
                "cx": k.cx + 0.5,
                "cy": k.cy + 0.5,
                "w": f.width,
                "h": f.height,
            });
            if with_depth(f) {
                j["depth_file_path"] = serde_json::Value::String(format!("depth/{}.npy", f.name));
            }
            j
        })
        .collect();
    let doc =
        serde_json::json!({ "camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": list });
    let text = serde_json::to_string_pretty(&doc).map_err(|e| SceneError::new(path, e.to_string()))?;
    write_text(path, &text)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::camera::look_at;
    use dens3r_geom::{Intrinsics, PinholeCamera};

    /// Parses COLMAP's text format as its documentation defines it, independently of the writer,
    /// and checks that a world point projects where the export says it is observed.
    #[test]
    fn colmap_text_reads_back_and_projects() {
        let dir = tempfile::tempdir().unwrap();
        let cams = [
            PinholeCamera {
                intrinsics: Intrinsics { fx: 500.0, fy: 510.0, cx: 319.5, cy: 239.0 },
                width: 640,
                height: 480,
                cam_to_world: look_at(DVec3::new(2.0, 0.5, 1.0), DVec3::ZERO, DVec3::Z).unwrap(),
            },
            PinholeCamera {
                intrinsics: Intrinsics::from_hfov(320, 200, 70.0),
                width: 320,
                height: 200,
                cam_to_world: look_at(DVec3::new(-1.0, 2.0, 0.3), DVec3::new(0.1, 0.0, 0.2), DVec3::Z).unwrap(),
            },
        ];
        let frames: Vec<Frame> = cams.iter().enumerate().map(|(i, c)| Frame::new(&format!("v{i}"), c)).collect();
        let x = DVec3::new(0.1, -0.2, 0.3);
        let obs: Vec<(usize, (f64, f64))> = cams
            .iter()
            .enumerate()
            .map(|(i, c)| (i, c.intrinsics.project(rigid_inverse(&c.cam_to_world).transform_point3(x))))
            .collect();
        let track = TrackPoint { xyz: x, rgb: [10, 20, 30], error: 0.0, observations: obs.clone() };
        write_colmap_text(dir.path(), &frames, &[track]).unwrap();

        let lines = |f: &str| -> Vec<String> {
            std::fs::read_to_string(dir.path().join(f))
                .unwrap()
                .lines()
                .filter(|l| !l.starts_with('#'))
                .map(String::from)
                .collect()
        };
        let num = |s: &str| s.parse::<f64>().unwrap();
        let cams_txt = lines("cameras.txt");
        let imgs_txt = lines("images.txt");
        assert_eq!(cams_txt.len(), 2);
        assert_eq!(imgs_txt.len(), 4);
        for i in 0..2 {
            let c: Vec<&str> = cams_txt[i].split(' ').collect();
            assert_eq!(c[1], "PINHOLE");
            let (fx, fy, cx, cy) = (num(c[4]), num(c[5]), num(c[6]), num(c[7]));
            let im: Vec<f64> = imgs_txt[2 * i].split(' ').take(8).map(num).collect();
            let q = DQuat::from_xyzw(im[2], im[3], im[4], im[1]);
            let t = DVec3::new(im[5], im[6], im[7]);
            // COLMAP: x_cam = R(q) X + t; pixel = (fx x/z + cx, fy y/z + cy), centre of the
            // top-left pixel at (0.5, 0.5).
            let pc = q * x + t;
            let (u, v) = (fx * pc.x / pc.z + cx, fy * pc.y / pc.z + cy);
            let p2d: Vec<f64> = imgs_txt[2 * i + 1].split(' ').map(num).collect();
            assert!((u - p2d[0]).abs() < 1e-6 && (v - p2d[1]).abs() < 1e-6, "{u},{v} vs {p2d:?}");
            assert!((p2d[0] - (obs[i].1 .0 + 0.5)).abs() < 1e-6);
            assert_eq!(p2d[2], 1.0);
            // The camera centre from (q, t) is ours.
            let centre = -(q.inverse() * t);
            assert!((centre - cams[i].center()).length() < 1e-9);
        }
        let p: Vec<f64> = lines("points3D.txt")[0].split(' ').map(num).collect();
        assert_eq!(&p[..8], &[1.0, x.x, x.y, x.z, 10.0, 20.0, 30.0, 0.0]);
        assert_eq!(&p[8..], &[1.0, 0.0, 2.0, 0.0]);

        // A track naming a missing frame is an error, and nothing is written.
        let bad = TrackPoint { xyz: x, rgb: [0; 3], error: 0.0, observations: vec![(5, (0.0, 0.0))] };
        let other = tempfile::tempdir().unwrap();
        assert!(write_colmap_text(other.path(), &frames, &[bad]).is_err());
        assert_eq!(std::fs::read_dir(other.path()).unwrap().count(), 0);
    }

    #[test]
    fn transforms_json_is_opengl() {
        let dir = tempfile::tempdir().unwrap();
        let cam = PinholeCamera {
            intrinsics: Intrinsics::from_hfov(64, 48, 60.0),
            width: 64,
            height: 48,
            cam_to_world: look_at(DVec3::new(1.0, 1.0, 1.0), DVec3::ZERO, DVec3::Z).unwrap(),
        };
        let frames = vec![Frame::new("a", &cam)];
        let path = dir.path().join("transforms.json");
        write_transforms_json(&path, &frames, |_| true).unwrap();
        let j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let m = &j["frames"][0]["transform_matrix"];
        // OpenGL cameras look down -z: the third column is minus the viewing direction.
        let view = (DVec3::ZERO - DVec3::ONE).normalize();
        let col2 = DVec3::new(m[0][2].as_f64().unwrap(), m[1][2].as_f64().unwrap(), m[2][2].as_f64().unwrap());
        assert!((col2 + view).length() < 1e-9);
        assert_eq!(j["frames"][0]["depth_file_path"], "depth/a.npy");
        assert_eq!(j["frames"][0]["cx"].as_f64().unwrap(), cam.intrinsics.cx + 0.5);
    }
}
