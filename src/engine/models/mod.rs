//! Models: a field, a sampler and settings, wired together in one folder per
//! kind, and what every model offers the trainer, the renderer and
//! checkpoints ([`Model`]).
//!
//! Adding a model is its folder (its config, a [`Model`] impl built from
//! the parts in `fields`, `sampling`, `render` and `models::pass`) and one
//! line of `config`'s `registry!` (docs/architecture.md, "Adding a model").

pub mod auto;
pub mod capture;
pub mod config;
pub mod instant;
pub mod nerf;
pub mod pass;
pub mod spec;
pub mod splats;
pub mod training;

/// The accessors every model implements alike, inside its `impl Model`:
/// from the `KIND` constant of its file and its `config`, `scene` and
/// `params` fields.
macro_rules! model_accessors {
    () => {
        super::model_accessors!(params_mut:);
    };
    // `params_mut: field, ...`: `params_mut` also resets these `OnceLock`
    // caches of values derived from the parameters.
    (params_mut: $($cache:ident),*) => {
        fn kind(&self) -> &'static str {
            KIND
        }
        fn scene(&self) -> &Scene {
            &self.scene
        }
        fn params(&self) -> &[f32] {
            &self.params
        }
        fn params_mut(&mut self) -> &mut [f32] {
            $(self.$cache = std::sync::OnceLock::new();)*
            &mut self.params
        }
        fn as_any(&self) -> &dyn std::any::Any {
            self
        }
        fn config_json(&self) -> serde_json::Value {
            serde_json::to_value(&self.config).unwrap_or(serde_json::Value::Null)
        }
    };
}
pub(crate) use model_accessors;

use crate::engine::batch::{BatchStats, RayOutput, StepCtx, TrainRay};
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::nn::adam::LrGroup;
use crate::engine::nn::hashgrid::{GridRecord, HashGrid};
use crate::engine::nn::pose_report::PoseReport;

/// Why a model could not be rebuilt from saved parts.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("{what}: expected {expected} values, found {found}")]
    Size { what: &'static str, expected: usize, found: usize },
    #[error("the checkpoint has no '{0}' tensor, which this model saves")]
    MissingState(String),
    #[error("unknown model kind '{0}' (known: {known})", known = config::KINDS.join(", "))]
    UnknownKind(String),
    #[error("the learning rate must be a positive number, not {0}")]
    LearningRate(f32),
    #[error("the {kind} model's configuration: {message}")]
    Config { kind: &'static str, message: String },
}

impl ModelError {
    /// Checks that `found` values were given where `expected` are needed.
    pub fn check_size(what: &'static str, expected: usize, found: usize) -> Result<(), ModelError> {
        match expected == found {
            true => Ok(()),
            false => Err(ModelError::Size { what, expected, found }),
        }
    }
}

/// A model's saved state, taken back by name ([`Model::restore_state`]).
pub type StateSource<'a> = &'a mut dyn FnMut(&str) -> Option<Vec<f32>>;

/// Options of one render that some models read; a model without them
/// ignores them and renders exactly as [`Model::render_rays`] does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderOptions {
    /// The training image whose appearance embedding the view takes;
    /// `None`: the mean embedding of the images trained on. The engine's
    /// choice of it (a user's `mean`, index or `nearest`, checked against
    /// the model) is `view::appearance`.
    pub image: Option<u32>,
}

/// A trainable radiance field.
pub trait Model: Send + Sync {
    /// "instant", "nerf", "capture" or "splats".
    fn kind(&self) -> &'static str;
    fn scene(&self) -> &Scene;
    fn params(&self) -> &[f32];
    fn params_mut(&mut self) -> &mut [f32];
    /// The model's configuration, saved in checkpoints.
    fn config_json(&self) -> serde_json::Value;
    /// Accumulates the gradient of the batch loss over `rays` (one part of a
    /// batch) into `grads` and returns the part's statistics.
    fn train_rays(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats;
    /// [`Model::train_rays`], also writing what it measured of each ray
    /// into `errors` (as long as `rays`). The default, for a model that
    /// does not measure them, leaves `errors` as it is.
    fn train_rays_measured(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        errors: &mut [RayMeasure],
    ) -> BatchStats {
        let _ = errors;
        self.train_rays(rays, ctx, grads)
    }
    /// The density the model draws at world points, per world unit (a ray
    /// through density `s` over length `d` keeps `exp(-s d)` of the light
    /// behind); `None` for a model that does not expose one.
    fn density(&self, world: &[[f32; 3]]) -> Option<Vec<f32>> {
        let _ = world;
        None
    }
    /// Training with the main grid's table gradient deferred to the
    /// trainer ([`DeferredGrid`]); `None` (the default): every gradient
    /// goes into `grads`.
    fn deferred(&self) -> Option<&dyn DeferredGrid> {
        None
    }
    /// Runs after each optimisation step (`step` is the number of steps
    /// done), e.g. to update an occupancy grid.
    fn after_step(&mut self, _step: u64, _seed: u64, _stats: &BatchStats) {}
    /// Rays per step the model wants (e.g. to keep a constant sample
    /// budget); `None` uses the trainer's setting.
    fn batch_rays(&self) -> Option<usize> {
        None
    }
    /// Non-parameter state saved with checkpoints (e.g. the occupancy grid).
    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        Vec::new()
    }
    /// Takes back what [`Model::state_tensors`] saved, after `step` steps.
    fn restore_state(&mut self, _state: StateSource<'_>, _step: u64) -> Result<(), ModelError> {
        Ok(())
    }
    /// Ranges of the parameters that learn at a scaled rate (sorted, not
    /// overlapping; e.g. camera pose corrections).
    fn lr_groups(&self) -> Vec<LrGroup> {
        Vec::new()
    }
    /// The training cameras' refined poses ([`PoseRefinement`]); `None`
    /// (the default) for a model that takes the cameras as given.
    fn poses(&self) -> Option<&dyn PoseRefinement> {
        None
    }
    /// A line about the model's set-up for a training log (e.g. where its
    /// rays start and end); `None` when there is nothing to say.
    fn log_note(&self) -> Option<String> {
        None
    }
    /// The concrete model, for callers that need its own API.
    fn as_any(&self) -> &dyn std::any::Any;
    /// Renders model-space rays with `options` (a model without per-image
    /// appearance reads none of them).
    fn render_rays(
        &self,
        rays: &[Ray],
        background: [f32; 3],
        options: &RenderOptions,
        out: &mut [RayOutput],
    ) -> BatchStats;
    /// Per-image appearance ([`Appearance`]); `None` (the default) for a
    /// model whose every view looks alike.
    fn appearance(&self) -> Option<&dyn Appearance> {
        None
    }
    /// Whole views drawn at once ([`splats::Rasteriser`]) rather than ray
    /// by ray; `None` (the default) for a model that renders rays.
    fn rasteriser(&self) -> Option<&dyn splats::Rasteriser> {
        None
    }
}

/// What a model with a per-image appearance embedding offers
/// ([`Model::appearance`]).
pub trait Appearance {
    /// The training images whose appearance a view can take
    /// ([`RenderOptions::image`]), ascending.
    fn images(&self) -> Vec<u32>;
    /// Where image `image`'s embedding lies in the parameters; `None` for an
    /// image beyond its table.
    fn row(&self, image: u32) -> Option<std::ops::Range<usize>>;
    /// The embedding a view takes under `options` (as
    /// [`Model::render_rays`] renders it); `None` for an image beyond its
    /// table.
    fn embedding(&self, options: &RenderOptions) -> Option<Vec<f32>>;
}

/// What a model that refines its training cameras' poses offers
/// ([`Model::poses`]).
pub trait PoseRefinement {
    /// The camera-to-world pose (world units, 3x4 rows) a held-out view is
    /// rendered from: moved with the training cameras' common drift, which
    /// the photographs cannot see.
    fn heldout_pose(&self, c2w: [[f32; 4]; 3]) -> [[f32; 4]; 3];
    /// What the refinement did so far (`None` before it has a report).
    fn report(&self) -> Option<PoseReport>;
}

/// Training with one hash grid's table gradient deferred
/// ([`Model::deferred`]): the trainer scatters each level's gradient for
/// all threads' parts at once and updates that level's parameters in the
/// same pass.
pub trait DeferredGrid {
    /// The deferred grid: a copy of its layout, which borrows nothing from
    /// the model.
    fn grid(&self) -> HashGrid;
    /// [`Model::train_rays`], except that the deferred grid's table
    /// gradient is not added to `grads` but kept in `record` (cleared
    /// first): one thread's part of a step ([`HashGrid::scatter`] of every
    /// part's record gives the same sum).
    fn train_rays_deferred(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        record: &mut GridRecord,
    ) -> BatchStats {
        self.train_rays_deferred_measured(rays, ctx, grads, record, &mut vec![RayMeasure::UNKNOWN; rays.len()])
    }
    /// [`DeferredGrid::train_rays_deferred`], also writing what it measured
    /// of each ray into `errors` (as long as `rays`).
    fn train_rays_deferred_measured(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        record: &mut GridRecord,
        errors: &mut [RayMeasure],
    ) -> BatchStats;
}

/// What a training pass measured of one ray: its mean squared colour
/// error, and the distance along it at which its opacity reaches one half
/// (where it meets a surface; NaN when it never does or was not drawn).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayMeasure {
    pub sq_err: f32,
    pub depth: f32,
}

impl RayMeasure {
    /// Nothing measured.
    pub const UNKNOWN: RayMeasure = RayMeasure { sq_err: f32::NAN, depth: f32::NAN };
}

/// Whether `model` learned a per-image appearance embedding with values in
/// its parameters (a capture model whose embedding is not empty).
pub fn learns_appearance(model: &dyn Model) -> bool {
    model.appearance().and_then(|a| a.row(0)).is_some_and(|r| !r.is_empty())
}

/// The pose a held-out view of `model` is rendered from
/// ([`PoseRefinement::heldout_pose`]; the pose itself for a model that
/// refines no cameras).
pub fn heldout_pose(model: &dyn Model, c2w: [[f32; 4]; 3]) -> [[f32; 4]; 3] {
    model.poses().map_or(c2w, |p| p.heldout_pose(c2w))
}
