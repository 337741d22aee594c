//! Which image pairs to run (DUSt3R's `make_pairs` scene graphs and the official Dens3R modes).

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
}

/// The ordered pairs `(i, j)` (i = the network's first view) of a graph over `n` images, without
/// duplicates; `symmetrize` adds `(j, i)` for every `(i, j)`, as DUSt3R does by default and as
/// [`crate::global_align`] needs for every image to have a pointmap in its own frame.
pub fn make_pairs(n: usize, graph: PairGraph, symmetrize: bool) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    let mut push = |i: usize, j: usize| {
        if i != j && !out.contains(&(i, j)) && !out.contains(&(j, i)) {
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
    }
    if symmetrize {
        let rev: Vec<_> = out.iter().map(|&(i, j)| (j, i)).collect();
        out.extend(rev);
    }
    out
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
    }
}
