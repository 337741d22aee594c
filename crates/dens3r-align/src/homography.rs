//! The plane-induced homography of two calibrated views and the poses it allows. Where the
//! part two views share is close to one plane (a wall, a table top, a facade), the essential
//! matrix is poorly conditioned: poses several degrees apart fit the epipolar constraint
//! alike. The homography of that plane is well conditioned there, and its decomposition gives
//! the candidate poses [`crate::epipolar`] weighs against each other.

use crate::epipolar::normalise;
use crate::ransac::ransac;
use crate::resection::jacobi_eigen;
use glam::{DMat3, DVec2, DVec3};
use glamx::DSvd3;

/// The homography `b ~ H a` of normalised correspondences by the direct linear transform
/// (Hartley-normalised); `None` under 4 correspondences or when degenerate.
pub fn homography_dlt(a: &[DVec2], b: &[DVec2]) -> Option<DMat3> {
    if a.len() < 4 || a.len() != b.len() {
        return None;
    }
    let (ta, na) = normalise(a)?;
    let (tb, nb) = normalise(b)?;
    let mut ata = vec![0.0; 81];
    let mut add = |row: [f64; 9]| {
        for r in 0..9 {
            for c in r..9 {
                ata[r * 9 + c] += row[r] * row[c];
            }
        }
    };
    for (p, q) in na.iter().zip(&nb) {
        add([-p.x, -p.y, -1.0, 0.0, 0.0, 0.0, q.x * p.x, q.x * p.y, q.x]);
        add([0.0, 0.0, 0.0, -p.x, -p.y, -1.0, q.y * p.x, q.y * p.y, q.y]);
    }
    for r in 0..9 {
        for c in 0..r {
            ata[r * 9 + c] = ata[c * 9 + r];
        }
    }
    let (vals, vecs) = jacobi_eigen(ata, 9);
    let k = (0..9).min_by(|&i, &j| vals[i].total_cmp(&vals[j]))?;
    let h: Vec<f64> = (0..9).map(|r| vecs[r * 9 + k]).collect();
    let hn = DMat3::from_cols(DVec3::new(h[0], h[3], h[6]), DVec3::new(h[1], h[4], h[7]), DVec3::new(h[2], h[5], h[8]));
    let h = tb.inverse() * hn * ta;
    (h.is_finite() && h.determinant().abs() > 1e-12).then_some(h)
}

/// Distance (normalised units) from `H a` to `b`; infinite for points sent to infinity.
pub fn transfer_error(h: &DMat3, a: DVec2, b: DVec2) -> f64 {
    let p = *h * a.extend(1.0);
    if p.z.abs() < 1e-12 {
        return f64::INFINITY;
    }
    (DVec2::new(p.x / p.z, p.y / p.z) - b).length()
}

/// The homography most correspondences agree with (transfer error under `threshold`,
/// normalised units): four-point samples in [`ransac`], `iterations` at most; with its
/// inliers. `None` under 8 correspondences.
pub fn homography_ransac(
    a: &[DVec2],
    b: &[DVec2],
    threshold: f64,
    iterations: usize,
    seed: u64,
) -> Option<(DMat3, Vec<bool>)> {
    let n = a.len();
    if n < 8 || b.len() != n {
        return None;
    }
    let score = |h: &DMat3| -> (usize, Vec<bool>) {
        let m: Vec<bool> = a.iter().zip(b).map(|(&p, &q)| transfer_error(h, p, q) < threshold).collect();
        (m.iter().filter(|&&x| x).count(), m)
    };
    ransac(a, b, 4, iterations, seed, homography_dlt, score).map(|(_, h, m)| (h, m))
}

/// The poses `(R, t)` (`x_b = R x_a + t`, `t` of unit length) that the homography `b ~ H a`
/// of a plane allows, by the SVD decomposition of Faugeras (as in Ma, Soatto, Kosecka and
/// Sastry, section 5.3): four solutions, two of them with the plane in front of camera `a` for
/// the points `a` (normalised coordinates); those two are returned. Empty for a pure rotation
/// (no translation to read) or a degenerate `H`.
pub fn homography_poses(h: &DMat3, a: &[DVec2], b: &[DVec2]) -> Vec<(DMat3, DVec3)> {
    let svd = DSvd3::from_matrix(*h);
    if !(svd.s.y > 1e-12 && svd.s.y.is_finite()) {
        return Vec::new();
    }
    let mut h = *h / svd.s.y;
    // The sign that puts the points in front: b^T H a > 0 for most.
    let positive = a.iter().zip(b).filter(|(p, q)| q.extend(1.0).dot(h * p.extend(1.0)) > 0.0).count();
    if positive * 2 < a.len() {
        h = -h;
    }
    let (l1, l3) = ((svd.s.x / svd.s.y).powi(2), (svd.s.z / svd.s.y).powi(2));
    if l1 - l3 < 1e-10 {
        return Vec::new();
    }
    let v = svd.vt.transpose();
    let (v1, v2, v3) = (v.x_axis, v.y_axis, v.z_axis);
    let (p, q, d) = ((1.0 - l3).max(0.0).sqrt(), (l1 - 1.0).max(0.0).sqrt(), (l1 - l3).sqrt());
    let mut out = Vec::new();
    for u in [(v1 * p + v3 * q) / d, (v1 * p - v3 * q) / d] {
        let um = DMat3::from_cols(v2, u, v2.cross(u));
        let wm = DMat3::from_cols(h * v2, h * u, (h * v2).cross(h * u));
        let r = wm * um.transpose();
        let n = v2.cross(u);
        let t = (h - r) * n;
        if !(r.determinant() > 0.5 && t.length() > 1e-12) {
            continue;
        }
        // Of (t, n) and (-t, -n), the one with the plane in front of camera a: n . a > 0.
        let front = a.iter().filter(|p| n.dot(p.extend(1.0)) > 0.0).count();
        let (t, _n) = if front * 2 >= a.len() { (t, n) } else { (-t, -n) };
        out.push((r, t.normalize()));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resection::SplitMix;
    use dens3r_geom::transform::{axis_angle, rotation_angle_deg};

    /// Points of the plane z = 3 + 0.4 x seen by two cameras: the homography maps one view's
    /// points onto the other's exactly, and one of the two poses it allows is the true one.
    #[test]
    fn a_plane_gives_its_homography_and_the_pose() {
        let r = axis_angle(DVec3::new(0.2, 1.0, 0.1).normalize(), 0.45);
        let t = DVec3::new(-0.6, 0.1, 0.25);
        let mut rng = SplitMix(11);
        let mut u = || rng.below(1_000_000) as f64 / 1e6;
        let (mut a, mut b) = (Vec::new(), Vec::new());
        while a.len() < 60 {
            let (px, py) = (u() - 0.3, u() - 0.5);
            let z = 3.0 / (1.0 - 0.4 * px);
            let y = r * DVec3::new(px * z, py * z, z) + t;
            a.push(DVec2::new(px, py));
            b.push(DVec2::new(y.x / y.z, y.y / y.z));
        }
        let (h, inl) = homography_ransac(&a, &b, 1e-4, 500, 0).unwrap();
        assert!(inl.iter().all(|&m| m));
        assert!(a.iter().zip(&b).all(|(p, q)| transfer_error(&h, *p, *q) < 1e-9));
        let poses = homography_poses(&h, &a, &b);
        assert_eq!(poses.len(), 2);
        let best = poses
            .iter()
            .map(|(rr, tt)| (rotation_angle_deg(&(rr.transpose() * r)), tt.dot(t.normalize())))
            .min_by(|x, y| x.0.total_cmp(&y.0))
            .unwrap();
        assert!(best.0 < 1e-6 && best.1 > 1.0 - 1e-9, "{best:?}");
    }
}
