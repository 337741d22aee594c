//! Which photos are paired: a fixed graph ([`dens3r_align::make_pairs`]) or image retrieval on
//! the predictor's own descriptors ([`dens3r_align::retrieval`]); by default every pair up to
//! [`AUTO_COMPLETE_UP_TO`] photos, retrieval above (the complete graph grows as the square).

use crate::cache::PairCache;
use crate::input::InputImage;
use crate::pipeline::Stage;
use crate::predictor::PairPredictor;
use crate::ReconError;
use dens3r_align::retrieval::{retrieval_graph, similarity};
use dens3r_align::{make_pairs, PairGraph};
use std::time::Instant;

/// The most photos the default graph pairs completely.
pub const AUTO_COMPLETE_UP_TO: usize = 30;

/// Sliding window added to a retrieval graph when the photos' order looks like the capture's.
pub const ORDERED_WINDOW: usize = 3;

/// The graph a run uses: `graph`, else complete up to [`AUTO_COMPLETE_UP_TO`] photos and
/// [`PairGraph::RETRIEVAL`] above.
pub fn resolve(graph: Option<PairGraph>, n: usize) -> PairGraph {
    graph.unwrap_or(if n <= AUTO_COMPLETE_UP_TO { PairGraph::Complete } else { PairGraph::RETRIEVAL })
}

/// How the pairs were chosen.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GraphInfo {
    /// The graph, as `--graph` names it (`retrieval-20-10`, `complete`, ...).
    pub name: String,
    /// A retrieval graph found the photos in capture order and added its sliding window.
    pub ordered: bool,
    /// Seconds computing image descriptors and similarities.
    pub seconds: f64,
    /// The pairs, as indices into `names`.
    pub list: Vec<(usize, usize)>,
    /// The photos' names, in input order.
    pub names: Vec<String>,
}

/// The unordered pairs `(i, j)` of `graph` (None: [`resolve`]) over `images`, in
/// [`GraphInfo::list`]; a retrieval graph
/// asks `predictor` for every image's descriptor, through `cache` (progress as
/// [`Stage::Retrieve`]).
pub fn plan_pairs(
    images: &[InputImage],
    predictor: &dyn PairPredictor,
    cache: &PairCache,
    graph: Option<PairGraph>,
    warnings: &mut Vec<String>,
    progress: &mut dyn FnMut(Stage, usize, usize),
) -> Result<GraphInfo, ReconError> {
    let n = images.len();
    let graph = resolve(graph, n);
    let t = Instant::now();
    let PairGraph::Retrieval { keys, neighbours } = graph else {
        return Ok(info(images, graph, make_pairs(n, graph, false), false, 0.0));
    };
    let mut desc = Vec::with_capacity(n);
    progress(Stage::Retrieve, 0, n);
    for i in 0..n {
        let err = |msg: String| ReconError::Predict { a: images[i].name.clone(), b: images[i].name.clone(), msg };
        let key = PairCache::key(&format!("{} descriptor", predictor.id()), &images[i], &images[i]);
        let d = cache.descriptor_or(&key, warnings, || predictor.embed(images, i)).map_err(err)?;
        let d = d.ok_or_else(|| {
            ReconError::Other(format!(
                "{}: this predictor gives no image descriptors for --graph retrieval: choose --graph complete, swin or logwin",
                predictor.id()
            ))
        })?;
        if d.is_empty()
            || d.iter().any(|v| !v.is_finite())
            || desc.first().is_some_and(|f: &Vec<f32>| f.len() != d.len())
        {
            return Err(err("its image descriptor is empty, not finite or of another length".into()));
        }
        desc.push(d);
        progress(Stage::Retrieve, i + 1, n);
    }
    let sim = similarity(&desc);
    let (pairs, ordered) = retrieval_graph(&sim, keys, neighbours, ORDERED_WINDOW);
    Ok(info(images, graph, pairs, ordered, t.elapsed().as_secs_f64()))
}

fn info(images: &[InputImage], graph: PairGraph, list: Vec<(usize, usize)>, ordered: bool, seconds: f64) -> GraphInfo {
    let names = images.iter().map(|im| im.name.clone()).collect();
    GraphInfo { name: name(graph), ordered, seconds, list, names }
}

/// A graph's name as `--graph` takes it.
pub fn name(graph: PairGraph) -> String {
    match graph {
        PairGraph::Complete => "complete".into(),
        PairGraph::SlidingWindow { k, cyclic } => format!("swin (window {k}{})", if cyclic { ", cyclic" } else { "" }),
        PairGraph::LogWindow { k, cyclic } => format!("logwin (window {k}{})", if cyclic { ", cyclic" } else { "" }),
        PairGraph::OneReference { reference } => format!("oneref (photo {reference})"),
        PairGraph::Retrieval { keys, neighbours } => format!("retrieval-{keys}-{neighbours}"),
    }
}
