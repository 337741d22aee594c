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

/// Per image, its keypoints (POINTS2D) in track order `(x, y, point id)` (COLMAP's pixel
/// convention: +0.5), and per point its track `(image id, keypoint index)`; ids are 1-based.
type Layout = (Vec<Vec<(f64, f64, usize)>>, Vec<Vec<(usize, usize)>>);

/// The keypoints and tracks of a COLMAP model of `frames` and `points` (checked: every
/// observation names a frame).
fn layout(dir: &Path, frames: &[Frame], points: &[TrackPoint]) -> Result<Layout, SceneError> {
    for (t, p) in points.iter().enumerate() {
        if let Some(&(f, _)) = p.observations.iter().find(|(f, _)| *f >= frames.len()) {
            return Err(SceneError::new(
                dir,
                format!("track {t} observes frame {f}, but there are {} frames", frames.len()),
            ));
        }
    }
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
    Ok((kps, track_refs))
}

/// A frame's world-to-camera rotation (unit quaternion, `w >= 0`) and translation.
fn colmap_pose(f: &Frame) -> (DQuat, DVec3) {
    let w2c = rigid_inverse(&f.camera().cam_to_world);
    let q = DQuat::from_mat3(&DMat3::from_mat4(w2c)).normalize();
    (if q.w < 0.0 { -q } else { q }, w2c.w_axis.truncate())
}

/// Writes COLMAP's binary model, `cameras.bin`, `images.bin` and `points3D.bin`, into `dir`:
/// the same model as [`write_colmap_text`] (PINHOLE cameras, little-endian, as COLMAP's
/// `model_converter` writes it).
pub fn write_colmap_binary(dir: &Path, frames: &[Frame], points: &[TrackPoint]) -> Result<(), SceneError> {
    let (kps, track_refs) = layout(dir, frames, points)?;
    let mut cams = Vec::new();
    cams.extend((frames.len() as u64).to_le_bytes());
    let mut imgs = Vec::new();
    imgs.extend((frames.len() as u64).to_le_bytes());
    for (i, f) in frames.iter().enumerate() {
        let k = f.camera().intrinsics;
        cams.extend((i as i32 + 1).to_le_bytes());
        cams.extend(1i32.to_le_bytes()); // PINHOLE
        cams.extend((f.width as u64).to_le_bytes());
        cams.extend((f.height as u64).to_le_bytes());
        for v in [k.fx, k.fy, k.cx + 0.5, k.cy + 0.5] {
            cams.extend(v.to_le_bytes());
        }
        let (q, t) = colmap_pose(f);
        imgs.extend((i as u32 + 1).to_le_bytes());
        for v in [q.w, q.x, q.y, q.z, t.x, t.y, t.z] {
            imgs.extend(v.to_le_bytes());
        }
        imgs.extend((i as u32 + 1).to_le_bytes());
        imgs.extend(f.image.as_bytes());
        imgs.push(0);
        imgs.extend((kps[i].len() as u64).to_le_bytes());
        for &(x, y, id) in &kps[i] {
            imgs.extend(x.to_le_bytes());
            imgs.extend(y.to_le_bytes());
            imgs.extend((id as u64).to_le_bytes());
        }
    }
    let mut pts = Vec::new();
    pts.extend((points.len() as u64).to_le_bytes());
    for (t, p) in points.iter().enumerate() {
        pts.extend((t as u64 + 1).to_le_bytes());
        for v in [p.xyz.x, p.xyz.y, p.xyz.z] {
            pts.extend(v.to_le_bytes());
        }
        pts.extend(p.rgb);
        pts.extend(p.error.to_le_bytes());
        pts.extend((track_refs[t].len() as u64).to_le_bytes());
        for &(im, idx) in &track_refs[t] {
            pts.extend((im as u32).to_le_bytes());
            pts.extend((idx as u32).to_le_bytes());
        }
    }
    for (name, bytes) in [("cameras.bin", cams), ("images.bin", imgs), ("points3D.bin", pts)] {
        write_atomic(&dir.join(name), |w| std::io::Write::write_all(w, &bytes))?;
    }
    Ok(())
}

/// Writes `cameras.txt`, `images.txt` and `points3D.txt` into `dir` (created if needed).
/// Image and camera ids are frame index + 1; point ids are track index + 1.
pub fn write_colmap_text(dir: &Path, frames: &[Frame], points: &[TrackPoint]) -> Result<(), SceneError> {
    let (kps, track_refs) = layout(dir, frames, points)?;
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
        let (q, t) = colmap_pose(f);
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
        let (frames, points) = two_view_model();
        let cams: Vec<PinholeCamera> = frames.iter().map(Frame::camera).collect();
        let (x, obs) = (points[0].xyz, points[0].observations.clone());
        let track = TrackPoint { error: 0.0, ..points[0].clone() };
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

    /// Two cameras and one point observed by both, as in the text test.
    fn two_view_model() -> (Vec<Frame>, Vec<TrackPoint>) {
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
        let obs = cams
            .iter()
            .enumerate()
            .map(|(i, c)| (i, c.intrinsics.project(rigid_inverse(&c.cam_to_world).transform_point3(x))))
            .collect();
        (frames, vec![TrackPoint { xyz: x, rgb: [10, 20, 30], error: 0.25, observations: obs }])
    }

    /// The binary model, parsed as COLMAP's documentation lays it out (read_write_model.py),
    /// holds the text model's numbers; and where Debian's `colmap` is installed, COLMAP itself
    /// converts it to the same text.
    #[test]
    fn colmap_binary_holds_the_text_model() {
        let (frames, points) = two_view_model();
        let dir = tempfile::tempdir().unwrap();
        write_colmap_binary(dir.path(), &frames, &points).unwrap();
        write_colmap_text(dir.path(), &frames, &points).unwrap();
        let bytes = |f: &str| std::fs::read(dir.path().join(f)).unwrap();
        struct Reader(Vec<u8>, usize);
        impl Reader {
            fn take<const N: usize>(&mut self) -> [u8; N] {
                let out = self.0[self.1..self.1 + N].try_into().unwrap();
                self.1 += N;
                out
            }
            fn u64(&mut self) -> u64 {
                u64::from_le_bytes(self.take())
            }
            fn u32(&mut self) -> u32 {
                u32::from_le_bytes(self.take())
            }
            fn f64(&mut self) -> f64 {
                f64::from_le_bytes(self.take())
            }
        }
        // A text model file's data lines as numbers (names dropped).
        let numbers = |path: &Path| -> Vec<Vec<f64>> {
            std::fs::read_to_string(path)
                .unwrap()
                .lines()
                .filter(|l| !l.starts_with('#'))
                .map(|l| l.split(' ').filter_map(|v| v.parse().ok()).collect())
                .collect()
        };
        let text = |f: &str| numbers(&dir.path().join(f));
        let mut c = Reader(bytes("cameras.bin"), 0);
        let cam_rows = text("cameras.txt");
        assert_eq!(c.u64(), 2);
        for row in &cam_rows {
            let (id, model, w, h) = (c.u32(), c.u32(), c.u64(), c.u64());
            let params = [c.f64(), c.f64(), c.f64(), c.f64()];
            assert_eq!((id as f64, model, w as f64, h as f64), (row[0], 1, row[1], row[2]));
            assert_eq!(&params[..], &row[3..7]);
        }
        assert_eq!(c.1, c.0.len());
        let mut im = Reader(bytes("images.bin"), 0);
        let img_rows = text("images.txt");
        assert_eq!(im.u64(), 2);
        for k in 0..2 {
            let id = im.u32();
            let pose: Vec<f64> = (0..7).map(|_| im.f64()).collect();
            let cam = im.u32();
            let end = im.0[im.1..].iter().position(|&b| b == 0).unwrap();
            let name = String::from_utf8(im.0[im.1..im.1 + end].to_vec()).unwrap();
            im.1 += end + 1;
            assert_eq!(name, frames[k].image);
            assert_eq!((id as f64, cam as f64), (img_rows[2 * k][0], img_rows[2 * k][8]));
            assert_eq!(&pose[..], &img_rows[2 * k][1..8]);
            assert_eq!(im.u64(), 1);
            let (x, y, pid) = (im.f64(), im.f64(), im.u64());
            assert_eq!(vec![x, y, pid as f64], img_rows[2 * k + 1]);
        }
        let mut p = Reader(bytes("points3D.bin"), 0);
        let row = &text("points3D.txt")[0];
        assert_eq!((p.u64(), p.u64()), (1, 1));
        let xyz = [p.f64(), p.f64(), p.f64()];
        let rgb: [u8; 3] = p.take();
        let err = p.f64();
        assert_eq!(&xyz[..], &row[1..4]);
        assert_eq!((rgb, err), ([10, 20, 30], row[7]));
        assert_eq!(p.u64(), 2);
        let track: Vec<f64> = (0..4).map(|_| p.u32() as f64).collect();
        assert_eq!(&track[..], &row[8..]);
        assert_eq!(p.1, p.0.len());

        // COLMAP's own reading, where it is installed.
        let out = tempfile::tempdir().unwrap();
        let bin = tempfile::tempdir().unwrap();
        for f in ["cameras.bin", "images.bin", "points3D.bin"] {
            std::fs::copy(dir.path().join(f), bin.path().join(f)).unwrap();
        }
        let run = std::process::Command::new("colmap")
            .args(["model_converter", "--output_type", "TXT", "--input_path"])
            .arg(bin.path())
            .arg("--output_path")
            .arg(out.path())
            .output();
        match run {
            Ok(o) if o.status.success() => {
                let theirs = |f: &str| numbers(&out.path().join(f));
                // COLMAP writes its maps in its own order: compared by id (images as their
                // two lines together).
                let by_id = |rows: Vec<Vec<f64>>, per: usize| -> Vec<Vec<f64>> {
                    let mut groups: Vec<Vec<f64>> = rows.chunks(per).map(|c| c.concat()).collect();
                    groups.sort_by(|a, b| a[0].total_cmp(&b[0]));
                    groups
                };
                for (f, per) in [("cameras.txt", 1), ("images.txt", 2), ("points3D.txt", 1)] {
                    let (a, b) = (by_id(text(f), per), by_id(theirs(f), per));
                    assert_eq!(a.len(), b.len(), "{f}");
                    for (ra, rb) in a.iter().zip(&b) {
                        assert!(
                            ra.len() == rb.len()
                                && ra.iter().zip(rb).all(|(x, y)| (x - y).abs() <= 1e-9 * x.abs().max(1.0)),
                            "{f}: {ra:?} vs COLMAP's {rb:?}"
                        );
                    }
                }
            }
            _ => eprintln!(
                "skipped COLMAP's reading of the binary model: no `colmap` (scripts/bench-setup.sh installs it)"
            ),
        }
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
