//! Which image pairs to run (DUSt3R's `make_pairs` scene graphs and the official Dens3R modes),
//! and which of them to keep once some are placed.

/// A scene graph over `n` images.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairGraph {
    /// Every unordered pair once (Dens3R's "exhaustive"; DUSt3R's "complete").
    Complete,
    /// Each image with the next `k` (DUSt3R "swin-k"; Dens3R's "sequential" with overlap `k`
    /// when not cyclic).
    SlidingWindow { k: usize, cyclic: bool },
    /// Each image with those `1, 2, 4, .., 2^(k-1)` ahead (DUSt3R "logwin-k").
    LogWindow { k: usize, cyclic: bool },
    /// Every image with one reference image (DUSt3R "oneref").
    OneReference { reference: usize },
    /// MASt3R-SfM's "retrieval-NA-K": `keys` key images paired among themselves, each image
    /// with its `neighbours` most similar ([`crate::retrieval`]). [`make_pairs`] has no
    /// images to compare and takes neighbours by index; [`crate::retrieval::retrieval_pairs`]
    /// takes them by image similarity.
    Retrieval { keys: usize, neighbours: usize },
}

impl PairGraph {
    /// MASt3R-SfM's retrieval defaults: 20 key images, 10 neighbours.
    pub const RETRIEVAL: Self = Self::Retrieval { keys: 20, neighbours: 10 };

    /// Parses a graph's name as the CLI and the Python module take it: `complete`, `swin`,
    /// `logwin` (window `window`, closed around the end when `cyclic`), `oneref`, `retrieval`
    /// or `retrieval-NA-K` (NA key images, K neighbours).
    pub fn parse(name: &str, window: usize, cyclic: bool) -> Result<Self, String> {
        let k = window.max(1);
        Ok(match name {
            "complete" => Self::Complete,
            "swin" => Self::SlidingWindow { k, cyclic },
            "logwin" => Self::LogWindow { k, cyclic },
            "oneref" => Self::OneReference { reference: 0 },
            "retrieval" => Self::RETRIEVAL,
            g if g.starts_with("retrieval-") => {
                let parts: Vec<Option<usize>> = g["retrieval-".len()..].split('-').map(|v| v.parse().ok()).collect();
                match parts[..] {
                    [Some(keys), Some(neighbours)] if neighbours > 0 => Self::Retrieval { keys, neighbours },
                    _ => {
                        return Err(format!(
                            "{g}: expected retrieval-NA-K (key images, neighbours; K >= 1), e.g. retrieval-20-10"
                        ))
                    }
                }
            }
            g => return Err(format!("{g}: expected complete, swin, logwin, oneref, retrieval or retrieval-NA-K")),
        })
    }
}

/// The ordered pairs `(i, j)` (i = the network's first view) of a graph over `n` images, without
/// duplicates; `symmetrize` adds `(j, i)` for every `(i, j)`, as DUSt3R does by default and as
/// [`crate::global_align`] needs for every image to have a pointmap in its own frame.
pub fn make_pairs(n: usize, graph: PairGraph, symmetrize: bool) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    let mut push = |i: usize, j: usize| {
        if i != j && seen.insert((i.min(j), i.max(j))) {
            out.push((i, j));
        }
    };
    let ahead = |i: usize, off: usize, cyclic: bool| -> Option<usize> {
        if cyclic {
            Some((i + off) % n)
        } else {
            (i + off < n).then_some(i + off)
        }
    };
    match graph {
        PairGraph::Complete => {
            for i in 0..n {
                for j in i + 1..n {
                    push(i, j);
                }
            }
        }
        PairGraph::SlidingWindow { k, cyclic } => {
            for i in 0..n {
                for off in 1..=k {
                    if let Some(j) = ahead(i, off, cyclic) {
                        push(i, j);
                    }
                }
            }
        }
        PairGraph::LogWindow { k, cyclic } => {
            for i in 0..n {
                for e in 0..k {
                    if let Some(j) = ahead(i, 1 << e, cyclic) {
                        push(i, j);
                    }
                }
            }
        }
        PairGraph::OneReference { reference } => {
            for j in 0..n {
                if reference < n {
                    push(reference, j);
                }
            }
        }
        PairGraph::Retrieval { keys, neighbours } => {
            let by_index = (0..n * n).map(|k| 1.0 - (k / n).abs_diff(k % n) as f32 / n.max(1) as f32).collect();
            let sim = crate::retrieval::Similarity::from_matrix(n, by_index);
            for (i, j) in crate::retrieval::retrieval_pairs(&sim, keys, neighbours, 0) {
                push(i, j);
            }
        }
    }
    if symmetrize {
        let rev: Vec<_> = out.iter().map(|&(i, j)| (j, i)).collect();
        out.extend(rev);
    }
    out
}

/// Which of `pairs` (over images `0..n`) global alignment should keep once some are
/// `verified` (placed by geometry, e.g. keypoint epipolar fits): every verified pair, and an
/// unverified one only where it joins two groups of images that verified pairs do not
/// connect. Unverified pairs inside a verified group would only pull it towards the
/// network's cross-view guesses; those between groups are all that places one group against
/// the other. With no verified pair every pair is kept.
pub fn verified_subgraph(n: usize, pairs: &[(usize, usize)], verified: &[bool]) -> Vec<bool> {
    assert_eq!(pairs.len(), verified.len(), "one flag per pair");
    if !verified.iter().any(|&v| v) {
        return vec![true; pairs.len()];
    }
    let mut groups = crate::union_find::UnionFind::new(n);
    for (&(i, j), _) in pairs.iter().zip(verified).filter(|(_, &v)| v) {
        groups.union(i, j);
    }
    pairs.iter().zip(verified).map(|(&(i, j), &v)| v || groups.find(i) != groups.find(j)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn graphs_have_the_expected_pairs() {
        assert_eq!(make_pairs(4, PairGraph::Complete, false).len(), 6);
        assert_eq!(make_pairs(4, PairGraph::Complete, true).len(), 12);
        assert_eq!(
            make_pairs(5, PairGraph::SlidingWindow { k: 2, cyclic: false }, false),
            vec![(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)]
        );
        // Cyclic: 4 -> 0 and 4 -> 1, 3 -> 0 join.
        assert_eq!(make_pairs(5, PairGraph::SlidingWindow { k: 2, cyclic: true }, false).len(), 10);
        assert_eq!(
            make_pairs(9, PairGraph::LogWindow { k: 3, cyclic: false }, false).iter().filter(|p| p.0 == 0).count(),
            3 // 1, 2, 4 ahead
        );
        assert_eq!(make_pairs(4, PairGraph::OneReference { reference: 2 }, false), vec![(2, 0), (2, 1), (2, 3)]);
        // Window wider than the set: no duplicates, no self-pairs.
        let p = make_pairs(3, PairGraph::SlidingWindow { k: 5, cyclic: true }, true);
        assert_eq!(p.len(), 6);
        assert!(p.iter().all(|(i, j)| i != j));
        // Retrieval by index: each image with its neighbours on either side, keys joined.
        let r = make_pairs(30, PairGraph::Retrieval { keys: 3, neighbours: 2 }, false);
        assert!((0..29).all(|i| r.contains(&(i, i + 1))));
        assert!(r.len() < 30 * 3 + 3);
        assert_eq!(PairGraph::parse("retrieval-5-7", 3, false), Ok(PairGraph::Retrieval { keys: 5, neighbours: 7 }));
        assert_eq!(PairGraph::parse("retrieval", 3, false), Ok(PairGraph::RETRIEVAL));
        assert!(PairGraph::parse("retrieval-5", 3, false).is_err());
        assert!(PairGraph::parse("retrieval-5-0", 3, false).is_err());
        assert!(PairGraph::parse("sideways", 3, false).is_err());
    }

    #[test]
    fn unverified_pairs_are_kept_only_between_verified_groups() {
        // Images 0-1-2 verified as a chain, 3-4 verified, 5 in no verified pair.
        let pairs = [(0, 1), (1, 2), (0, 2), (3, 4), (2, 3), (1, 4), (4, 5), (0, 5), (1, 0)];
        let verified = [true, true, false, true, false, false, false, false, true];
        let keep = verified_subgraph(6, &pairs, &verified);
        // (0, 2) lies inside the group {0, 1, 2}: dropped; (2, 3) and (1, 4) join {0, 1, 2} to
        // {3, 4}, (4, 5) and (0, 5) reach image 5: kept.
        assert_eq!(keep, vec![true, true, false, true, true, true, true, true, true]);
        // Nothing verified: everything stays.
        assert_eq!(verified_subgraph(6, &pairs, &[false; 9]), vec![true; 9]);
    }
}
