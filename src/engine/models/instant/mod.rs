//! The fast model (Instant-NGP): the hash-grid field (`fields::hash_grid`)
//! sampled by constant steps through the cells an occupancy grid marks
//! occupied (`sampling::marcher`), trained with the shared pass
//! (`models::pass`) and rendered by the shared loop (`render::rounds`).
//!
//! What a scene does not need is skipped: rays are clipped to the scene box,
//! empty cells are stepped over, and when rendering the colour network runs
//! only on samples in front of the point where transmittance falls below
//! `min_transmittance`.

pub mod config;

pub use config::InstantConfig;

use rayon::prelude::*;

use super::{Model, ModelError, RenderOptions, StateSource};
use crate::engine::batch::{BatchStats, RayOutput, StepCtx, TrainRay};
use crate::engine::fields::hash_grid::{Ctx, HashGridField};
use crate::engine::fields::{Field, Points, densities};
use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::pass::{PassBuffers, train_pass};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::render::composite::{CompositeOptions, RaySamples, composite, optical_depth};
use crate::engine::render::rounds::{RoundSettings, render_in_rounds};
use crate::engine::rng::Rng;
use crate::engine::sampling::Samples;
use crate::engine::sampling::marcher::GridMarcher;
use crate::engine::sampling::occupancy::{OccupancyGrid, Probe};

/// The kind's name in checkpoints, the API and `--model`.
pub const KIND: &str = "instant";

/// One thread's buffers: the field's activations, the samples and the
/// training pass's buffers.
type Scratch = (Ctx, Samples, PassBuffers);

thread_local! {
    /// Each worker thread's activation and sample buffers, kept across
    /// steps and views: fresh ones cost page faults and zero-filling every
    /// step (about 6% of training time in the profile).
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Default::default());
}

/// Runs `f` with this thread's scratch buffers (fresh ones if they are in
/// use further up the stack).
fn with_scratch<R>(f: impl FnOnce(&mut Scratch) -> R) -> R {
    SCRATCH.with(|s| match s.try_borrow_mut() {
        Ok(mut s) => f(&mut s),
        Err(_) => f(&mut Default::default()),
    })
}

/// Rays rendered together by one thread (in rounds of samples).
const RENDER_CHUNK_RAYS: usize = 256;
/// Samples per ray and round when rendering.
const RENDER_ROUND: usize = 16;
/// Points whose densities one task evaluates for the occupancy grid.
const DENSITY_CHUNK: usize = 4096;

/// The fast model.
pub struct InstantModel {
    pub config: InstantConfig,
    scene: Scene,
    field: HashGridField,
    params: Vec<f32>,
    pub grid: OccupancyGrid,
    /// Running mean of samples per training ray (sets the batch size).
    samples_per_ray: f64,
    dt: f32,
}

/// The field for `config` over `scene`'s box, its parameters laid out in
/// `layout` (without allocating them).
fn field(layout: &mut ParamLayout, config: &InstantConfig, scene: &Scene) -> HashGridField {
    let aabb = (Vec3::from_array(scene.aabb_min), Vec3::from_array(scene.aabb_max));
    HashGridField::new(layout, config.grid.clone(), config.hidden, config.geo_features, aabb)
}

/// Lays out the fast model's parameters for `config` (without allocating
/// them): what [`InstantModel::new`] allocates.
pub fn layout(layout: &mut ParamLayout, config: &InstantConfig) {
    // The box only scales positions; the layout does not depend on it.
    let unit = (Vec3::splat(0.0), Vec3::splat(1.0));
    HashGridField::new(layout, config.grid.clone(), config.hidden, config.geo_features, unit);
}

impl InstantModel {
    pub fn new(mut config: InstantConfig, scene: Scene, seed: u64) -> Self {
        let mut layout = ParamLayout::default();
        let field = field(&mut layout, &config, &scene);
        let mut params = vec![0.0; layout.len];
        field.init(&mut params, &mut Rng::new(seed));
        let aabb = scene.aabb();
        let dt = (aabb.max - aabb.min).norm() / config.steps_per_diagonal.max(1) as f32;
        if config.occupancy.threshold <= 0.0 {
            // Empty: less than 1% opacity over one marching step.
            config.occupancy.threshold = 0.01 / dt;
        }
        if config.occupancy.dilate.is_none() {
            // The marcher tests each sample's own cell, so dilation only adds
            // a shell of cells the threshold called empty. Where transparent
            // training pixels teach that the space around the object is
            // empty, skipping that shell is both faster and sharper (lego,
            // 60 s: 30.4 dB and 15 samples per ray, against 29.6 dB and 22);
            // a capture without them may need faint density in that shell
            // to explain its background (fox: 22.0 dB undilated, 24.0 dB
            // dilated), so it keeps it.
            config.occupancy.dilate = Some(!scene.transparent);
        }
        let grid = OccupancyGrid::new(config.occupancy.clone(), aabb);
        let spr = 64.0;
        Self { config, scene, field, params, grid, samples_per_ray: spr, dt }
    }

    /// A model with saved parameters (its state comes back through
    /// [`Model::restore_state`]).
    pub fn from_parts(config: InstantConfig, scene: Scene, params: Vec<f32>) -> Result<Self, ModelError> {
        let m = Self::new(config, scene, 0);
        ModelError::check_size("parameters", m.params.len(), params.len())?;
        Ok(Self { params, ..m })
    }

    /// Restores the occupancy grid and batch-size state.
    pub fn set_state(&mut self, density: Vec<f32>, samples_per_ray: f64, step: u64) -> Result<(), ModelError> {
        ModelError::check_size("occupancy grid cells", self.grid.density.len(), density.len())?;
        self.grid.density = density;
        self.grid.apply(step, &[], &[]);
        if samples_per_ray.is_finite() && samples_per_ray > 0.0 {
            self.samples_per_ray = samples_per_ray;
        }
        Ok(())
    }

    fn marcher(&self) -> GridMarcher<'_> {
        GridMarcher { scene: &self.scene, grid: &self.grid, dt: self.dt, max_samples: self.config.max_samples }
    }

    fn train_chunk(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32], s: &mut Scratch) -> BatchStats {
        let (c, m, buf) = s;
        let plain: Vec<Ray> = rays.iter().map(|r| r.ray).collect();
        let mut rng = Rng::stream(ctx.seed, ctx.step, rays.first().map_or(0, |r| r.index));
        self.marcher().march(&plain, Some(&mut rng), m);
        let skipped = m.skipped;
        let scale = 1.0 / (ctx.batch_rays.max(1) as f32 * 3.0);
        // Samples behind the point where transmittance falls below the
        // threshold contribute less than it: skip their colour and backward.
        let cull = Some(self.config.min_transmittance);
        let p = train_pass(&self.field, &self.params, rays, m, cull, scale, c, buf, grads);
        BatchStats {
            sq_err: p.sq_err,
            loss: p.sq_err,
            samples: p.samples,
            skipped: skipped + p.culled,
            rays: rays.len() as u64,
            ..BatchStats::default()
        }
    }
}

impl Model for InstantModel {
    super::model_accessors!();

    fn train_rays(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats {
        with_scratch(|s| {
            let mut stats = BatchStats::default();
            for chunk in rays.chunks(self.config.chunk_rays.max(1)) {
                stats.add(&self.train_chunk(chunk, ctx, grads, s));
            }
            stats
        })
    }

    fn after_step(&mut self, step: u64, seed: u64, stats: &BatchStats) {
        if stats.rays > 0 {
            let spr = stats.samples as f64 / stats.rays as f64;
            self.samples_per_ray = 0.9 * self.samples_per_ray + 0.1 * spr.max(1.0);
        }
        if self.grid.due(step) {
            let (cells, pts) = self.grid.update_points(step, seed);
            let sigma = densities(&self.field, &self.params, &pts, DENSITY_CHUNK);
            self.grid.apply(step, &cells, &sigma);
        }
    }

    fn batch_rays(&self) -> Option<usize> {
        let n = self.config.samples_per_step as f64 / self.samples_per_ray.max(1.0);
        Some((n as usize).clamp(64, 1 << 16))
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        vec![
            (OCCUPANCY.to_string(), self.grid.density.clone()),
            (SAMPLES_PER_RAY.to_string(), vec![self.samples_per_ray as f32]),
        ]
    }

    fn restore_state(&mut self, state: StateSource<'_>, step: u64) -> Result<(), ModelError> {
        let density = state(OCCUPANCY).ok_or_else(|| ModelError::MissingState(OCCUPANCY.into()))?;
        let spr = state(SAMPLES_PER_RAY).ok_or_else(|| ModelError::MissingState(SAMPLES_PER_RAY.into()))?;
        self.set_state(density, spr.first().copied().unwrap_or(0.0) as f64, step)
    }

    /// Zero where the occupancy grid calls the space empty: the renderer
    /// never samples there, so neither does a surface taken from it.
    fn density(&self, world: &[[f32; 3]]) -> Option<Vec<f32>> {
        let pos: Vec<f32> = world.iter().flat_map(|p| self.scene.point_to_model(*p)).collect();
        let sigma = densities(&self.field, &self.params, &pos, DENSITY_CHUNK);
        let per_world = self.scene.scale;
        let drawn = |p: &[f32]| self.grid.occupied(Vec3::new(p[0], p[1], p[2]));
        Some(sigma.iter().zip(pos.chunks(3)).map(|(&s, p)| if drawn(p) { s * per_world } else { 0.0 }).collect())
    }

    fn render_rays(
        &self,
        rays: &[Ray],
        background: [f32; 3],
        _options: &RenderOptions,
        out: &mut [RayOutput],
    ) -> BatchStats {
        let settings = RoundSettings {
            round: RENDER_ROUND,
            min_transmittance: self.config.min_transmittance,
            max_dropped_weight: self.config.max_dropped_weight,
        };
        with_scratch(|(c, m, _)| {
            let mut stats = BatchStats::default();
            for (chunk, outc) in rays.chunks(RENDER_CHUNK_RAYS).zip(out.chunks_mut(RENDER_CHUNK_RAYS)) {
                let mut sampler = self.marcher().rounds(chunk);
                let s = render_in_rounds(&self.field, &self.params, &mut sampler, settings, background, c, m, outc);
                stats.add(&s);
            }
            stats
        })
    }
}

/// Names of the saved state.
const OCCUPANCY: &str = "occupancy.density";
const SAMPLES_PER_RAY: &str = "samples_per_ray";

impl InstantModel {
    /// Renders model-space `rays` the slow, obvious way, as a reference for
    /// the marcher: every lattice point of each clipped ray (no occupancy
    /// grid, no early termination, every colour). Also says, per ray, what
    /// the occupancy grid would have skipped: the lattice points in cells it
    /// marks empty, how many of them hold a density at or above its cutoff,
    /// and the sum of their opacities, which bounds how much skipping them
    /// changes the pixel.
    pub fn reference_rays(&self, rays: &[Ray], background: [f32; 3]) -> Vec<ReferenceRay> {
        rays.par_iter().map(|ray| self.reference_ray(ray, background)).collect()
    }

    fn reference_ray(&self, ray: &Ray, background: [f32; 3]) -> ReferenceRay {
        let mut m = Samples::default();
        if let Some((t0, t1)) = self.scene.clip(ray) {
            let mut t = t0 + 0.5 * self.dt;
            while t < t1 && m.len() < self.config.max_samples {
                m.push(ray, t, self.dt);
                t += self.dt;
            }
        }
        let n = m.len();
        let mut r = ReferenceRay::default();
        if n == 0 {
            r.out.rgb = background;
            return r;
        }
        let mut c = Ctx::default();
        self.field.density(&self.params, Points { pos: &m.pos, dirs: &m.dirs, image: &[] }, &mut c);
        self.field.color(&self.params, &m.dirs, &mut c);
        let sigma = self.field.sigma(&c);
        // The marcher's own test of a point, so the two cannot round
        // differently at a cell's face.
        let gr = self.grid.grid_ray(ray);
        for (&t, &s) in m.t.iter().zip(sigma) {
            if !matches!(self.grid.probe(&gr, t), Probe::Occupied { .. }) {
                r.skipped += 1;
                r.skipped_above_cutoff += (s >= self.grid.cutoff) as usize;
                r.skipped_opacity += 1.0 - (-optical_depth(s, self.dt)).exp();
            }
        }
        let mut w = vec![0.0; n];
        let s = RaySamples::new(sigma, self.field.rgb(&c), &m.t, &m.delta).expect("one ray's samples");
        let opts = CompositeOptions { background, ..Default::default() };
        let comp = composite(s, &opts, &mut w).expect("one weight per sample");
        r.out = RayOutput { rgb: comp.rgb, depth: comp.depth, opacity: comp.opacity, median: comp.median };
        r
    }
}

/// One ray of [`InstantModel::reference_rays`].
#[derive(Clone, Debug, Default)]
pub struct ReferenceRay {
    /// The ray rendered from every lattice point.
    pub out: RayOutput,
    /// Lattice points in cells the occupancy grid marks empty...
    pub skipped: usize,
    /// ... of which these hold a density at or above the grid's cutoff...
    pub skipped_above_cutoff: usize,
    /// ... and the sum of their opacities.
    pub skipped_opacity: f32,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `Model::density` is what the renderer integrates, in world units:
    /// a ray's opacity from every lattice point of the field equals the one
    /// summed from the densities at those points' world positions.
    #[test]
    fn density_at_world_points_is_what_a_ray_integrates() {
        use crate::engine::dataset::synthetic::BallScene;
        let scene = BallScene { size: 8, views: 2, ..Default::default() }.dataset().scene();
        let model = InstantModel::new(InstantConfig::default(), scene.clone(), 3);
        let aabb = scene.aabb();
        let centre = (aabb.min + aabb.max) * 0.5;
        let dir = Vec3::new(1.0, 0.3, -0.2).normalized().unwrap();
        let ray = Ray { origin: centre - dir * 0.6 * (aabb.max - aabb.min).norm(), dir };
        let want = model.reference_rays(&[ray], [0.0; 3])[0].out.opacity;
        let (t0, t1) = scene.clip(&ray).unwrap();
        let mut world = Vec::new();
        let mut t = t0 + 0.5 * model.dt;
        while t < t1 && world.len() < model.config.max_samples {
            world.push(scene.point_to_world((ray.origin + ray.dir * t).to_array()));
            t += model.dt;
        }
        let depth: f32 = model.density(&world).unwrap().iter().map(|s| s * model.dt / scene.scale).sum();
        let got = 1.0 - (-depth).exp();
        assert!(want > 0.05, "a ray through the box meets some density: {want}");
        assert!((got - want).abs() < 1e-4 * want.max(1e-3) + 1e-5, "{got} against {want}");
    }

    /// The preset leaves dilation to the scene: none behind transparent
    /// training pixels, dilated otherwise; explicit settings and configs
    /// written before the setting existed are kept (those are dilated).
    #[test]
    fn occupancy_dilation_follows_the_scene_unless_set() {
        use crate::engine::dataset::synthetic::BallScene;
        let mut ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        let transparent = ds.scene();
        assert!(transparent.transparent);
        for f in &mut ds.frames {
            f.image.rgba.chunks_exact_mut(4).for_each(|p| p[3] = 255);
        }
        let opaque = ds.scene();
        assert!(!opaque.transparent);
        let built = |c: InstantConfig, s: &Scene| InstantModel::new(c, s.clone(), 0).config.occupancy.dilate;
        assert_eq!(InstantConfig::default().occupancy.dilate, None);
        assert_eq!(built(InstantConfig::default(), &transparent), Some(false));
        assert_eq!(built(InstantConfig::default(), &opaque), Some(true));
        let mut set = InstantConfig::default();
        set.occupancy.dilate = Some(true);
        assert_eq!(built(set.clone(), &transparent), Some(true));
        set.occupancy.dilate = Some(false);
        assert_eq!(built(set, &opaque), Some(false));
        // A stored config without the field (older checkpoints) is dilated.
        let mut json = serde_json::to_value(InstantConfig::default()).unwrap();
        json["occupancy"].as_object_mut().unwrap().remove("dilate");
        let old: InstantConfig = serde_json::from_value(json).unwrap();
        assert_eq!(built(old, &transparent), Some(true));
        // And the choice changes the bits: dilated grids mark more cells.
        let grid = |d: bool| {
            let mut c = InstantConfig::default();
            c.occupancy.resolution = 16;
            c.occupancy.dilate = Some(d);
            let mut m = InstantModel::new(c, transparent.clone(), 0);
            let n = m.grid.density.len();
            let density: Vec<f32> = (0..n).map(|i| if i == n / 2 + 8 * 16 + 8 { 1e3 } else { 0.0 }).collect();
            m.set_state(density, 16.0, 1000).unwrap();
            m.grid.occupancy()
        };
        assert!(grid(true) > 20.0 * grid(false) && grid(false) > 0.0, "{} {}", grid(true), grid(false));
    }
}
