//! Integration tests of `dens3r-backbone`, one module per file, linked into one test binary (one link
//! of the dependency stack instead of one per file keeps CI's build short and its disk small).

mod dinov2;
mod dinov2_encoder;
#[path = "../../../../tests/support/fetched.rs"]
mod fetched;
#[path = "../../../../tests/support/fixtures.rs"]
mod fixtures;
mod gpu;
mod linear_head;
mod parity;
mod predict;
mod pth;
mod rotation;
