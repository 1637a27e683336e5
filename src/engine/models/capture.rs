//! The real-capture model (issue 12, design `real-captures.md`): photographs
//! of an object in a real room, seen all around or from the front, with no
//! box around the scene and exposures that differ from photo to photo.
//!
//! - **Space**: the model's own normalisation puts the point the training
//!   cameras look at (`Scene::rig`'s focus) at the origin and the cameras
//!   `camera_radius` from it; a scene contraction maps all of space into the
//!   grids' cube (`fields::space`), so the background is modelled too.
//! - **Sampling**: proposal networks (`fields::proposal`) place each ray's
//!   samples over the ray-distance warp (`train::capture_levels`); the last
//!   interval of a ray is opaque (photographs have no see-through pixels).
//! - **Field**: the fast model's networks in contracted space with a
//!   per-image appearance embedding (`fields::capture`); new views use the
//!   mean embedding of the images trained on.
//! - **Training**: `train::capture_pass` (colour, distortion and interlevel
//!   losses); **rendering**: the shared loop (`render::rounds`) over the
//!   final samples, with early termination and dropped colours.
//!
//! Not built yet (later steps of the design): NDC for forward-facing
//! captures as a model option, camera pose refinement, a chosen image's
//! appearance when rendering.

use std::sync::atomic::{AtomicBool, Ordering};

use super::config::{Checks, FieldValue, Footprint, ModelSpec};
use super::{BatchStats, Model, ModelError, RayOutput, StateSource, StepCtx, TrainRay};
use crate::engine::fields::capture::{CaptureField, CaptureFieldConfig};
use crate::engine::fields::proposal::ProposalField;
use crate::engine::fields::space::{Norm, SpaceMap};
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::nn::adam::AdamConfig;
use crate::engine::nn::hashgrid::{HashGrid, HashGridConfig};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::sh;
use crate::engine::render::rounds::{RoundSettings, render_in_rounds};
use crate::engine::rng::Rng;
use crate::engine::sampling::Samples;
use crate::engine::sampling::proposal::{Anneal, ProposalError, ProposalRays, Resampling, Warp};
use crate::engine::train::capture_levels::Drawn;
use crate::engine::train::capture_pass::{CaptureBuffers, CaptureNets, PassSettings, capture_pass, samplable};

/// The kind's name in checkpoints, the API and `--model`.
pub const KIND: &str = "capture";

/// The proposal networks and how their weights place the next level.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ProposalConfig {
    /// Intervals per ray of the first level, stratified in `s` (64).
    pub coarse_samples: usize,
    /// Intervals of the second level, drawn from the first's weights (32);
    /// 0: one proposal level only.
    pub fine_samples: usize,
    /// The first network's hash grid (5 levels, 2^15, 16 to 128).
    pub coarse_grid: HashGridConfig,
    /// The second network's (5 levels, 2^15, 16 to 256).
    pub fine_grid: HashGridConfig,
    /// Hidden width of both networks (16).
    pub hidden: usize,
    /// Added to every weight before drawing the next level (0.01,
    /// nerfacto's `histogram_padding`): no interval becomes unreachable.
    pub padding: f32,
    /// Steps over which the weights' exponent rises from 0 to 1 (500).
    pub anneal_steps: u64,
    /// How fast it rises at first (10).
    pub anneal_slope: f32,
}

/// The real-capture model's configuration: every tunable is a scalar, so
/// `--set key=value` reaches each.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CaptureConfig {
    /// The norm of the scene contraction: `linf` (the whole grid cube is
    /// used) or `l2`.
    pub contraction: Norm,
    /// Model units from the focus to the cameras (their median distance):
    /// the unit cube around the focus, which the contraction leaves as it
    /// is, reaches that far (1).
    pub camera_radius: f32,
    /// The ray interval in model units (0.05 to 1000).
    pub near: f32,
    pub far: f32,
    /// The main hash grid (16 levels, 2^16, 16 to 2048: the contraction
    /// spends most of the cube on the background, so the finest level is
    /// finer than the fast model's).
    pub grid: HashGridConfig,
    /// Hidden width of both MLPs (64).
    pub hidden: usize,
    /// Outputs of the density MLP: log-density and geometry features (16).
    pub geo_features: usize,
    /// Density of the untrained field (1). nerfacto starts nearly
    /// transparent (0.01) for fewer early floaters over its 30k steps; in
    /// the few thousand steps of a CPU budget, a field that starts
    /// transparent explains the photos by what it paints far away (the
    /// opaque last interval) before it builds the foreground, and generalises
    /// worse: on `tests/train_capture.rs`'s scene, `capture-tiny` reaches
    /// 15.5/13.9/15.2 dB held out (seeds 1-3) from 0.01, 19.8/19.4/17.6
    /// from 0.1 and 21.6/20.7/19.1 from 1. To be measured on real captures.
    pub init_density: f32,
    /// Values of each image's appearance embedding (16; 0: none).
    pub appearance_dim: usize,
    /// Images with an embedding (2000, `radiance poses`' limit); frames
    /// beyond it are trained with a zero embedding.
    pub max_images: usize,
    pub proposal: ProposalConfig,
    /// Main-field samples (final intervals) per ray (32).
    pub samples: usize,
    /// Rays per training step (1024).
    pub rays_per_step: usize,
    /// Training rays processed together by one thread (256).
    pub chunk_rays: usize,
    /// Weight of the interlevel loss, the proposals' training signal (1).
    pub interlevel: f32,
    /// Weight of the distortion loss (0.002).
    pub distortion: f32,
    /// Transmittance below which rendering stops, and behind which
    /// training skips a ray's samples (1e-4).
    pub min_transmittance: f32,
    /// Weight per ray that rendering may leave uncoloured (1e-3).
    pub max_dropped_weight: f32,
}

impl Default for CaptureConfig {
    fn default() -> Self {
        Self {
            contraction: Norm::Linf,
            camera_radius: 1.0,
            near: 0.05,
            far: 1000.0,
            grid: HashGridConfig { levels: 16, log2_table: 16, base_resolution: 16, finest_resolution: 2048 },
            hidden: 64,
            geo_features: 16,
            init_density: 1.0,
            appearance_dim: 16,
            max_images: 2000,
            proposal: ProposalConfig {
                coarse_samples: 64,
                fine_samples: 32,
                coarse_grid: HashGridConfig { levels: 5, log2_table: 15, base_resolution: 16, finest_resolution: 128 },
                fine_grid: HashGridConfig { levels: 5, log2_table: 15, base_resolution: 16, finest_resolution: 256 },
                hidden: 16,
                padding: 0.01,
                anneal_steps: 500,
                anneal_slope: 10.0,
            },
            samples: 32,
            rays_per_step: 1024,
            chunk_rays: 256,
            interlevel: 1.0,
            distortion: 0.002,
            min_transmittance: 1e-4,
            max_dropped_weight: 1e-3,
        }
    }
}

impl CaptureConfig {
    /// A small model for previews and tests: 8 grid levels up to 256,
    /// narrow MLPs, proposals of 16 and 8 intervals and 8 final samples.
    pub fn tiny() -> Self {
        let d = Self::default();
        Self {
            grid: HashGridConfig { levels: 8, log2_table: 12, base_resolution: 8, finest_resolution: 256 },
            hidden: 32,
            geo_features: 8,
            appearance_dim: 8,
            proposal: ProposalConfig {
                coarse_samples: 16,
                fine_samples: 8,
                coarse_grid: HashGridConfig { levels: 4, log2_table: 12, base_resolution: 8, finest_resolution: 64 },
                fine_grid: HashGridConfig { levels: 4, log2_table: 12, base_resolution: 8, finest_resolution: 128 },
                hidden: 16,
                ..d.proposal
            },
            samples: 8,
            rays_per_step: 512,
            chunk_rays: 128,
            ..d
        }
    }

    /// Intervals per ray at each proposal level, then the final level.
    fn intervals(&self) -> Vec<usize> {
        let p = &self.proposal;
        let mut v = vec![p.coarse_samples];
        if p.fine_samples > 0 {
            v.push(p.fine_samples);
        }
        v.push(self.samples);
        v
    }

    /// The weights' exponent and padding at training step `step`.
    fn resampling(&self, step: u64) -> Result<Resampling, ProposalError> {
        let p = &self.proposal;
        Resampling::new(Anneal::new(p.anneal_steps, p.anneal_slope)?.exponent(step), p.padding)
    }
}

/// Records a float field that must be finite and positive.
fn positive(c: &mut Checks, field: &'static str, value: f32, allowed: &str) {
    if !(value.is_finite() && value > 0.0) {
        c.fail(field, FieldValue::Float(value), allowed.into());
    }
}

/// Records a float field that must be finite and not negative.
fn non_negative(c: &mut Checks, field: &'static str, value: f32) {
    if !(value.is_finite() && value >= 0.0) {
        c.fail(field, FieldValue::Float(value), "a finite number >= 0".into());
    }
}

/// A hash grid's fields, named by `names` (levels, log2_table,
/// base_resolution, finest_resolution).
fn check_grid(c: &mut Checks, g: &HashGridConfig, names: [&'static str; 4]) {
    c.int(names[0], g.levels, 1..=32);
    c.int(names[1], g.log2_table, 8..=24);
    c.int(names[2], g.base_resolution, 2..=4096);
    c.int(names[3], g.finest_resolution, u64::from(g.base_resolution)..=8192);
}

impl ModelSpec for CaptureConfig {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn check(&self, c: &mut Checks) {
        positive(c, "camera_radius", self.camera_radius, "a finite number > 0");
        positive(c, "near", self.near, "a finite number > 0");
        // Beyond the near bound (beyond 0 when that is itself refused, so
        // each message names one field).
        let floor = if self.near.is_finite() && self.near > 0.0 { self.near } else { 0.0 };
        if !(self.far.is_finite() && self.far > floor) {
            c.fail("far", FieldValue::Float(self.far), format!("a finite number > {floor}"));
        }
        check_grid(c, &self.grid, ["grid.levels", "grid.log2_table", "grid.base_resolution", "grid.finest_resolution"]);
        c.int("hidden", self.hidden, 1..=256);
        c.int("geo_features", self.geo_features, 1..=64);
        positive(c, "init_density", self.init_density, "a finite number > 0");
        c.int("appearance_dim", self.appearance_dim, 0..=64);
        c.int("max_images", self.max_images, 1..=100_000);
        let p = &self.proposal;
        c.int("proposal.coarse_samples", p.coarse_samples, 1..=1024);
        c.int("proposal.fine_samples", p.fine_samples, 0..=1024);
        let coarse = ["proposal.coarse_grid.levels", "proposal.coarse_grid.log2_table"];
        let coarse_res = ["proposal.coarse_grid.base_resolution", "proposal.coarse_grid.finest_resolution"];
        check_grid(c, &p.coarse_grid, [coarse[0], coarse[1], coarse_res[0], coarse_res[1]]);
        let fine = ["proposal.fine_grid.levels", "proposal.fine_grid.log2_table"];
        let fine_res = ["proposal.fine_grid.base_resolution", "proposal.fine_grid.finest_resolution"];
        check_grid(c, &p.fine_grid, [fine[0], fine[1], fine_res[0], fine_res[1]]);
        c.int("proposal.hidden", p.hidden, 1..=256);
        non_negative(c, "proposal.padding", p.padding);
        positive(c, "proposal.anneal_slope", p.anneal_slope, "a finite number > 0");
        c.int("samples", self.samples, 1..=1024);
        c.int("rays_per_step", self.rays_per_step, 1..=(1 << 16));
        c.int("chunk_rays", self.chunk_rays, 1..=4096);
        non_negative(c, "interlevel", self.interlevel);
        non_negative(c, "distortion", self.distortion);
        c.unit_open("min_transmittance", self.min_transmittance);
        c.unit_open("max_dropped_weight", self.max_dropped_weight);
    }

    fn build(&self, scene: Scene, seed: u64) -> Box<dyn Model> {
        Box::new(CaptureModel::new(self.clone(), scene, seed))
    }

    fn rebuild(&self, scene: Scene, params: Vec<f32>) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(CaptureModel::from_parts(self.clone(), scene, params)?))
    }

    /// Instant-NGP's (nerfacto's fields use the same 1e-2 and epsilon).
    fn adam(&self) -> AdamConfig {
        AdamConfig { lr: 1e-2, lr_end: 1e-3, beta1: 0.9, beta2: 0.99, eps: 1e-15 }
    }

    /// Photographs are opaque: the last interval of every ray is too, and
    /// RGBA images are trained on the dataset's background.
    fn random_background(&self) -> bool {
        false
    }

    /// One training thread's chunk: `chunk_rays` rays (or fewer, when a
    /// step's rays split between the threads are fewer) with every level's
    /// samples, the networks' activations and gradients, and the pass's
    /// per-sample buffers. Rendering uses the same buffers, for fewer
    /// samples.
    fn footprint(&self, threads: u64) -> Footprint {
        let mut ps = ParamLayout::default();
        layout(&mut ps, self);
        let rays = (self.chunk_rays as u64).min((self.rays_per_step as u64).div_ceil(threads.max(1))).max(1);
        let width = |g: &HashGridConfig| HashGrid::new(&mut ParamLayout::default(), g.clone()).width() as u64;
        // Samples (t, delta, position, direction) and edges in s and t,
        // twice: they are pushed, and a growing vector may hold up to twice
        // what it was given.
        let sample = 2 * (8 + 2);
        // Proposal: unit position, encoding and its gradient, hidden and its
        // gradient, raw and density, weight, dL/dw, dL/dsigma, colours (zero).
        let proposal = |g: &HashGridConfig| sample + 3 + 2 * width(g) + 2 * self.proposal.hidden as u64 + 2 + 3 + 3;
        let p = &self.proposal;
        let mut per_ray = p.coarse_samples as u64 * proposal(&p.coarse_grid);
        if p.fine_samples > 0 {
            per_ray += p.fine_samples as u64 * proposal(&p.fine_grid);
        }
        let (h, g, gw) = (self.hidden as u64, self.geo_features as u64, width(&self.grid));
        // Main: as the fast model's sample (unit position, encoding,
        // hidden, features, density, SH code, two colour hiddens, colour;
        // their gradients), the image and its slot, and the pass's weight,
        // gradients, full weights and kept index.
        let main = sample + (3 + gw + h + g + 1 + sh::WIDTH as u64 + 2 * h + 3) + (3 + 2 * h + g + gw) + 2 + 8;
        per_ray += self.samples as u64 * main;
        Footprint { params: ps.len as u64, occupancy_cells: 0, activations: rays * per_ray }
    }
}

/// The space the grids live in.
fn space(config: &CaptureConfig) -> SpaceMap {
    SpaceMap::Contract { norm: config.contraction }
}

/// Lays out the model's parameters for `config` (without allocating
/// them): the main field, then the proposal networks (`proposal0`, and
/// `proposal1` unless there is one level).
pub fn layout(layout: &mut ParamLayout, config: &CaptureConfig) -> (CaptureField, Vec<ProposalField>) {
    let field_config = CaptureFieldConfig {
        grid: config.grid.clone(),
        hidden: config.hidden,
        geo_features: config.geo_features,
        init_density: config.init_density,
        max_images: config.max_images,
        appearance_dim: config.appearance_dim,
    };
    let field = CaptureField::new(layout, space(config), &field_config);
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
            ProposalField::new(layout, &name, space(config), g.clone(), p.hidden, config.init_density)
        })
        .collect();
    (field, proposals)
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
    /// Steps done (the annealing of the proposals' weights when rendering).
    step: u64,
}

impl CaptureModel {
    /// A fresh model for `scene` (normalised by [`capture_scene`]).
    pub fn new(config: CaptureConfig, scene: Scene, seed: u64) -> Self {
        let mut ps = ParamLayout::default();
        let (field, proposals) = layout(&mut ps, &config);
        let mut params = vec![0.0; ps.len];
        let mut rng = Rng::new(seed);
        field.init(&mut params, &mut rng);
        for p in &proposals {
            p.init(&mut params, &mut rng);
        }
        let scene = capture_scene(&scene, &config);
        let seen = (0..config.max_images).map(|_| AtomicBool::new(false)).collect();
        let intervals = config.intervals();
        Self { config, scene, field, proposals, params, intervals, seen, step: 0 }
    }

    /// A model with saved parameters (its state comes back through
    /// [`Model::restore_state`]).
    pub fn from_parts(config: CaptureConfig, scene: Scene, params: Vec<f32>) -> Result<Self, ModelError> {
        let m = Self::new(config, scene, 0);
        ModelError::check_size("parameters", m.params.len(), params.len())?;
        Ok(Self { params, ..m })
    }

    /// The networks, for passes over them.
    fn nets(&self) -> CaptureNets<'_> {
        CaptureNets { proposals: &self.proposals, field: &self.field, params: &self.params }
    }

    /// The training images seen so far.
    pub fn seen_images(&self) -> Vec<u32> {
        (0..self.seen.len() as u32).filter(|&i| self.seen[i as usize].load(Ordering::Relaxed)).collect()
    }

    /// A new view's appearance: the mean embedding of the images trained on.
    pub fn mean_embedding(&self) -> Vec<f32> {
        self.field.appearance().mean_embedding(&self.params, self.seen_images())
    }

    /// Renders a chunk of model-space rays over `background`.
    fn render_chunk(&self, s: &mut Scratch, rays: &[Ray], background: [f32; 3], out: &mut [RayOutput]) -> BatchStats {
        let mut stats = BatchStats { rays: rays.len() as u64, ..Default::default() };
        let miss = RayOutput { rgb: background, depth: 0.0, opacity: 0.0 };
        s.rays.clear();
        s.warps.clear();
        s.valid.clear();
        s.index.clear();
        for (i, r) in rays.iter().enumerate() {
            match Warp::for_ray(r, self.config.near, self.config.far) {
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
}

impl Model for CaptureModel {
    super::model_accessors!();

    fn train_rays(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats {
        for r in rays {
            if let Some(flag) = self.seen.get(r.image as usize) {
                flag.store(true, Ordering::Relaxed);
            }
        }
        let mut stats = BatchStats::default();
        let Ok(how) = self.config.resampling(ctx.step) else {
            // Only with a configuration `check` refuses: a non-finite loss
            // makes the trainer skip the step.
            return BatchStats { loss: f64::NAN, rays: rays.len() as u64, ..stats };
        };
        let settings = PassSettings {
            intervals: &self.intervals,
            near: self.config.near,
            far: self.config.far,
            cull: Some(self.config.min_transmittance),
            batch_rays: ctx.batch_rays,
            interlevel: self.config.interlevel,
            distortion: self.config.distortion,
        };
        with_scratch(|s| {
            for chunk in rays.chunks(self.config.chunk_rays.max(1)) {
                let mut placement = Drawn::jittered(how, ctx.seed, ctx.step);
                let p = capture_pass(self.nets(), &settings, chunk, &mut placement, &mut s.pass, grads);
                stats.add(&BatchStats {
                    sq_err: p.sq_err,
                    loss: p.loss(),
                    samples: p.samples,
                    skipped: p.culled,
                    rays: p.rays,
                });
            }
        });
        stats
    }

    fn after_step(&mut self, step: u64, _seed: u64, _stats: &BatchStats) {
        self.step = step;
    }

    fn batch_rays(&self) -> Option<usize> {
        Some(self.config.rays_per_step)
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        let seen = self.seen.iter().map(|f| f32::from(u8::from(f.load(Ordering::Relaxed)))).collect();
        vec![(SEEN.to_string(), seen)]
    }

    fn restore_state(&mut self, state: StateSource<'_>, step: u64) -> Result<(), ModelError> {
        let seen = state(SEEN).ok_or_else(|| ModelError::MissingState(SEEN.into()))?;
        ModelError::check_size("images seen", self.seen.len(), seen.len())?;
        for (flag, &v) in self.seen.iter().zip(&seen) {
            flag.store(v != 0.0, Ordering::Relaxed);
        }
        self.step = step;
        Ok(())
    }

    fn render_rays(&self, rays: &[Ray], background: [f32; 3], out: &mut [RayOutput]) -> BatchStats {
        let mean = self.mean_embedding();
        with_scratch(|s| {
            self.field.set_view_appearance(&self.params, Some(&mean), &mut s.pass.ctx);
            let mut stats = BatchStats::default();
            for (chunk, o) in rays.chunks(RENDER_CHUNK_RAYS).zip(out.chunks_mut(RENDER_CHUNK_RAYS)) {
                stats.add(&self.render_chunk(s, chunk, background, o));
            }
            stats
        })
    }
}

#[cfg(test)]
#[path = "capture_tests.rs"]
mod tests;
