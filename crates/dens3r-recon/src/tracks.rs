//! Match tracks after alignment become 3-D points (COLMAP's points3D): triangulated from the
//! aligned cameras, so that they agree with the poses (a view's depth alone puts them 5-15
//! pixels off in the other views).

use dens3r_align::matching::{tracks, Match};
use dens3r_align::Alignment;
use dens3r_geom::camera::triangulate;
use dens3r_geom::DVec3;
use dens3r_scene::export::TrackPoint;
use image::RgbImage;

/// How tracks become points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackOptions {
    /// Shortest track exported as a point.
    pub min_track: usize,
    /// A track is triangulated when two of its rays are at least this far apart (degrees) and
    /// it reprojects within [`Self::max_error_px`]; otherwise its point is the most confident
    /// view's aligned depth, as before triangulation.
    pub min_angle_deg: f64,
    /// Largest mean reprojection error of a triangulated point, pixels.
    pub max_error_px: f64,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self { min_track: 2, min_angle_deg: 2.0, max_error_px: 3.0 }
    }
}

/// Tracks with one keypoint per image become 3-D points: triangulated from the cameras where
/// [`TrackOptions`] allows, else the most confident keypoint's aligned depth. Returns the
/// points and, for each, whether it was triangulated.
pub fn track_points(
    a: &Alignment,
    rgb: &[RgbImage],
    matches: &[(usize, usize, Vec<Match>)],
    opts: &TrackOptions,
) -> (Vec<TrackPoint>, Vec<bool>) {
    tracks(matches, opts.min_track.max(2))
        .into_iter()
        .filter(|t| t.windows(2).all(|w| w[0].0 != w[1].0)) // sorted: repeats are adjacent
        .filter_map(|t| {
            let views: Vec<_> = t.iter().map(|&(k, (x, y))| (a.views[k].camera, (x as f64, y as f64))).collect();
            let tri = triangulate(&views)
                .filter(|p| p.max_angle_deg >= opts.min_angle_deg && p.error_px <= opts.max_error_px);
            let (xyz, k, (x, y), error) = match tri {
                Some(p) => {
                    // The colour of the view that sees it nearest.
                    let &(k, xy) = t
                        .iter()
                        .min_by(|u, v| {
                            let d = |&(k, _): &(usize, _)| a.views[k].camera.center().distance(p.xyz);
                            d(u).total_cmp(&d(v))
                        })
                        .expect("tracks have two views");
                    (p.xyz, k, xy, Some(p.error_px))
                }
                None => {
                    let world = |&(k, (x, y)): &(usize, (usize, usize))| {
                        let v = &a.views[k];
                        let d = *v.depth.get(x, y);
                        (d > 0.0 && d.is_finite()).then(|| {
                            let c = v.camera.intrinsics.unproject(x as f64, y as f64) * d as f64;
                            (v.camera.cam_to_world.transform_point3(c), *v.conf.get(x, y))
                        })
                    };
                    let (best, (xyz, _)) = t
                        .iter()
                        .enumerate()
                        .filter_map(|(o, kp)| world(kp).map(|w| (o, w)))
                        .max_by(|a, b| a.1 .1.total_cmp(&b.1 .1))?;
                    let (k, xy) = t[best];
                    (xyz, k, xy, None)
                }
            };
            // A triangulated point's error comes with it (and it is in front of every view).
            let triangulated = error.is_some();
            let error = match error {
                Some(e) => e,
                None => {
                    let mut err = 0.0;
                    for &(k, (x, y)) in &t {
                        let cam = &a.views[k].camera;
                        let c: DVec3 = cam.world_to_cam().transform_point3(xyz);
                        if c.z <= 0.0 {
                            return None;
                        }
                        let (u, v) = cam.intrinsics.project(c);
                        err += (u - x as f64).hypot(v - y as f64);
                    }
                    err / t.len() as f64
                }
            };
            let point = TrackPoint {
                xyz,
                rgb: rgb[k].get_pixel(x as u32, y as u32).0,
                error,
                observations: t.iter().map(|&(k, (x, y))| (k, (x as f64, y as f64))).collect(),
            };
            Some((point, triangulated))
        })
        .unzip()
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_align::AlignedView;
    use dens3r_geom::camera::{look_at, Intrinsics, PinholeCamera};
    use dens3r_geom::Raster;

    /// Matches of each pair `(i, j, matches)`.
    type PairMatches = Vec<(usize, usize, Vec<Match>)>;

    /// Views of a 5 x 5 grid of points 3 away, each point matched between consecutive views at
    /// its rounded pixel; every view's depth is 10% long at those pixels.
    fn scene(eyes: &[DVec3], targets: &[DVec3]) -> (Alignment, PairMatches, Vec<DVec3>) {
        let k = Intrinsics::from_hfov(320, 240, 60.0);
        let pts: Vec<DVec3> = (0..25)
            .map(|i| DVec3::new((i % 5) as f64 * 0.3 - 0.6, (i / 5) as f64 * 0.3 - 0.6, 3.0 + 0.1 * (i % 3) as f64))
            .collect();
        let cams: Vec<PinholeCamera> = eyes
            .iter()
            .zip(targets)
            .map(|(&e, &t)| PinholeCamera {
                intrinsics: k,
                width: 320,
                height: 240,
                cam_to_world: look_at(e, t, DVec3::NEG_Y).unwrap(),
            })
            .collect();
        let pixel = |c: &PinholeCamera, p: DVec3| {
            let (u, v) = k.project(c.world_to_cam().transform_point3(p));
            (u.round() as usize, v.round() as usize)
        };
        let views = cams
            .iter()
            .map(|c| {
                let mut depth = Raster::filled(320, 240, 0.0f32);
                for &p in &pts {
                    let (x, y) = pixel(c, p);
                    // The depth along the pixel's own ray that reaches the point's distance, 10% long.
                    let z = c.world_to_cam().transform_point3(p).length() / k.unproject(x as f64, y as f64).length();
                    *depth.get_mut(x, y) = (1.1 * z) as f32;
                }
                AlignedView { camera: *c, depth, conf: Raster::filled(320, 240, 2.0) }
            })
            .collect();
        let matches = (0..cams.len() - 1)
            .map(|i| {
                let ms = pts
                    .iter()
                    .map(|&p| Match { a: pixel(&cams[i], p), b: pixel(&cams[i + 1], p), conf: 2.0 })
                    .collect();
                (i, i + 1, ms)
            })
            .collect();
        let a = Alignment { views, pair_transforms: Vec::new(), loss: (0.0, 0.0), warnings: Vec::new() };
        (a, matches, pts)
    }

    fn nearest(p: DVec3, truth: &[DVec3]) -> f64 {
        truth.iter().map(|t| t.distance(p)).fold(f64::INFINITY, f64::min)
    }

    /// Three cameras 0.5 apart: every track is triangulated, within 4 cm of its point (pixels
    /// rounded to whole ones: up to 3.5 cm of depth at this baseline) and within a pixel of its keypoints, where a view's 10%-long depth puts it 30 cm
    /// off. Three cameras turning about one centre cannot triangulate: the points then come
    /// from the depth, as before.
    #[test]
    fn tracks_triangulate_where_the_cameras_are_apart() {
        let rgb = vec![RgbImage::new(320, 240); 3];
        let eyes = [DVec3::new(-0.5, 0.0, 0.0), DVec3::ZERO, DVec3::new(0.5, 0.0, 0.0)];
        let at = [DVec3::new(0.0, 0.0, 3.0); 3];
        let (a, matches, truth) = scene(&eyes, &at);
        let (points, tri) = track_points(&a, &rgb, &matches, &TrackOptions::default());
        assert_eq!(points.len(), 25);
        assert!(tri.iter().all(|&t| t));
        for p in &points {
            assert_eq!(p.observations.len(), 3);
            assert!(nearest(p.xyz, &truth) < 0.04, "{:?} off by {}", p.xyz, nearest(p.xyz, &truth));
            assert!(p.error < 1.0, "{}", p.error);
        }

        let turned = [DVec3::new(-0.3, 0.0, 3.0), DVec3::new(0.0, 0.0, 3.0), DVec3::new(0.3, 0.0, 3.0)];
        let (a, matches, truth) = scene(&[DVec3::ZERO; 3], &turned);
        let (points, tri) = track_points(&a, &rgb, &matches, &TrackOptions::default());
        assert_eq!(points.len(), 25);
        assert!(tri.iter().all(|&t| !t));
        for p in &points {
            let off = nearest(p.xyz, &truth);
            assert!(off > 0.25 && off < 0.4, "{off}");
        }
    }
}
