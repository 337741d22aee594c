//! The network's share of a reconstruction computed apart, into a pair cache that a later
//! `reconstruct` reads (`dens3r pairs --shard I/N`, the Python module's Ray executor): with
//! the structure-from-motion cameras every photo's own pass, with the dense path every pair of
//! the graph (both orders); shard `I` of `N` takes every `N`-th of them from the `I`-th
//! (counting from 0), so `N` jobs with one shared folder compute each entry once. A
//! retrieval graph's photo descriptors are computed by every shard that needs the graph (and
//! cached: the first to finish serves the others).

use crate::cache::PairCache;
use crate::input::InputImage;
use crate::pipeline::{pair_output, Cameras, ReconOptions, Stage};
use crate::predictor::PairPredictor;
use crate::sfm::mono_output;
use crate::ReconError;
use std::collections::HashSet;

/// One shard of `count` (`index` from 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// Which shard, from 0.
    pub index: usize,
    /// How many shards.
    pub count: usize,
}

impl Shard {
    /// All the work in one shard.
    pub const ALL: Self = Self { index: 0, count: 1 };

    /// Parses `I/N` (0 <= I < N).
    pub fn parse(s: &str) -> Result<Self, String> {
        let bad = || format!("{s}: expected I/N with 0 <= I < N, e.g. 0/4 for the first of four shards");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let (index, count) = (i.trim().parse().map_err(|_| bad())?, n.trim().parse().map_err(|_| bad())?);
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Self { index, count })
    }

    fn mine(&self, k: usize) -> bool {
        k % self.count == self.index
    }
}

/// What a shard did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ShardStats {
    /// Entries in this shard (photos, or ordered pairs).
    pub entries: usize,
    /// Of those, already in the cache.
    pub cached: usize,
    /// Entries over all shards.
    pub total: usize,
}

/// Computes `shard`'s entries of the run `opts` describes into `cache` (see the module's
/// documentation). `progress` reports [`Stage::Retrieve`] and [`Stage::Predict`].
pub fn compute_shard(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    opts: &ReconOptions,
    shard: Shard,
    warnings: &mut Vec<String>,
    progress: &mut dyn FnMut(Stage, usize, usize),
) -> Result<ShardStats, ReconError> {
    if cache.dir().is_none() {
        return Err(ReconError::Other("computing a shard needs a cache folder to put it in".into()));
    }
    // A shard's only output is what it stores: a folder that takes nothing fails it up front.
    cache.check_writable()?;
    let mut stats = ShardStats::default();
    match &opts.cameras {
        Cameras::Sfm(_) => {
            let mine: Vec<usize> = (0..images.len()).filter(|&k| shard.mine(k)).collect();
            stats.total = images.len();
            progress(Stage::Predict, 0, mine.len());
            for (done, &k) in mine.iter().enumerate() {
                let (_, hit) = mono_output(images, predictor, cache, k, warnings)?;
                stats.entries += 1;
                stats.cached += usize::from(hit);
                progress(Stage::Predict, done + 1, mine.len());
            }
        }
        Cameras::Dense => {
            let pairs = crate::graph::plan_pairs(images, predictor, cache, opts.graph, warnings, progress)?.list;
            let order: Vec<(usize, usize)> = pairs.iter().flat_map(|&(i, j)| [(i, j), (j, i)]).collect();
            let ordered: HashSet<(usize, usize)> = order.iter().copied().collect();
            stats.total = order.len();
            // An unordered pair's two runs stay in one shard: a predictor reuses work between them.
            let mine: Vec<(usize, usize)> =
                order.iter().enumerate().filter(|(e, _)| shard.mine(e / 2)).map(|(_, &p)| p).collect();
            progress(Stage::Predict, 0, mine.len());
            for (done, &(i, j)) in mine.iter().enumerate() {
                let matched = i < j || !ordered.contains(&(j, i));
                let (_, hit) = pair_output(images, predictor, cache, (i, j), matched, warnings)?;
                stats.entries += 1;
                stats.cached += usize::from(hit);
                progress(Stage::Predict, done + 1, mine.len());
            }
        }
    }
    if let (failed @ 1.., why) = cache.failed_stores() {
        let why = why.unwrap_or_default();
        return Err(ReconError::Other(format!(
            "{failed} of {} network runs could not be stored in the cache ({why}); free space or fix the folder, then run the shard again",
            stats.entries
        )));
    }
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::Shard;

    #[test]
    fn shards_parse_and_split_the_work_once() {
        assert_eq!(Shard::parse("1/3"), Ok(Shard { index: 1, count: 3 }));
        for bad in ["3/3", "1", "a/2", "0/0", "-1/2"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
        let shards: Vec<Shard> = (0..3).map(|index| Shard { index, count: 3 }).collect();
        for k in 0..20 {
            assert_eq!(shards.iter().filter(|s| s.mine(k)).count(), 1);
        }
    }
}
