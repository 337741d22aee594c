//! What a person looks at: the page dens3r writes beside its outputs, and the local server
//! that shows it.
//!
//! ```text
//! OUT/index.html               opens by double-click: no network, no server
//! OUT/viewer/app.js            three.js and the page's code, bundled at build time (build.rs)
//! OUT/viewer/scene.js          the page's data: cameras, decimated point cloud and mesh (base64)
//! OUT/viewer/scores.js         scores against a ground truth (`dens3r eval` adds them)
//! OUT/viewer/views/*.png       per view: depth, normals, confidence pictures (and a photo copy)
//! OUT/viewer/THREE-LICENSE.txt three.js's licence
//! ```
//!
//! Storage apart from drawing: [`cloud`] and [`decimate`] make the geometry small enough for
//! a browser, [`pictures`] the per-view images, [`page`] writes the files, [`serve`] serves a
//! folder on 127.0.0.1 for browsers that refuse `file://` pages. Conventions of the data:
//! dens3r's world frame, OpenCV cameras, camera-to-world poses.

pub mod cloud;
pub mod decimate;
pub mod page;
pub mod pictures;
pub mod scene_views;
pub mod serve;

pub use page::{add_scores, page_of, title_of, write_page, MatchPicture, Page, PageOptions, PageSummary, View};

mod assets {
    include!(concat!(env!("OUT_DIR"), "/bundled.rs"));
    /// The bundled script (three.js + the page), or a placeholder saying how to get it.
    pub const APP_JS: &str = include_str!(concat!(env!("OUT_DIR"), "/app.js"));
    /// three.js's licence, shipped beside the script.
    pub const THREE_LICENSE: &str = include_str!(concat!(env!("OUT_DIR"), "/THREE-LICENSE.txt"));
    /// The page itself.
    pub const INDEX_HTML: &str = include_str!("../web/index.html");
}

/// The page's files that do not depend on the views (a file of the user's there is refused).
pub const PAGE_FILES: [&str; 5] =
    [page::INDEX_HTML, page::APP_JS, page::SCENE_JS, page::SCORES_JS, page::THREE_LICENSE];

/// Whether this build carries the 3-D viewer (three.js was bundled; see `scripts/build-viewer.sh`).
pub const VIEWER_BUNDLED: bool = assets::BUNDLED;
