//! Camera-pose metrics that need no gauge: relative rotation and translation-direction errors
//! over every pair of views (the measure of pairwise pose benchmarks such as CO3D's RRA / RTA),
//! and focal errors relative to the image width.

use crate::camera::PinholeCamera;
use crate::transform::rotation_angle_deg;
use glam::{DMat3, DVec3};

/// Errors of estimated cameras against the truth, over all pairs `i < j`.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraMetrics {
    /// Angle of `R_ij,est^T R_ij,true` per pair, degrees (`R_ij` = rotation of j in i's frame).
    pub rotation_deg: Vec<f64>,
    /// Angle between the estimated and true directions of j's centre in i's frame, degrees
    /// (up to the scene's scale); pairs with a zero true baseline are left out.
    pub translation_deg: Vec<f64>,
    /// `|f_est / w_est - f_true / w_true| / (f_true / w_true)` per view (fx; sizes may differ).
    pub focal_rel: Vec<f64>,
}

/// Relative pose of camera `b` in camera `a`'s frame: rotation and the direction of b's centre.
fn relative(a: &PinholeCamera, b: &PinholeCamera) -> (DMat3, DVec3) {
    let ra = DMat3::from_mat4(a.cam_to_world);
    let rb = DMat3::from_mat4(b.cam_to_world);
    (ra.transpose() * rb, ra.transpose() * (b.center() - a.center()))
}

/// Compares `est` with `truth` (the same views in the same order).
pub fn camera_metrics(est: &[PinholeCamera], truth: &[PinholeCamera]) -> CameraMetrics {
    assert_eq!(est.len(), truth.len(), "one estimate per true camera");
    let mut m = CameraMetrics { rotation_deg: Vec::new(), translation_deg: Vec::new(), focal_rel: Vec::new() };
    for i in 0..truth.len() {
        let fe = est[i].intrinsics.fx / est[i].width as f64;
        let ft = truth[i].intrinsics.fx / truth[i].width as f64;
        m.focal_rel.push((fe - ft).abs() / ft);
        for j in i + 1..truth.len() {
            let (re, te) = relative(&est[i], &est[j]);
            let (rt, tt) = relative(&truth[i], &truth[j]);
            m.rotation_deg.push(rotation_angle_deg(&(re.transpose() * rt)));
            if tt.length() > 1e-12 {
                let cos = te.normalize_or_zero().dot(tt.normalize());
                m.translation_deg.push(cos.clamp(-1.0, 1.0).acos().to_degrees());
            }
        }
    }
    m
}

/// Median of a list (NaN when empty).
pub fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    crate::focal::median(&mut v).unwrap_or(f64::NAN)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};
    use crate::transform::axis_angle;
    use glam::DMat4;

    fn ring(n: usize, fx: f64) -> Vec<PinholeCamera> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.4;
                let eye = DVec3::new(3.0 * a.cos(), -0.5, 3.0 * a.sin());
                PinholeCamera {
                    intrinsics: Intrinsics { fx, fy: fx, cx: 32.0, cy: 24.0 },
                    width: 64,
                    height: 48,
                    cam_to_world: look_at(eye, DVec3::ZERO, DVec3::new(0.0, -1.0, 0.0)).unwrap(),
                }
            })
            .collect()
    }

    #[test]
    fn a_similarity_of_the_truth_scores_zero_and_a_turned_view_scores_its_angle() {
        let truth = ring(4, 50.0);
        // Any rotation, translation and scale of the whole rig leaves every error at zero.
        let g = DMat4::from_mat3(axis_angle(DVec3::new(1.0, 2.0, 0.5).normalize(), 0.9));
        let est: Vec<PinholeCamera> = truth
            .iter()
            .map(|c| {
                let mut c = *c;
                let mut p = g * c.cam_to_world;
                p.w_axis = (g.transform_point3(c.center()) * 2.5 + DVec3::new(1.0, -2.0, 3.0)).extend(1.0);
                c.cam_to_world = p;
                c
            })
            .collect();
        let m = camera_metrics(&est, &truth);
        assert_eq!((m.rotation_deg.len(), m.translation_deg.len(), m.focal_rel.len()), (6, 6, 4));
        assert!(m.rotation_deg.iter().chain(&m.translation_deg).all(|&e| e < 1e-5), "{m:?}");
        assert!(m.focal_rel.iter().all(|&e| e < 1e-12));
        // Turning one camera by 7 degrees about its own axis: its 3 pairs err by 7 degrees.
        let mut turned = truth.clone();
        let r = DMat3::from_mat4(turned[2].cam_to_world) * axis_angle(DVec3::Z, 7f64.to_radians());
        let c = turned[2].center();
        turned[2].cam_to_world = DMat4::from_mat3(r);
        turned[2].cam_to_world.w_axis = c.extend(1.0);
        turned[2].intrinsics.fx = 55.0;
        let m = camera_metrics(&turned, &truth);
        let bad: Vec<f64> = m.rotation_deg.iter().copied().filter(|&e| e > 1e-6).collect();
        assert_eq!(bad.len(), 3);
        assert!(bad.iter().all(|e| (e - 7.0).abs() < 1e-6), "{bad:?}");
        assert!((m.focal_rel[2] - 0.1).abs() < 1e-12 && (median(&m.rotation_deg) - 3.5).abs() < 1e-6);
    }
}
