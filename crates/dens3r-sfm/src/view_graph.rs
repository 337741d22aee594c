//! Stage 1: the view graph. Every candidate pair's keypoints matched (mutual nearest
//! neighbours with Lowe's ratio test) and verified by their epipolar geometry (essential
//! matrix or homography in RANSAC, at the views' focals): an edge keeps only the inlier matches
//! and the relative pose they give.

use dens3r_align::epipolar::{essential_ransac, EpipolarOptions};
use dens3r_align::keypoints::{match_mutual, Keypoints};
use glam::{DMat3, DVec2, DVec3};
use rayon::prelude::*;

/// Matching and verification settings.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewGraphOptions {
    /// Lowe's ratio test.
    pub ratio: f32,
    /// Fewest inlier matches for an edge.
    pub min_inliers: usize,
    /// Smallest share of a pair's matches that must be inliers.
    pub min_inlier_ratio: f64,
    /// Essential-matrix RANSAC.
    pub epipolar: EpipolarOptions,
}

impl Default for ViewGraphOptions {
    fn default() -> Self {
        Self { ratio: 0.8, min_inliers: 24, min_inlier_ratio: 0.2, epipolar: EpipolarOptions::default() }
    }
}

/// Putative matches of one pair `i < j`: keypoint indices `(in i, in j)`.
#[derive(Debug, Clone, PartialEq)]
pub struct PairMatches {
    /// First view.
    pub i: usize,
    /// Second view.
    pub j: usize,
    /// Matched keypoints.
    pub matches: Vec<(usize, usize)>,
}

/// A verified pair: `x_j = rotation * x_i + translation` (camera frames, OpenCV axes).
#[derive(Debug, Clone, PartialEq)]
pub struct Edge {
    /// First view.
    pub i: usize,
    /// Second view.
    pub j: usize,
    /// Camera `i`'s frame into camera `j`'s.
    pub rotation: DMat3,
    /// Unit translation in camera `j`'s frame.
    pub translation: DVec3,
    /// The inlier matches, keypoint indices `(in i, in j)`.
    pub inliers: Vec<(usize, usize)>,
    /// Putative matches the inliers were found among.
    pub matches: usize,
}

impl Edge {
    /// How far the edge is trusted: its inliers times their share of its matches. A pair
    /// matched across repeated texture (two sides of an object in one tiled photograph) can
    /// find as many inliers as a true neighbour, but among far more putative matches.
    pub fn weight(&self) -> f64 {
        let n = self.inliers.len() as f64;
        n * n / self.matches.max(1) as f64
    }
}

/// Putative matches of `pairs` (pairs with fewer than `min_inliers` matches are left out).
pub fn match_pairs(kps: &[Keypoints], pairs: &[(usize, usize)], opts: &ViewGraphOptions) -> Vec<PairMatches> {
    pairs
        .par_iter()
        .filter_map(|&(a, b)| {
            let (i, j) = (a.min(b), a.max(b));
            if i == j || j >= kps.len() {
                return None;
            }
            let matches = match_mutual(&kps[i], &kps[j], opts.ratio);
            (matches.len() >= opts.min_inliers).then_some(PairMatches { i, j, matches })
        })
        .collect()
}

/// A keypoint in normalised camera coordinates: `(xy - principal) / focal`.
pub fn normalised(xy: DVec2, principal: DVec2, focal: f64) -> DVec2 {
    (xy - principal) / focal
}

/// Verifies each pair's matches by its epipolar geometry at the views' `focals` and
/// `principal` points: the edges whose inliers pass [`ViewGraphOptions`]' bounds.
pub fn verify(
    kps: &[Keypoints],
    pairs: &[PairMatches],
    focals: &[f64],
    principal: &[DVec2],
    opts: &ViewGraphOptions,
) -> Vec<Edge> {
    pairs
        .par_iter()
        .filter_map(|p| {
            let (fi, fj) = (focals[p.i], focals[p.j]);
            let a: Vec<DVec2> = p.matches.iter().map(|m| normalised(kps[p.i].xy[m.0], principal[p.i], fi)).collect();
            let b: Vec<DVec2> = p.matches.iter().map(|m| normalised(kps[p.j].xy[m.1], principal[p.j], fj)).collect();
            let pose = essential_ransac(&a, &b, (fi * fj).sqrt(), &opts.epipolar)?;
            let inliers: Vec<(usize, usize)> =
                p.matches.iter().zip(&pose.inliers).filter(|(_, &ok)| ok).map(|(m, _)| *m).collect();
            let enough = inliers.len() >= opts.min_inliers
                && inliers.len() as f64 >= opts.min_inlier_ratio * p.matches.len() as f64;
            let matches = p.matches.len();
            enough.then_some(Edge {
                i: p.i,
                j: p.j,
                rotation: pose.rotation,
                translation: pose.translation,
                inliers,
                matches,
            })
        })
        .collect()
}
