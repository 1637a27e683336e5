//! The real-capture model (issue 12, design `real-captures.md`): photographs
//! of an object in a real room, seen all around or from the front, with no
//! box around the scene and exposures that differ from photo to photo.
//!
//! - **Space**: the model's own normalisation puts the point the training
//!   cameras look at (`Scene::rig`'s focus) at the origin and the cameras
//!   `camera_radius` from it; a scene contraction maps all of space into the
//!   grids' cube (`fields::space`), so the background is modelled too. For
//!   forward-facing captures, `space: ndc` maps the mean training camera's
//!   frustum there instead (`space`).
//! - **Sampling**: proposal networks (`fields::proposal`) place each ray's
//!   samples over the ray-distance warp (`levels`); the last
//!   interval of a ray is opaque (photographs have no see-through pixels).
//! - **Field**: the fast model's networks in contracted space with a
//!   per-image appearance embedding (`fields::capture`); a new view takes
//!   the mean embedding of the images trained on, or one image's
//!   ([`RenderOptions::image`], chosen by `view::appearance`).
//! - **Training**: `pass` (colour, distortion and interlevel
//!   losses); **rendering**: the shared loop (`render::rounds`) over the
//!   final samples, with early termination and dropped colours.
//! - **Poses** (`pose_refine`): each training image's camera is corrected
//!   by six parameters (`nn::pose`) learning at `pose_lr_scale` times the
//!   networks' rate; held-out views are rendered from their cameras moved
//!   by the training cameras' common drift ([`PoseRefinement::heldout_pose`]), and
//!   [`CaptureModel::pose_report`] says how far the cameras moved.
//!
//! The configuration and its checks are in `config`.
//!

pub mod config;
pub mod levels;
pub mod pass;
mod roles;
pub mod space;

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, OnceLock};

use super::{Appearance, DeferredGrid, Model, ModelError, PoseRefinement, RayMeasure, RenderOptions, StateSource};
use crate::engine::batch::{BatchStats, RayOutput, StepCtx, TrainRay};
use crate::engine::fields::capture::{CaptureField, CaptureFieldConfig};
use crate::engine::fields::proposal::ProposalField;
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::capture::levels::Drawn;
use crate::engine::models::capture::pass::{
    CaptureBuffers, CaptureNets, PassSettings, RayInterval, capture_pass, samplable,
};
use crate::engine::nn::adam::LrGroup;
use crate::engine::nn::hashgrid::{GridRecord, HalfTable};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::pose::PoseRefine;
use crate::engine::nn::pose_report::{Gauge, PoseReport};
use crate::engine::render::rounds::{RoundSettings, render_in_rounds};
use crate::engine::rng::Rng;
use crate::engine::sampling::Samples;
use crate::engine::sampling::proposal::{ProposalRays, Warp};
pub use config::{CaptureConfig, ProposalConfig, Space};
use space::{check_resolved, resolve, space_map};

/// The kind's name in checkpoints, the API and `--model`.
pub const KIND: &str = "capture";

/// The model's networks and pose corrections, as laid out in its buffer.
pub struct Parts {
    pub field: CaptureField,
    pub proposals: Vec<ProposalField>,
    /// With `pose_refine` only.
    pub pose: Option<PoseRefine>,
}

/// Lays out the model's parameters for `config` (without allocating
/// them): the main field, then the proposal networks (`proposal0`, and
/// `proposal1` unless there is one level), then with `pose_refine` the
/// pose corrections (`pose`, `max_images` rows of 6), last, so that a model
/// without them is laid out as before they existed.
pub fn layout(layout: &mut ParamLayout, config: &CaptureConfig) -> Parts {
    let field_config = CaptureFieldConfig {
        grid: config.grid.clone(),
        hidden: config.hidden,
        geo_features: config.geo_features,
        init_density: config.init_density,
        max_images: config.max_images,
        appearance_dim: config.appearance_dim,
    };
    let field = CaptureField::new(layout, space_map(config), &field_config);
    let p = &config.proposal;
    let mut grids = vec![&p.coarse_grid];
    if p.fine_samples > 0 {
        grids.push(&p.fine_grid);
    }
    let proposals = grids
        .into_iter()
        .enumerate()
        .map(|(k, g)| {
            let name = format!("proposal{k}");
            ProposalField::new(layout, &name, space_map(config), g.clone(), p.hidden, config.init_density)
        })
        .collect();
    let pose = config.pose_refine.then(|| PoseRefine::new(layout, "pose", config.max_images));
    Parts { field, proposals, pose }
}

/// The model's own normalisation of a scene: the focus of the training
/// cameras at the origin and their median distance at `camera_radius`;
/// the unit cube as its box and `[near, far]` as its ray interval. A scene
/// without a rig keeps its box normalisation. Applying it twice changes
/// nothing (a checkpoint stores the normalised scene).
pub fn capture_scene(scene: &Scene, config: &CaptureConfig) -> Scene {
    let (centre, scale) = match &scene.rig {
        Some(rig) if rig.radius.is_finite() && rig.radius > 0.0 && rig.focus.iter().all(|v| v.is_finite()) => {
            (rig.focus, config.camera_radius / rig.radius)
        }
        _ => (scene.centre, scene.scale),
    };
    Scene {
        centre,
        scale,
        aabb_min: [-1.0; 3],
        aabb_max: [1.0; 3],
        near: config.near,
        far: config.far,
        ..scene.clone()
    }
}

/// One thread's buffers: the pass's (its levels and field context serve
/// rendering too) and the render loop's.
#[derive(Default)]
struct Scratch {
    pass: CaptureBuffers,
    samples: Samples,
    rays: Vec<Ray>,
    warps: Vec<Warp>,
    valid: Vec<usize>,
    index: Vec<u64>,
    out: Vec<RayOutput>,
}

thread_local! {
    /// Each worker thread's buffers, kept across steps and views.
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// Runs `f` with this thread's scratch buffers (fresh ones if they are in
/// use further up the stack).
fn with_scratch<R>(f: impl FnOnce(&mut Scratch) -> R) -> R {
    SCRATCH.with(|s| match s.try_borrow_mut() {
        Ok(mut s) => f(&mut s),
        Err(_) => f(&mut Scratch::default()),
    })
}

/// Rays rendered together by one thread.
const RENDER_CHUNK_RAYS: usize = 256;
/// Final samples per ray and round when rendering.
const RENDER_ROUND: usize = 8;
/// The name of the saved record of images trained on.
const SEEN: &str = "appearance.seen";
/// The name of the saved camera centres of the images trained on (with
/// pose refinement only).
const CENTRES: &str = "pose.centres";

/// The real-capture model.
pub struct CaptureModel {
    pub config: CaptureConfig,
    scene: Scene,
    field: CaptureField,
    proposals: Vec<ProposalField>,
    params: Vec<f32>,
    /// Intervals per ray at each level.
    intervals: Vec<usize>,
    /// Which images training has seen (their mean embedding is a new
    /// view's appearance).
    seen: Vec<AtomicBool>,
    /// The pose corrections (with `pose_refine`).
    pose: Option<PoseRefine>,
    /// Each image's camera centre in model space (f32 bits), as its
    /// training rays start there; `[max_images x 3]` with `pose_refine`,
    /// empty otherwise. The common drift is fitted over them.
    centres: Vec<AtomicU32>,
    /// Steps done (the annealing of the proposals' weights when rendering).
    step: u64,
    /// The grids' tables in half precision, built by the first render after
    /// the parameters last changed (`params_mut` drops them).
    render_tables: OnceLock<RenderTables>,
}

/// The tables renders read the hash grids from: each `None` when
/// `half_render` is off or the CPU cannot use half tables (the parameters
/// are read then).
#[derive(Default)]
struct RenderTables {
    main: Option<Arc<HalfTable>>,
    /// One per proposal network.
    proposals: Vec<Option<Arc<HalfTable>>>,
}

impl CaptureModel {
    /// A fresh model for `scene` (as the dataset gives it; normalised by
    /// [`capture_scene`]). With `space: ndc`, its NDC camera comes from the
    /// scene's training cameras (`space::resolve`), and a scene
    /// that cannot give one is refused.
    pub fn new(config: CaptureConfig, scene: Scene, seed: u64) -> Result<Self, ModelError> {
        let config = resolve(config, &scene)?;
        Ok(Self::init(config, scene, seed))
    }

    /// A fresh model for a configuration whose space is resolved.
    fn init(config: CaptureConfig, scene: Scene, seed: u64) -> Self {
        let mut ps = ParamLayout::default();
        let Parts { field, proposals, pose } = layout(&mut ps, &config);
        let mut params = vec![0.0; ps.len];
        let mut rng = Rng::new(seed);
        field.init(&mut params, &mut rng);
        for p in &proposals {
            p.init(&mut params, &mut rng);
        }
        let scene = capture_scene(&scene, &config);
        let seen = (0..config.max_images).map(|_| AtomicBool::new(false)).collect();
        let centres = match pose {
            Some(_) => (0..3 * config.max_images).map(|_| AtomicU32::new(0)).collect(),
            None => Vec::new(),
        };
        let intervals = config.intervals();
        Self {
            config,
            scene,
            field,
            proposals,
            params,
            intervals,
            seen,
            pose,
            centres,
            step: 0,
            render_tables: OnceLock::new(),
        }
    }

    /// A model with saved parameters (its state comes back through
    /// [`Model::restore_state`]).
    pub fn from_parts(config: CaptureConfig, scene: Scene, params: Vec<f32>) -> Result<Self, ModelError> {
        check_resolved(&config)?;
        let m = Self::init(config, scene, 0);
        ModelError::check_size("parameters", m.params.len(), params.len())?;
        Ok(Self { params, ..m })
    }

    /// The tables renders read the grids from (see `render_tables`).
    fn render_tables(&self) -> &RenderTables {
        self.render_tables.get_or_init(|| {
            if !self.config.half_render {
                return RenderTables::default();
            }
            let half = |t: Option<HalfTable>| t.map(Arc::new);
            RenderTables {
                main: half(self.field.half_table(&self.params)),
                proposals: self.proposals.iter().map(|p| half(p.half_table(&self.params))).collect(),
            }
        })
    }

    /// Makes the passes of `s` read the grids from `tables` (from the
    /// parameters: `&RenderTables::default()`, as training must), and stop
    /// a ray's proposal samples below transmittance `early_stop` (0: never,
    /// as training must; `Levels::set_early_stop`).
    fn read_grids_from(&self, s: &mut Scratch, tables: &RenderTables, early_stop: f32) {
        self.field.set_render_table(tables.main.clone(), &mut s.pass.ctx);
        s.pass.levels.set_render_tables(&self.proposals, &tables.proposals);
        s.pass.levels.set_early_stop(early_stop);
    }

    /// Where rays are sampled: `[near, far]`, and in a contraction rays
    /// starting nearer the focus than the training cameras start nearer
    /// ([`RayInterval::near_of`]); in NDC, `near` for every ray.
    fn interval(&self) -> RayInterval {
        let radius = match self.config.space {
            Space::Contract => self.config.camera_radius,
            Space::Ndc => 0.0,
        };
        RayInterval { near: self.config.near, far: self.config.far, radius }
    }

    /// The networks, for passes over them.
    fn nets(&self) -> CaptureNets<'_> {
        CaptureNets { proposals: &self.proposals, field: &self.field, params: &self.params }
    }

    /// Where rays are sampled, for people: `[near, far]` in model units
    /// (`near` raised to the dataset's near bound with `near_from_data`),
    /// against the training cameras' distance from their focus.
    /// `None` with `space: ndc` (its near plane is the NDC camera's).
    pub fn ray_interval(&self) -> Option<String> {
        let c = &self.config;
        (c.space == Space::Contract).then(|| {
            format!(
                "rays sampled from {:.3} to {} model units (the training cameras are {} from their focus)",
                c.near, c.far, c.camera_radius
            )
        })
    }

    /// The training images seen so far.
    pub fn seen_images(&self) -> Vec<u32> {
        (0..self.seen.len() as u32).filter(|&i| self.seen[i as usize].load(Ordering::Relaxed)).collect()
    }

    /// A new view's appearance: the mean embedding of the images trained on.
    pub fn mean_embedding(&self) -> Vec<f32> {
        self.field.appearance().mean_embedding(&self.params, self.seen_images())
    }

    /// The camera centres (model space) of the images trained on.
    fn trained_centres(&self) -> Vec<(u32, [f64; 3])> {
        let at = |k: usize| self.centres.get(k).map_or(0.0, |c| f64::from(f32::from_bits(c.load(Ordering::Relaxed))));
        let centre = |i: u32| std::array::from_fn(|a| at(3 * i as usize + a));
        self.seen_images().into_iter().map(|i| (i, centre(i))).collect()
    }

    /// How far pose refinement moved the cameras of the images trained on;
    /// `None` without pose refinement.
    pub fn pose_report(&self) -> Option<PoseReport> {
        let pose = self.pose.as_ref()?;
        Some(PoseReport::new(pose, &self.params, &self.trained_centres(), f64::from(self.config.camera_radius)))
    }

    /// The training cameras' common drift (zero without pose refinement).
    pub fn pose_gauge(&self) -> Gauge {
        match &self.pose {
            Some(pose) => Gauge::fit(pose, &self.params, &self.trained_centres()),
            None => Gauge::default(),
        }
    }

    /// The training pass's settings for a batch of `batch_rays` rays, from
    /// the configuration (tests override single fields of it).
    fn pass_settings(&self, batch_rays: usize) -> PassSettings<'_> {
        PassSettings {
            intervals: &self.intervals,
            interval: self.interval(),
            cull: Some(self.config.min_transmittance),
            batch_rays,
            interlevel: self.config.interlevel,
            distortion: self.config.distortion,
            pose: self.pose.as_ref(),
        }
    }

    /// Renders a chunk of model-space rays over `background`.
    fn render_chunk(&self, s: &mut Scratch, rays: &[Ray], background: [f32; 3], out: &mut [RayOutput]) -> BatchStats {
        let mut stats = BatchStats { rays: rays.len() as u64, ..Default::default() };
        let miss = RayOutput { rgb: background, depth: 0.0, opacity: 0.0, median: 0.0 };
        s.rays.clear();
        s.warps.clear();
        s.valid.clear();
        s.index.clear();
        let interval = self.interval();
        for (i, r) in rays.iter().enumerate() {
            match interval.warp(r) {
                Ok(w) if samplable(r) => {
                    s.valid.push(i);
                    s.rays.push(*r);
                    s.warps.push(w);
                    s.index.push(i as u64);
                }
                _ => out[i] = miss,
            }
        }
        if s.valid.is_empty() {
            return stats;
        }
        let placed = self.config.resampling(self.step).map_err(Into::into).and_then(|how| {
            let mut placement = Drawn::centred(how);
            let (nets, levels) = (self.nets(), &mut s.pass.levels);
            levels.place(nets.proposals, nets.params, &s.rays, &s.warps, &self.intervals, &mut placement, &s.index)
        });
        stats.proposal_samples = *placed.as_ref().unwrap_or(&0);
        let Some(fin) = placed.ok().and(s.pass.levels.last()) else {
            // Only with a configuration `check` refuses: nothing to show.
            s.valid.iter().for_each(|&i| out[i] = miss);
            return stats;
        };
        let Ok(mut sampler) = ProposalRays::new(&s.rays, &fin.t, true) else {
            s.valid.iter().for_each(|&i| out[i] = miss);
            return stats;
        };
        let settings = RoundSettings {
            round: RENDER_ROUND,
            min_transmittance: self.config.min_transmittance,
            max_dropped_weight: self.config.max_dropped_weight,
        };
        s.out.clear();
        s.out.resize(s.rays.len(), RayOutput::default());
        let (ctx, m) = (&mut s.pass.ctx, &mut s.samples);
        let r = render_in_rounds(&self.field, &self.params, &mut sampler, settings, background, ctx, m, &mut s.out);
        for (&i, o) in s.valid.iter().zip(&s.out) {
            out[i] = *o;
        }
        stats.samples = r.samples;
        stats.skipped = r.skipped;
        stats
    }
    /// Whether training passes record the main grid's gradient
    /// ([`Model::deferred`]): not with pose refinement, whose passes
    /// need the grid's input gradient at once.
    fn defers_grid(&self) -> bool {
        self.pose.is_none()
    }

    /// [`Model::train_rays`]; with `record`, the main grid's gradient is
    /// recorded there instead ([`DeferredGrid::train_rays_deferred`]).
    fn train(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        mut record: Option<&mut GridRecord>,
        mut errors: Option<&mut [RayMeasure]>,
    ) -> BatchStats {
        for r in rays {
            if let Some(flag) = self.seen.get(r.image as usize) {
                flag.store(true, Ordering::Relaxed);
            }
            // A pinhole camera's rays all start at its centre.
            let origin = [r.ray.origin.x, r.ray.origin.y, r.ray.origin.z];
            if let Some(c) = self.centres.get(3 * r.image as usize..3 * r.image as usize + 3) {
                c.iter().zip(origin).for_each(|(c, v)| c.store(v.to_bits(), Ordering::Relaxed));
            }
        }
        let mut stats = BatchStats::default();
        let Ok(how) = self.config.resampling(ctx.step) else {
            // Only with a configuration `check` refuses: a non-finite loss
            // makes the trainer skip the step.
            return BatchStats { loss: f64::NAN, rays: rays.len() as u64, ..stats };
        };
        let settings = self.pass_settings(ctx.batch_rays);
        with_scratch(|s| {
            self.read_grids_from(s, &RenderTables::default(), 0.0);
            match record.as_deref_mut() {
                Some(r) => self.field.begin_deferring(&mut s.pass.ctx, r),
                // Set every time: a pass that panicked while deferring left
                // the thread's scratch so.
                None => self.field.end_deferring(&mut s.pass.ctx, &mut GridRecord::default()),
            }
            let per = self.config.chunk_rays.max(1);
            for (c, chunk) in rays.chunks(per).enumerate() {
                let mut placement = Drawn::jittered(how, ctx.seed, ctx.step);
                let p = capture_pass(self.nets(), &settings, chunk, &mut placement, &mut s.pass, grads);
                if let Some(e) = errors.as_deref_mut().and_then(|e| e.get_mut(c * per..c * per + chunk.len())) {
                    e.copy_from_slice(&s.pass.errors);
                }
                stats.add(&BatchStats {
                    sq_err: p.sq_err,
                    loss: p.loss(),
                    samples: p.samples,
                    proposal_samples: p.proposal_samples,
                    skipped: p.culled,
                    rays: p.rays,
                });
            }
            if let Some(r) = record {
                self.field.end_deferring(&mut s.pass.ctx, r);
            }
        });
        stats
    }
}

impl Model for CaptureModel {
    super::model_accessors!(params_mut: render_tables);

    fn train_rays(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats {
        self.train(rays, ctx, grads, None, None)
    }

    fn train_rays_measured(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        errors: &mut [RayMeasure],
    ) -> BatchStats {
        self.train(rays, ctx, grads, None, Some(errors))
    }

    /// The main grid, without pose refinement (whose passes need the
    /// grid's input gradient at once).
    fn deferred(&self) -> Option<&dyn DeferredGrid> {
        self.defers_grid().then_some(self as &dyn DeferredGrid)
    }

    fn after_step(&mut self, step: u64, _seed: u64, _stats: &BatchStats) {
        self.step = step;
    }

    fn batch_rays(&self) -> Option<usize> {
        Some(self.config.rays_per_step)
    }

    fn appearance(&self) -> Option<&dyn Appearance> {
        Some(self)
    }

    fn poses(&self) -> Option<&dyn PoseRefinement> {
        self.pose.is_some().then_some(self as &dyn PoseRefinement)
    }

    fn log_note(&self) -> Option<String> {
        self.ray_interval()
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        let seen = self.seen.iter().map(|f| f32::from(u8::from(f.load(Ordering::Relaxed)))).collect();
        let mut state = vec![(SEEN.to_string(), seen)];
        if self.pose.is_some() {
            let centres = self.centres.iter().map(|c| f32::from_bits(c.load(Ordering::Relaxed))).collect();
            state.push((CENTRES.to_string(), centres));
        }
        state
    }

    fn restore_state(&mut self, state: StateSource<'_>, step: u64) -> Result<(), ModelError> {
        let seen = state(SEEN).ok_or_else(|| ModelError::MissingState(SEEN.into()))?;
        ModelError::check_size("images seen", self.seen.len(), seen.len())?;
        for (flag, &v) in self.seen.iter().zip(&seen) {
            flag.store(v != 0.0, Ordering::Relaxed);
        }
        if self.pose.is_some() {
            let centres = state(CENTRES).ok_or_else(|| ModelError::MissingState(CENTRES.into()))?;
            ModelError::check_size("camera centres", self.centres.len(), centres.len())?;
            for (c, v) in self.centres.iter().zip(centres) {
                c.store(v.to_bits(), Ordering::Relaxed);
            }
        }
        self.step = step;
        Ok(())
    }

    fn lr_groups(&self) -> Vec<LrGroup> {
        let scale = self.config.pose_lr_scale;
        self.pose.iter().map(|p| LrGroup { range: p.range.clone(), scale }).collect()
    }

    /// Renders with the appearance `options` names: an image's embedding
    /// (zero for an image beyond the table, or one never trained on:
    /// `view::appearance` refuses those before they get here), or the
    /// mean of the images trained on.
    fn render_rays(
        &self,
        rays: &[Ray],
        background: [f32; 3],
        options: &RenderOptions,
        out: &mut [RayOutput],
    ) -> BatchStats {
        let embedding = Appearance::embedding(self, options);
        with_scratch(|s| {
            self.field.set_view_appearance(&self.params, embedding.as_deref(), &mut s.pass.ctx);
            // Proposal rays stop where rendering's do.
            self.read_grids_from(s, self.render_tables(), self.config.min_transmittance);
            let mut stats = BatchStats::default();
            for (chunk, o) in rays.chunks(RENDER_CHUNK_RAYS).zip(out.chunks_mut(RENDER_CHUNK_RAYS)) {
                stats.add(&self.render_chunk(s, chunk, background, o));
            }
            // The thread's scratch keeps no reference to tables that the
            // next `params_mut` makes stale.
            self.read_grids_from(s, &RenderTables::default(), 0.0);
            stats
        })
    }
}

#[cfg(test)]
#[path = "model_tests.rs"]
mod tests;

#[cfg(test)]
#[path = "ndc_tests.rs"]
mod ndc_tests;
