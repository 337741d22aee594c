//! Camera rotations from pairwise relative rotations: which pairs agree with the others
//! (a spanning forest of the most trusted ones as the reference), and one rotation per camera
//! that agrees best with all of them (robust chordal averaging). `reconstruct` uses both on the
//! pairs keypoints placed, so the global alignment starts from, and keeps, rotations that owe
//! nothing to the network's depth.

use crate::union_find::UnionFind;
use dens3r_geom::transform::{nearest_rotation, rotation_angle_deg};
use glam::DMat3;

/// Which relative rotations agree with the others. `edges[k] = (i, j, r, weight)` says
/// `x_i = r x_j` (camera `j`'s frame into camera `i`'s) with trust `weight` (e.g. inlier
/// matches). An edge is kept when its [`rotation_disagreements`] is at most `max_deg`. A
/// confident but wrong placement, such as repeated texture matched across two sides of an
/// object, contradicts the chain of stronger pairs around it and is left out.
pub fn consistent_rotations(n: usize, edges: &[(usize, usize, DMat3, f64)], max_deg: f64) -> Vec<bool> {
    rotation_disagreements(n, edges).iter().map(|d| d.is_some_and(|d| d <= max_deg)).collect()
}

/// How far (degrees) each edge's rotation is from what the others imply (`edges` as in
/// [`consistent_rotations`]): the maximum spanning forest of the weights fixes one rotation
/// per image, and each edge is compared with the rotation between its images' (0 for the
/// forest's own edges, which only count as `Some(0.0)`). `None` for an edge naming an image
/// outside `0..n`.
pub fn rotation_disagreements(n: usize, edges: &[(usize, usize, DMat3, f64)]) -> Vec<Option<f64>> {
    rotation_residuals(&spanning_rotations(n, edges), edges)
}

/// How far (degrees) each edge's rotation (`edges` as in [`consistent_rotations`]) is from the
/// one between its cameras' rotations `w` (camera-to-world, e.g. [`average_rotations`]');
/// `None` where either camera has none.
pub fn rotation_residuals(w: &[Option<DMat3>], edges: &[(usize, usize, DMat3, f64)]) -> Vec<Option<f64>> {
    edges
        .iter()
        .map(|&(i, j, r, _)| {
            let (wi, wj) = (w.get(i).copied().flatten()?, w.get(j).copied().flatten()?);
            Some(rotation_angle_deg(&((wi.transpose() * wj).transpose() * r)))
        })
        .collect()
}

/// Camera-to-world rotations (one common, arbitrary world frame) that best agree with the
/// relative rotations of `edges` (as in [`consistent_rotations`]: `x_i = r x_j`, so
/// `w_j = w_i r`): started from the maximum spanning forest of the weights, then each camera in
/// turn set to the chordal mean `proj_SO3(sum k (w_i r))` over its edges, with weights
/// `weight / (1 + (d / 5 deg)^2)` for an edge `d` degrees from the current cameras (a wrong
/// edge barely pulls), for `iterations` sweeps. Only the cameras of the largest group the
/// edges connect get one (the others would need a frame of their own); `None` for the rest.
pub fn average_rotations(n: usize, edges: &[(usize, usize, DMat3, f64)], iterations: usize) -> Vec<Option<DMat3>> {
    let mut sets = UnionFind::new(n);
    let mut edges: Vec<(usize, usize, DMat3, f64)> =
        edges.iter().copied().filter(|e| e.0 < n && e.1 < n && e.0 != e.1 && e.3 > 0.0).collect();
    edges.iter().for_each(|e| {
        sets.union(e.0, e.1);
    });
    let mut size = vec![0usize; n];
    edges.iter().flat_map(|e| [e.0, e.1]).collect::<std::collections::BTreeSet<_>>().iter().for_each(|&k| {
        size[sets.find(k)] += 1;
    });
    let Some(largest) = (0..n).filter(|&k| size[k] > 0).max_by_key(|&k| (size[k], std::cmp::Reverse(k))) else {
        return vec![None; n];
    };
    edges.retain(|e| sets.find(e.0) == largest);
    let mut w = spanning_rotations(n, &edges);
    for _ in 0..iterations {
        for k in 0..n {
            if w[k].is_none() {
                continue;
            }
            let mut sum = DMat3::ZERO;
            for &(i, j, r, weight) in &edges {
                // The rotation edge (i, j) implies for camera k.
                let implied = match (i == k, j == k) {
                    (false, true) => w[i].map(|wi| wi * r),
                    (true, false) => w[j].map(|wj| wj * r.transpose()),
                    _ => None,
                };
                if let (Some(m), Some(wk)) = (implied, w[k]) {
                    let d = rotation_angle_deg(&(wk.transpose() * m));
                    sum += m * (weight / (1.0 + (d / 5.0).powi(2)));
                }
            }
            if sum != DMat3::ZERO {
                w[k] = Some(nearest_rotation(sum));
            }
        }
    }
    w
}

/// Camera-to-root rotations along the maximum spanning forest of the weights (`w_j = w_i r`).
fn spanning_rotations(n: usize, edges: &[(usize, usize, DMat3, f64)]) -> Vec<Option<DMat3>> {
    let mut order: Vec<usize> = (0..edges.len()).collect();
    order.sort_by(|&a, &b| edges[b].3.total_cmp(&edges[a].3));
    let mut sets = UnionFind::new(n);
    let mut adj: Vec<Vec<(usize, DMat3)>> = vec![Vec::new(); n];
    for &k in &order {
        let (i, j, r, _) = edges[k];
        if i < n && j < n && sets.union(i, j) {
            adj[i].push((j, r));
            adj[j].push((i, r.transpose()));
        }
    }
    let mut w: Vec<Option<DMat3>> = vec![None; n];
    for root in 0..n {
        if w[root].is_some() || adj[root].is_empty() {
            continue;
        }
        w[root] = Some(DMat3::IDENTITY);
        let mut stack = vec![root];
        while let Some(i) = stack.pop() {
            let wi = w[i].expect("set before it is stacked");
            for &(j, r) in &adj[i] {
                if w[j].is_none() {
                    w[j] = Some(wi * r);
                    stack.push(j);
                }
            }
        }
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;
    use dens3r_geom::transform::axis_angle;
    use glam::DVec3;

    /// Eight cameras on a circle, 45 degrees apart, as camera-to-world rotations.
    fn circle(k: usize) -> DMat3 {
        axis_angle(DVec3::Y, (45.0 * k as f64).to_radians())
    }

    /// Neighbours and second neighbours on [`circle`], measured with errors of 0.2 to 1.4
    /// degrees about assorted axes (the edge's index picks it), trust falling along the
    /// list; plus one pair across the circle placed 120 degrees wrong with the fewest inliers.
    fn circle_edges() -> Vec<(usize, usize, DMat3, f64)> {
        let noise = |k: usize| {
            let axis = DVec3::new(1.0, 0.3 * k as f64, -0.5 + 0.2 * (k % 3) as f64).normalize();
            axis_angle(axis, (0.2 * (k % 8 + 1) as f64).to_radians())
        };
        let mut edges = Vec::new();
        for k in 0..8 {
            for d in [1, 2] {
                let (i, j) = (k, (k + d) % 8);
                // x_i = cam_i^T cam_j x_j (cameras to world).
                let e = edges.len();
                edges.push((i, j, noise(e) * circle(i).transpose() * circle(j), 100.0 - e as f64));
            }
        }
        let wrong = axis_angle(DVec3::X, 120f64.to_radians()) * circle(1).transpose() * circle(5);
        edges.push((1, 5, wrong, 30.0));
        edges
    }

    /// Only the wrong pair is left out at 15 degrees; a bound tighter than the measurement
    /// noise drops good pairs too.
    #[test]
    fn a_rotation_that_contradicts_the_circle_is_left_out() {
        let edges = circle_edges();
        let keep = consistent_rotations(8, &edges, 15.0);
        assert_eq!(keep.iter().filter(|&&k| !k).count(), 1, "{keep:?}");
        assert!(!keep[16]);
        assert!(consistent_rotations(8, &edges, 0.1).iter().filter(|&&k| !k).count() > 1);
    }

    /// Averaging over every pair, the wrong one included, brings the relative rotations of all
    /// 28 camera pairs closer to the truth than the spanning tree does (worst 1.0 against 2.9 degrees).
    #[test]
    fn averaging_beats_the_tree_and_shrugs_off_the_wrong_pair() {
        let edges = circle_edges();
        let worst = |w: &[Option<DMat3>]| -> f64 {
            let mut worst: f64 = 0.0;
            for i in 0..8 {
                for j in i + 1..8 {
                    let (wi, wj) = (w[i].unwrap(), w[j].unwrap());
                    let truth = circle(i).transpose() * circle(j);
                    worst = worst.max(rotation_angle_deg(&((wi.transpose() * wj).transpose() * truth)));
                }
            }
            worst
        };
        let (tree, avg) = (worst(&spanning_rotations(8, &edges)), worst(&average_rotations(8, &edges, 30)));
        eprintln!("worst relative rotation error: tree {tree:.3} deg, averaged {avg:.3} deg");
        assert!(avg < 1.2 && avg < 0.7 * tree, "tree {tree}, averaged {avg}");
        // A camera no pair reaches has no rotation, nor do those of a smaller separate group.
        let mut more = edges.clone();
        more.push((8, 9, DMat3::IDENTITY, 50.0));
        let w = average_rotations(11, &more, 5);
        assert!(w[..8].iter().all(Option::is_some) && w[8..].iter().all(Option::is_none));
    }
}
