//! Stage 2: tracks. The verified matches joined over all views (union-find over
//! `(view, keypoint)`); a track that would see one view at two different keypoints is
//! ambiguous (a wrong match somewhere along it) and dropped.

use crate::view_graph::Edge;
use dens3r_align::union_find::UnionFind;
use std::collections::HashMap;

/// One track: the keypoints `(view, keypoint index)` that see one scene point, one per view,
/// sorted by view.
pub type Track = Vec<(usize, usize)>;

/// Tracks over the inliers of `edges`, at least two views each, in a stable order (by their
/// first observation). Returns them with how many were dropped as ambiguous.
pub fn build_tracks(edges: &[Edge]) -> (Vec<Track>, usize) {
    let mut id: HashMap<(usize, usize), usize> = HashMap::new();
    let mut nodes: Vec<(usize, usize)> = Vec::new();
    let mut sets = UnionFind::new(0);
    let mut node = |key: (usize, usize), sets: &mut UnionFind| {
        *id.entry(key).or_insert_with(|| {
            nodes.push(key);
            sets.push()
        })
    };
    for e in edges {
        for &(a, b) in &e.inliers {
            let (na, nb) = (node((e.i, a), &mut sets), node((e.j, b), &mut sets));
            sets.union(na, nb);
        }
    }
    let mut groups: HashMap<usize, Track> = HashMap::new();
    for (k, &key) in nodes.iter().enumerate() {
        groups.entry(sets.find(k)).or_default().push(key);
    }
    let mut tracks = Vec::with_capacity(groups.len());
    let mut ambiguous = 0;
    for (_, mut t) in groups {
        t.sort_unstable();
        if t.windows(2).any(|w| w[0].0 == w[1].0) {
            ambiguous += 1;
        } else if t.len() >= 2 {
            tracks.push(t);
        }
    }
    tracks.sort_unstable();
    (tracks, ambiguous)
}
