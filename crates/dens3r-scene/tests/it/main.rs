//! Integration tests of `dens3r-scene`, one module per file, linked into one test binary (one link
//! of the dependency stack instead of one per file keeps CI's build short and its disk small).

mod pycolmap;
mod scene;
