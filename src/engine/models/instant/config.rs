//! The fast model's configuration and what it provides the registry
//! (`models::spec::ModelSpec`): checks, building, sizes.

use super::{InstantModel, KIND, layout};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::spec::{self, Checks, Footprint, ModelSpec};
use crate::engine::models::{Model, ModelError};
use crate::engine::nn::adam::AdamConfig;
use crate::engine::nn::hashgrid::HashGrid;
use crate::engine::nn::hashgrid::HashGridConfig;
use crate::engine::nn::linear::ParamLayout;
use crate::engine::sampling::occupancy::OccupancyConfig;

/// The fast model's configuration. `Default` is what `radiance train` uses.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InstantConfig {
    pub grid: HashGridConfig,
    /// Hidden width of both MLPs (64).
    pub hidden: usize,
    /// Outputs of the density MLP: log-density and geometry features (16).
    pub geo_features: usize,
    pub occupancy: OccupancyConfig,
    /// Marching steps along the scene box's diagonal (384).
    pub steps_per_diagonal: usize,
    /// Upper bound of samples per ray.
    pub max_samples: usize,
    /// Network samples per training step; the number of rays adapts.
    pub samples_per_step: usize,
    /// Transmittance below which rendering stops (1e-4).
    pub min_transmittance: f32,
    /// Rendering skips the colour of samples whose weights, summed along a
    /// ray, stay below this (1e-3, a quarter of an 8-bit step): a pixel
    /// changes by at most this much.
    #[serde(default = "default_max_dropped_weight")]
    pub max_dropped_weight: f32,
    /// Training rays processed together by one thread (256: enough samples
    /// that each hash-grid level's table is reused from cache while all of
    /// them visit it).
    pub chunk_rays: usize,
}

impl Default for InstantConfig {
    fn default() -> Self {
        Self {
            grid: HashGridConfig::default(),
            hidden: 64,
            geo_features: 16,
            occupancy: OccupancyConfig {
                resolution: 128,
                threshold: 0.0, // set from the step size in `InstantModel::new`
                decay: 0.95,
                update_every: 16,
                sweep: 8,
                warmup_steps: 32,
                full_updates_until: 128,
                empty_sweep: 64,
                // Decided from the scene in `InstantModel::new`.
                dilate: None,
            },
            steps_per_diagonal: 384,
            max_samples: 1024,
            samples_per_step: 1 << 14,
            min_transmittance: 1e-4,
            max_dropped_weight: default_max_dropped_weight(),
            chunk_rays: 256,
        }
    }
}

fn default_max_dropped_weight() -> f32 {
    1e-3
}

impl ModelSpec for InstantConfig {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn check(&self, c: &mut Checks) {
        let i = self;
        let g = &i.grid;
        c.int("grid.levels", g.levels, 1..=32);
        c.int("grid.log2_table", g.log2_table, 8..=24);
        c.int("grid.base_resolution", g.base_resolution, 2..=4096);
        // The finest level is at least as fine as the coarsest; the range names
        // the number, not the other field, so each message names one field.
        c.int("grid.finest_resolution", g.finest_resolution, u64::from(g.base_resolution)..=8192);
        c.int("hidden", i.hidden, 1..=256);
        c.int("geo_features", i.geo_features, 1..=64);
        spec::check_occupancy(&i.occupancy, c);
        c.int("steps_per_diagonal", i.steps_per_diagonal, 16..=8192);
        c.int("max_samples", i.max_samples, 1..=8192);
        c.int("samples_per_step", i.samples_per_step, (1 << 8)..=(1 << 20));
        c.unit_open("min_transmittance", i.min_transmittance);
        c.int("chunk_rays", i.chunk_rays, 1..=4096);
    }

    fn build(&self, scene: Scene, seed: u64) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(InstantModel::new(self.clone(), scene, seed)))
    }

    fn rebuild(&self, scene: Scene, params: Vec<f32>) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(InstantModel::from_parts(self.clone(), scene, params)?))
    }

    /// Instant-NGP's: 1e-2 with beta2 0.99 and a tiny epsilon for the hash grid.
    fn adam(&self) -> AdamConfig {
        AdamConfig { lr: 1e-2, lr_end: 1e-3, beta1: 0.9, beta2: 0.99, eps: 1e-15 }
    }

    /// The fast model learns transparency from random backgrounds (Instant-NGP).
    fn random_background(&self) -> bool {
        true
    }

    fn footprint(&self, threads: u64) -> Footprint {
        let mut ps = ParamLayout::default();
        layout(&mut ps, self);
        // Rays per step start at `samples_per_step / 64` (the first guess of
        // samples per ray) and shrink once the real figure is known, so the
        // largest chunk is the first: `min(chunk_rays, rays per thread)` rays
        // of up to one sample per marching step (the grid is not warm yet).
        let first_rays = (self.samples_per_step as u64).div_ceil(64).div_ceil(threads.max(1));
        let rays = (self.chunk_rays as u64).min(first_rays).max(1);
        let per_ray = (self.max_samples as u64).min(self.steps_per_diagonal as u64 + 1);
        let grid = HashGrid::new(&mut ParamLayout::default(), self.grid.clone()).width() as u64;
        let (h, g) = (self.hidden as u64, self.geo_features as u64);
        // Forward: unit position, encoding, density hidden, geometry
        // features, density, SH direction code (16), two colour hiddens,
        // colour; backward: two hidden-sized gradients, the features' and the
        // encoding's; the samples' distance, step, position and direction (8);
        // the pass's weight, gradients and image index (6).
        let per_sample = (3 + grid + h + g + 1 + 16 + 2 * h + 3) + (2 * h + g + grid) + 8 + 6;
        Footprint {
            params: ps.len as u64,
            occupancy_cells: (self.occupancy.resolution as u64).pow(3),
            activations: rays * per_ray * per_sample,
        }
    }
}

/// This kind's presets, the default first.
pub const PRESETS: &[&str] = &["instant", "instant-tiny"];

/// A named configuration:
/// - `instant`: the fast model (the default of all kinds);
/// - `instant-tiny`: a small hash grid and narrow MLPs, for previews and tests.
pub fn preset(name: &str) -> Option<InstantConfig> {
    match name {
        "instant" => Some(InstantConfig::default()),
        "instant-tiny" => {
            let mut c = InstantConfig {
                grid: HashGridConfig { levels: 8, log2_table: 12, base_resolution: 8, finest_resolution: 128 },
                hidden: 32,
                geo_features: 8,
                steps_per_diagonal: 128,
                samples_per_step: 1 << 12,
                ..InstantConfig::default()
            };
            c.occupancy.resolution = 32;
            Some(c)
        }
        _ => None,
    }
}
