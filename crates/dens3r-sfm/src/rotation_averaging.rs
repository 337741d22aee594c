//! Stage 3: rotation averaging. The edges' relative rotations checked against a spanning
//! forest of the strongest ([`Edge::weight`]: inliers times inlier share), averaged into one camera-to-world rotation per view
//! (robust chordal averaging, [`dens3r_align::average_rotations`]), and the edges that still
//! disagree with the averaged rotations dropped before everything after.

use crate::view_graph::Edge;
use dens3r_align::rotations::{average_rotations, consistent_rotations, rotation_residuals};
use glam::DMat3;

/// Rotation averaging settings.
#[derive(Debug, Clone, PartialEq)]
pub struct RotationOptions {
    /// An edge further than this (degrees) from the spanning forest's rotations is dropped
    /// before averaging.
    pub max_disagreement_deg: f64,
    /// An edge further than this (degrees) from the averaged rotations is dropped after.
    pub max_residual_deg: f64,
    /// Averaging sweeps.
    pub sweeps: usize,
}

impl Default for RotationOptions {
    fn default() -> Self {
        Self { max_disagreement_deg: 15.0, max_residual_deg: 5.0, sweeps: 40 }
    }
}

/// Camera-to-world rotations of the largest group of views the edges connect (`None` for the
/// others), and which edges agree with them.
#[derive(Debug, Clone)]
pub struct Rotations {
    /// One per view.
    pub world: Vec<Option<DMat3>>,
    /// One per edge: kept (agrees with `world`).
    pub kept: Vec<bool>,
}

/// Averages the rotations of `edges` over `n` views.
pub fn average(n: usize, edges: &[Edge], opts: &RotationOptions) -> Rotations {
    // average_rotations' edges say x_i = r x_j: the transpose of an edge's rotation.
    let rel: Vec<(usize, usize, DMat3, f64)> =
        edges.iter().map(|e| (e.i, e.j, e.rotation.transpose(), e.weight())).collect();
    let consistent = consistent_rotations(n, &rel, opts.max_disagreement_deg);
    let mut kept = consistent.clone();
    let mut world = vec![None; n];
    for _ in 0..2 {
        let used: Vec<_> = rel.iter().zip(&kept).filter(|(_, &k)| k).map(|(e, _)| *e).collect();
        world = average_rotations(n, &used, opts.sweeps);
        // Edges outside the averaged group keep the spanning forest's verdict, so the other
        // groups are still seen as groups.
        let residuals = rotation_residuals(&world, &rel);
        kept = residuals.iter().zip(&consistent).map(|(r, &c)| r.map_or(c, |d| d <= opts.max_residual_deg)).collect();
    }
    Rotations { world, kept }
}
