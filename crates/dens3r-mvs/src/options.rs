//! The settings of each stage, with the defaults the bench chose.

/// PatchMatch on one reference view ([`crate::patch_match`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PatchMatchOptions {
    /// Half width of the matching window, in pixels of the level being solved.
    pub window_radius: usize,
    /// Step between the window's samples (Gipuma's sparse window: 2 reads every other pixel).
    pub window_step: usize,
    /// Spatial sigma of the bilateral weights, pixels.
    pub sigma_spatial: f32,
    /// Intensity sigma of the bilateral weights (grey levels in 0..1).
    pub sigma_color: f32,
    /// Red-black iterations at the coarsest level.
    pub coarse_iterations: usize,
    /// Red-black iterations at every finer level (the upsampled solution only needs polish).
    pub fine_iterations: usize,
    /// Pyramid levels are added until the coarsest long side is at most this.
    pub coarsest_size: usize,
    /// The matching cost of a hypothesis is the mean of its best this many source views.
    pub best_views: usize,
    /// Weight of the network's prior (depth and normal) in the cost, times its confidence
    /// weight in 0..1; 0 turns the prior off (random initialisation only).
    pub prior_weight: f32,
    /// Relative depth difference at which the prior's depth term saturates.
    pub prior_depth_tolerance: f32,
    /// Normal angle (degrees) at which the prior's normal term saturates.
    pub prior_normal_tolerance_deg: f32,
    /// Weight of the geometric-consistency term (ACMM's forward-backward reprojection error,
    /// pixels, capped at [`Self::geom_max_error`]) in the geometric passes.
    pub geom_weight: f32,
    /// Cap of the forward-backward reprojection error, pixels.
    pub geom_max_error: f32,
    /// Geometric-consistency passes over all views after the photometric one.
    pub geom_iterations: usize,
    /// Seed of the random hypotheses (every pixel's draws are a hash of it, so a run repeats).
    pub seed: u64,
}

impl Default for PatchMatchOptions {
    fn default() -> Self {
        Self {
            window_radius: 5,
            window_step: 2,
            sigma_spatial: 5.0,
            sigma_color: 0.08,
            coarse_iterations: 4,
            fine_iterations: 1,
            coarsest_size: 400,
            best_views: 3,
            prior_weight: 0.15,
            prior_depth_tolerance: 0.05,
            prior_normal_tolerance_deg: 30.0,
            geom_weight: 0.2,
            geom_max_error: 3.0,
            geom_iterations: 1,
            seed: 0,
        }
    }
}

/// Fusion of the views' depth maps into points ([`crate::fusion`]), COLMAP's stereo_fusion
/// rules.
#[derive(Debug, Clone, PartialEq)]
pub struct FusionOptions {
    /// A pixel enters only where at least this many other views agree with it.
    pub min_agreeing: usize,
    /// Relative depth difference within which another view agrees.
    pub depth_tolerance: f32,
    /// Normal angle (degrees) within which another view agrees.
    pub normal_tolerance_deg: f32,
    /// Matching cost above which a pixel is not trusted at all (costs run 0..2).
    pub max_cost: f32,
    /// Views each view's pixels are checked against (its best-scoring partners, and the views
    /// that chose it).
    pub partners: usize,
}

impl Default for FusionOptions {
    fn default() -> Self {
        Self { min_agreeing: 2, depth_tolerance: 0.01, normal_tolerance_deg: 15.0, max_cost: 1.2, partners: 16 }
    }
}

/// The whole dense stage.
#[derive(Debug, Clone, PartialEq)]
pub struct MvsOptions {
    /// Long side of the working images (photos larger are resized; smaller stay).
    pub max_size: usize,
    /// Source views per reference view.
    pub neighbours: usize,
    /// PatchMatch settings.
    pub patch_match: PatchMatchOptions,
    /// Fusion settings.
    pub fusion: FusionOptions,
}

impl Default for MvsOptions {
    fn default() -> Self {
        Self {
            max_size: 1600,
            neighbours: 6,
            patch_match: PatchMatchOptions::default(),
            fusion: FusionOptions::default(),
        }
    }
}
