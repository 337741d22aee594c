//! Integration tests of `dens3r-render`, one module per file, linked into one test binary (one link
//! of the dependency stack instead of one per file keeps CI's build short and its disk small).

#[path = "../../../../tests/support/fetched.rs"]
mod fetched;
mod render;
mod scanned;
