//! Which photos to pair when there are too many for every pair: image retrieval, as
//! MASt3R-SfM's `retrieval-NA-K` scene graph. Each image is one global descriptor (pooled
//! encoder tokens); descriptors are whitened on the set itself (centred, covariance shrunk towards its diagonal,
//! Cholesky whitening) and compared by cosine. `NA` key images chosen by farthest-point
//! sampling are paired among themselves (the graph's backbone across the whole capture); every
//! image is paired with its `K` most similar and its most similar key. An ordered capture
//! (most consecutive photos among each other's nearest) also gets its sliding window.

use std::collections::BTreeSet;

/// Cosine similarity of whitened image descriptors, `n x n`, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Similarity {
    n: usize,
    s: Vec<f32>,
}

impl Similarity {
    /// Number of images.
    pub fn len(&self) -> usize {
        self.n
    }

    /// True for no image.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Similarity of images `i` and `j` (1 for `i == j`).
    pub fn get(&self, i: usize, j: usize) -> f32 {
        self.s[i * self.n + j]
    }

    /// Image `i`'s others, most similar first.
    pub fn ranked(&self, i: usize) -> Vec<usize> {
        let mut o: Vec<usize> = (0..self.n).filter(|&j| j != i).collect();
        o.sort_by(|&a, &b| self.get(i, b).total_cmp(&self.get(i, a)).then(a.cmp(&b)));
        o
    }

    /// From a precomputed `n x n` matrix (symmetric, row-major).
    pub fn from_matrix(n: usize, s: Vec<f32>) -> Self {
        assert_eq!(s.len(), n * n, "an n x n matrix");
        Self { n, s }
    }
}

/// Share of the covariance's correlations shrunk away before whitening (the covariance moved
/// towards its own diagonal): the descriptors of a few dozen photos do not determine the
/// correlations of hundreds of dimensions; every dimension's variance is still normalised.
const SHRINK: f64 = 0.25;

/// Whitened cosine similarity of `descriptors` (one per image, all of one length).
pub fn similarity(descriptors: &[Vec<f32>]) -> Similarity {
    let n = descriptors.len();
    let c = descriptors.first().map_or(0, Vec::len);
    assert!(descriptors.iter().all(|d| d.len() == c), "descriptors of one length");
    let mean: Vec<f64> =
        (0..c).map(|k| descriptors.iter().map(|d| d[k] as f64).sum::<f64>() / n.max(1) as f64).collect();
    let x: Vec<Vec<f64>> =
        descriptors.iter().map(|d| d.iter().zip(&mean).map(|(&v, m)| v as f64 - m).collect()).collect();
    let whitened: Vec<Vec<f64>> = match whitening(&x, c) {
        Some(l) => x.iter().map(|v| forward_substitute(&l, c, v)).collect(),
        None => x,
    };
    let unit: Vec<Vec<f64>> = whitened
        .into_iter()
        .map(|v| {
            let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt().max(1e-12);
            v.into_iter().map(|a| a / norm).collect()
        })
        .collect();
    let mut s = vec![0f32; n * n];
    for i in 0..n {
        for j in i..n {
            let d = if i == j { 1.0 } else { unit[i].iter().zip(&unit[j]).map(|(a, b)| a * b).sum::<f64>() as f32 };
            s[i * n + j] = d;
            s[j * n + i] = d;
        }
    }
    Similarity { n, s }
}

/// The lower Cholesky factor of the shrunk covariance of the centred rows `x` (`c` columns),
/// row-major; None when it is not positive definite (no variance at all).
fn whitening(x: &[Vec<f64>], c: usize) -> Option<Vec<f64>> {
    let n = x.len().max(1) as f64;
    let mut cov = vec![0f64; c * c];
    for v in x {
        for a in 0..c {
            let va = v[a];
            if va == 0.0 {
                continue;
            }
            for b in 0..=a {
                cov[a * c + b] += va * v[b];
            }
        }
    }
    let trace = (0..c).map(|a| cov[a * c + a]).sum::<f64>() / n / c as f64;
    if trace.is_nan() || trace <= 0.0 {
        return None;
    }
    for a in 0..c {
        for b in 0..a {
            cov[a * c + b] *= (1.0 - SHRINK) / n;
        }
        // Dimensions without variance stay at zero (centred) rather than breaking the factor.
        cov[a * c + a] = cov[a * c + a] / n + 1e-6 * trace;
    }
    // In-place Cholesky (lower triangle).
    for j in 0..c {
        let mut d = cov[j * c + j];
        for k in 0..j {
            d -= cov[j * c + k] * cov[j * c + k];
        }
        if d <= 0.0 {
            return None;
        }
        let d = d.sqrt();
        cov[j * c + j] = d;
        for i in j + 1..c {
            let mut s = cov[i * c + j];
            for k in 0..j {
                s -= cov[i * c + k] * cov[j * c + k];
            }
            cov[i * c + j] = s / d;
        }
    }
    Some(cov)
}

/// `L^-1 v` for the lower-triangular `l` (`c x c`).
fn forward_substitute(l: &[f64], c: usize, v: &[f64]) -> Vec<f64> {
    let mut y = vec![0f64; c];
    for i in 0..c {
        let s: f64 = (0..i).map(|k| l[i * c + k] * y[k]).sum();
        y[i] = (v[i] - s) / l[i * c + i];
    }
    y
}

/// `keys` key images by farthest-point sampling on `1 - similarity`, starting from the image
/// most similar to all others.
pub fn key_images(sim: &Similarity, keys: usize) -> Vec<usize> {
    let n = sim.len();
    if n == 0 {
        return vec![];
    }
    let central = (0..n)
        .max_by(|&a, &b| {
            let t = |i: usize| (0..n).map(|j| sim.get(i, j) as f64).sum::<f64>();
            t(a).total_cmp(&t(b)).then(b.cmp(&a))
        })
        .expect("n > 0");
    let mut chosen = vec![central];
    let mut dist: Vec<f32> = (0..n).map(|j| 1.0 - sim.get(central, j)).collect();
    while chosen.len() < keys.min(n) {
        let far = (0..n)
            .filter(|j| !chosen.contains(j))
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]).then(b.cmp(&a)))
            .expect("fewer chosen than images");
        chosen.push(far);
        for (j, d) in dist.iter_mut().enumerate() {
            *d = d.min(1.0 - sim.get(far, j));
        }
    }
    chosen
}

/// True when the images' order is the capture's: at least half of the consecutive images are
/// among each other's `k` most similar.
pub fn looks_ordered(sim: &Similarity, k: usize) -> bool {
    let n = sim.len();
    if n < 3 {
        return true;
    }
    let near: Vec<Vec<usize>> = (0..n).map(|i| sim.ranked(i).into_iter().take(k).collect()).collect();
    let hits = (0..n - 1).filter(|&i| near[i].contains(&(i + 1)) || near[i + 1].contains(&i)).count();
    2 * hits >= n - 1
}

/// The unordered pairs `(i, j)`, `i < j`, of the `retrieval-keys-neighbours` graph (see the
/// module's documentation), plus the sliding window `window` where the capture
/// [`looks_ordered`] (0: never). Sorted.
pub fn retrieval_pairs(sim: &Similarity, keys: usize, neighbours: usize, window: usize) -> Vec<(usize, usize)> {
    retrieval_graph(sim, keys, neighbours, window).0
}

/// [`retrieval_pairs`] and whether the capture [`looks_ordered`] (false when `window` is 0,
/// which does not ask).
pub fn retrieval_graph(sim: &Similarity, keys: usize, neighbours: usize, window: usize) -> (Vec<(usize, usize)>, bool) {
    let n = sim.len();
    let mut out = BTreeSet::new();
    let mut add = |i: usize, j: usize| {
        if i != j {
            out.insert((i.min(j), i.max(j)));
        }
    };
    let key = key_images(sim, keys);
    for (a, &i) in key.iter().enumerate() {
        for &j in &key[a + 1..] {
            add(i, j);
        }
    }
    for i in 0..n {
        for j in sim.ranked(i).into_iter().take(neighbours) {
            add(i, j);
        }
        if let Some(&best) = key.iter().filter(|&&k| k != i).max_by(|&&a, &&b| sim.get(i, a).total_cmp(&sim.get(i, b)))
        {
            add(i, best);
        }
    }
    let ordered = window > 0 && looks_ordered(sim, neighbours.max(1));
    if ordered {
        for i in 0..n {
            for j in i + 1..(i + 1 + window).min(n) {
                add(i, j);
            }
        }
    }
    (out.into_iter().collect(), ordered)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Descriptors of images along a loop: image i sees the part of the loop around angle
    /// 2 pi i / n, so its true neighbours are i +- 1, 2 (mod n); a shared offset and a strong
    /// nuisance direction that says nothing about place are what whitening must remove.
    fn loop_descriptors(n: usize, order: &[usize]) -> Vec<Vec<f32>> {
        order
            .iter()
            .map(|&i| {
                let a = std::f32::consts::TAU * i as f32 / n as f32;
                let mut d: Vec<f32> = (1..=6).flat_map(|f| [(f as f32 * a).cos(), (f as f32 * a).sin()]).collect();
                d.push(5.0 + 3.0 * ((i * 7919) % 13) as f32); // nuisance: large, random per image
                d.push(10.0); // offset shared by all
                d
            })
            .collect()
    }

    #[test]
    fn retrieval_finds_the_true_neighbours_in_any_file_order() {
        let n = 40;
        // A shuffled order (file names that say nothing of the capture).
        let order: Vec<usize> = (0..n).map(|k| (k * 17) % n).collect();
        let sim = similarity(&loop_descriptors(n, &order));
        let pairs = retrieval_pairs(&sim, 5, 3, 3);
        // Every true neighbour (one step along the loop) is paired, whatever the order.
        let pos = |img: usize| order.iter().position(|&o| o == img).unwrap();
        for img in 0..n {
            let (a, b) = (pos(img), pos((img + 1) % n));
            assert!(pairs.contains(&(a.min(b), a.max(b))), "loop neighbours {img}, {} not paired", (img + 1) % n);
        }
        // The shuffled order is recognised as such: no sliding window over it.
        assert!(!looks_ordered(&sim, 3));
        // Keys 10 (45 pairs) + neighbours: far fewer than all 780 pairs.
        assert!(pairs.len() < 5 * 4 / 2 + n * 4, "{} pairs", pairs.len());
        let in_order = similarity(&loop_descriptors(n, &(0..n).collect::<Vec<_>>()));
        assert!(looks_ordered(&in_order, 3));
    }

    #[test]
    fn key_images_spread_over_the_capture() {
        let n = 36;
        let sim = similarity(&loop_descriptors(n, &(0..n).collect::<Vec<_>>()));
        let mut keys = key_images(&sim, 4);
        keys.sort();
        // Four keys on a loop of 36: no two see the same part of it (the descriptors' six
        // harmonics make images more than ~3 steps apart unrelated), unlike the 4 most
        // central images, neighbours of each other.
        for a in 0..4 {
            for b in a + 1..4 {
                let gap = keys[a].abs_diff(keys[b]).min(n - keys[a].abs_diff(keys[b]));
                assert!(gap >= 3, "keys {keys:?}");
            }
        }
    }
}
