//! The classic NeRF model: a coarse and a fine MLP field
//! (`fields::mlp`), stratified coarse samples and fine samples drawn from
//! the coarse weights along the occupied part of each ray
//! (`sampling::hierarchical`), both fields trained with the shared pass
//! (`models::pass`); views are rendered by the shared loop
//! (`render::rounds`) over the fine samples.

pub mod config;

pub use config::NerfConfig;

use super::{Model, ModelError, RenderOptions, StateSource};
use crate::engine::batch::{BatchStats, RayOutput, StepCtx, TrainRay};
use crate::engine::fields::mlp::MlpField;
use crate::engine::fields::{Field, Points, densities};
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::pass::{PassBuffers, train_pass};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::nerf_net::NetCtx;
use crate::engine::render::composite::{CompositeOptions, RaySamples, composite};
use crate::engine::render::rounds::{RoundSettings, render_in_rounds};
use crate::engine::rng::Rng;
use crate::engine::sampling::Samples;
use crate::engine::sampling::hierarchical::{self, Drawn, SegmentRay};
use crate::engine::sampling::occupancy::OccupancyGrid;

/// The kind's name in checkpoints, the API and `--model`.
pub const KIND: &str = "nerf";

/// The classic NeRF.
pub struct NerfModel {
    pub config: NerfConfig,
    scene: Scene,
    coarse: MlpField,
    fine: MlpField,
    params: Vec<f32>,
    grid: Option<OccupancyGrid>,
}

/// Reusable buffers of one thread.
#[derive(Default)]
struct Work {
    ctx: NetCtx,
    samples: Samples,
    pass: PassBuffers,
}

/// Samples per ray and round when rendering the fine pass.
const RENDER_ROUND: usize = 32;
/// Points whose densities one task evaluates for the occupancy grid.
const DENSITY_CHUNK: usize = 1024;
/// The name of the saved occupancy grid.
const OCCUPANCY: &str = "occupancy.density";

/// Lays out the classic model's parameters for `config` (without
/// allocating them): the coarse field, then the fine one.
pub fn layout(layout: &mut ParamLayout, config: &NerfConfig) -> (MlpField, MlpField) {
    (MlpField::new(layout, "coarse", config.net.clone()), MlpField::new(layout, "fine", config.net.clone()))
}

impl NerfModel {
    pub fn new(config: NerfConfig, scene: Scene, seed: u64) -> Self {
        let mut ps = ParamLayout::default();
        let (coarse, fine) = layout(&mut ps, &config);
        let mut params = vec![0.0; ps.len];
        let mut rng = Rng::new(seed);
        coarse.init(&mut params, &mut rng);
        fine.init(&mut params, &mut rng);
        let grid = config.occupancy.clone().map(|c| OccupancyGrid::new(c, scene.aabb()));
        Self { config, scene, coarse, fine, params, grid }
    }

    /// A model with saved parameters (its state comes back through
    /// [`Model::restore_state`]).
    pub fn from_parts(config: NerfConfig, scene: Scene, params: Vec<f32>) -> Result<Self, ModelError> {
        let m = Self::new(config, scene, 0);
        ModelError::check_size("parameters", m.params.len(), params.len())?;
        Ok(Self { params, ..m })
    }

    /// Uses another model's occupancy grid (same configuration).
    pub fn copy_grid_from(&mut self, other: &NerfModel) {
        self.grid = other.grid.clone();
    }

    /// The occupancy grid, when the model skips empty space.
    pub fn grid(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref()
    }

    /// Replaces the grid's running densities.
    pub fn set_grid_state(&mut self, density: Vec<f32>, step: u64) -> Result<(), ModelError> {
        let Some(g) = self.grid.as_mut() else { return Ok(()) };
        ModelError::check_size("occupancy grid cells", g.density.len(), density.len())?;
        g.density = density;
        g.apply(step, &[], &[]);
        Ok(())
    }

    /// The occupied part of a model-space ray, if it has one.
    fn segment_ray(&self, ray: &Ray) -> Option<SegmentRay> {
        SegmentRay::new(&self.scene, self.grid.as_ref(), ray)
    }

    /// Network evaluations per ray without skipping (coarse + fine + coarse again).
    pub fn dense_samples(&self) -> u64 {
        (2 * self.config.coarse_samples + self.config.fine_samples) as u64
    }

    /// Trains both fields on a chunk of rays.
    fn train_chunk(&self, w: &mut Work, chunk: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats {
        let scale = 1.0 / (ctx.batch_rays.max(1) as f32 * 3.0);
        let mut stats = BatchStats { rays: chunk.len() as u64, ..Default::default() };
        let (mut rays, mut segs, mut rngs) = (Vec::new(), Vec::new(), Vec::new());
        for r in chunk {
            match self.segment_ray(&r.ray) {
                Some(h) => {
                    rays.push(*r);
                    segs.push(h);
                    rngs.push(Some(Rng::stream(ctx.seed, ctx.step, r.index)));
                }
                None => {
                    // The ray sees only the background: no gradient, but it
                    // counts in the loss (of both passes).
                    let e = crate::engine::render::loss::l2(r.background, r.target, 0.0).0;
                    stats.sq_err += e;
                    stats.loss += 2.0 * e;
                }
            }
        }
        if segs.is_empty() {
            return stats;
        }
        let coarse = hierarchical::coarse(&segs, self.config.coarse_samples, &mut rngs);
        hierarchical::pack(&segs, &coarse, &mut w.samples);
        let c =
            train_pass(&self.coarse, &self.params, &rays, &mut w.samples, None, scale, &mut w.ctx, &mut w.pass, grads);
        let spans = &w.samples.spans;
        let fine = hierarchical::fine(&segs, &coarse, spans, &w.pass.weights, self.config.fine_samples, &mut rngs);
        hierarchical::pack(&segs, &fine, &mut w.samples);
        let f =
            train_pass(&self.fine, &self.params, &rays, &mut w.samples, None, scale, &mut w.ctx, &mut w.pass, grads);
        stats.samples = c.samples + f.samples;
        stats.sq_err += f.sq_err;
        stats.loss += c.sq_err + f.sq_err;
        stats
    }

    /// Renders a chunk of rays: the coarse field composited (with early
    /// termination) for the weights the fine samples are drawn from, then
    /// the fine field through the shared render loop.
    fn render_chunk(&self, w: &mut Work, chunk: &[Ray], background: [f32; 3], out: &mut [RayOutput]) -> BatchStats {
        let min_t = self.config.min_transmittance;
        let mut stats = BatchStats { rays: chunk.len() as u64, ..Default::default() };
        let (mut idx, mut segs) = (Vec::new(), Vec::new());
        for (i, r) in chunk.iter().enumerate() {
            match self.segment_ray(r) {
                Some(h) => {
                    idx.push(i);
                    segs.push(h);
                }
                None => out[i] = RayOutput { rgb: background, depth: 0.0, opacity: 0.0, median: 0.0 },
            }
        }
        if segs.is_empty() {
            return stats;
        }
        let mut rngs = vec![None; segs.len()];
        let coarse = hierarchical::coarse(&segs, self.config.coarse_samples, &mut rngs);
        let m = &mut w.samples;
        hierarchical::pack(&segs, &coarse, m);
        self.coarse.density(&self.params, Points { pos: &m.pos, dirs: &m.dirs, image: &[] }, &mut w.ctx);
        self.coarse.color(&self.params, &m.dirs, &mut w.ctx);
        let (sigma, rgb) = (self.coarse.sigma(&w.ctx), self.coarse.rgb(&w.ctx));
        w.pass.weights.resize(m.len(), 0.0);
        for &(o, k) in &m.spans {
            let (t, d, wt) = (&m.t[o..o + k], &m.delta[o..o + k], &mut w.pass.weights[o..o + k]);
            let s =
                RaySamples::new(&sigma[o..o + k], &rgb[3 * o..3 * (o + k)], t, d).expect("one span of packed samples");
            let opts = CompositeOptions { background, min_transmittance: min_t, opaque_last: false };
            composite(s, &opts, wt).expect("one weight per sample");
        }
        stats.samples += m.len() as u64;
        let fine = hierarchical::fine(&segs, &coarse, &m.spans, &w.pass.weights, self.config.fine_samples, &mut rngs);
        let mut drawn = Drawn::new(&segs, &fine);
        let settings = RoundSettings { round: RENDER_ROUND, min_transmittance: min_t, max_dropped_weight: 0.0 };
        let mut hit = vec![RayOutput::default(); segs.len()];
        let s = render_in_rounds(&self.fine, &self.params, &mut drawn, settings, background, &mut w.ctx, m, &mut hit);
        stats.samples += s.samples;
        for (&i, o) in idx.iter().zip(hit) {
            out[i] = o;
        }
        stats
    }
}

impl Model for NerfModel {
    super::model_accessors!();

    fn train_rays(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats {
        let mut w = Work::default();
        let mut stats = BatchStats::default();
        for chunk in rays.chunks(self.config.chunk_rays.max(1)) {
            stats.add(&self.train_chunk(&mut w, chunk, ctx, grads));
        }
        stats.skipped = (stats.rays * self.dense_samples()).saturating_sub(stats.samples);
        stats
    }

    fn after_step(&mut self, step: u64, seed: u64, _stats: &BatchStats) {
        let Some(g) = self.grid.as_ref() else { return };
        if !g.due(step) {
            return;
        }
        let (cells, pts) = g.update_points(step, seed);
        // Either network may put density where the other does not.
        let mut sigma = densities(&self.coarse, &self.params, &pts, DENSITY_CHUNK);
        let fine = densities(&self.fine, &self.params, &pts, DENSITY_CHUNK);
        for (a, b) in sigma.iter_mut().zip(fine) {
            *a = a.max(b);
        }
        if let Some(g) = self.grid.as_mut() {
            g.apply(step, &cells, &sigma);
        }
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        self.grid.iter().map(|g| (OCCUPANCY.to_string(), g.density.clone())).collect()
    }

    fn restore_state(&mut self, state: StateSource<'_>, step: u64) -> Result<(), ModelError> {
        if self.grid.is_none() {
            return Ok(());
        }
        let density = state(OCCUPANCY).ok_or_else(|| ModelError::MissingState(OCCUPANCY.into()))?;
        self.set_grid_state(density, step)
    }

    fn render_rays(
        &self,
        rays: &[Ray],
        background: [f32; 3],
        _options: &RenderOptions,
        out: &mut [RayOutput],
    ) -> BatchStats {
        let mut w = Work::default();
        let mut stats = BatchStats::default();
        let per_chunk = self.config.chunk_rays.max(1) * 8;
        for (chunk, outc) in rays.chunks(per_chunk).zip(out.chunks_mut(per_chunk)) {
            stats.add(&self.render_chunk(&mut w, chunk, background, outc));
        }
        stats.skipped = (stats.rays * self.dense_samples()).saturating_sub(stats.samples);
        stats
    }
}
