//! What can go wrong while fusing, meshing or storing a grid.

/// What can go wrong while fusing.
#[derive(Debug, thiserror::Error)]
pub enum FusionError {
    /// A parameter is out of range.
    #[error("invalid fusion parameter: {0}")]
    Param(String),
    /// The next frame would take the grid past its memory budget.
    #[error(
        "the voxel grid would need {}{needed_mb:.0} MB ({blocks} blocks), over the {budget_mb:.0} MB budget: use a larger --voxel, a smaller --max-depth or --trunc, or raise --budget-mb",
        if *.at_least { "more than " } else { "" }
    )]
    Budget {
        /// Blocks the grid would hold.
        blocks: usize,
        /// Memory they would take.
        needed_mb: f64,
        /// The budget.
        budget_mb: f64,
        /// Counting stopped once past the budget: the grid would need more.
        at_least: bool,
    },
    /// The GPU path could not run (no adapter, buffer limits, device lost).
    #[error("GPU fusion: {0}")]
    Gpu(String),
    /// A frame's layers do not fit its camera.
    #[error("frame '{0}': {1}")]
    Frame(String, String),
}
