//! Integration tests of `dens3r-train`, one module per file, linked into one test binary (one link
//! of the dependency stack instead of one per file keeps CI's build short and its disk small).

mod augment;
#[path = "../../../../tests/support/fetched.rs"]
mod fetched;
#[path = "../../../../tests/support/fixtures.rs"]
mod fixtures;
mod real;
mod synth;
mod train;
