//! The classic model's configuration and what it provides the registry
//! (`models::spec::ModelSpec`): checks, building, sizes.

use super::{KIND, NerfModel, layout};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::spec::{self, Checks, FieldValue, Footprint, ModelSpec};
use crate::engine::models::{Model, ModelError};
use crate::engine::nn::adam::AdamConfig;
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::nerf_net::NetConfig;
use crate::engine::sampling::occupancy::OccupancyConfig;

/// The classic model's configuration. `Default` is the paper's.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NerfConfig {
    pub net: NetConfig,
    /// Stratified samples per ray for the coarse network (64).
    pub coarse_samples: usize,
    /// Extra samples per ray from the coarse weights (128); the fine network
    /// sees these and the coarse ones.
    pub fine_samples: usize,
    /// Rays processed together through the networks by one thread.
    pub chunk_rays: usize,
    /// Transmittance below which rendering stops marching a ray (1e-4).
    pub min_transmittance: f32,
    /// Skip empty space with an occupancy grid (`None`: sample the whole
    /// clipped ray, as the paper does).
    pub occupancy: Option<OccupancyConfig>,
}

impl Default for NerfConfig {
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            coarse_samples: 64,
            fine_samples: 128,
            chunk_rays: 8,
            min_transmittance: 1e-4,
            occupancy: Some(OccupancyConfig::default()),
        }
    }
}

impl ModelSpec for NerfConfig {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn check(&self, c: &mut Checks) {
        let n = self;
        let net = &n.net;
        c.int("net.width", net.width, 1..=1024);
        c.int("net.depth", net.depth, 1..=32);
        if net.skip >= net.depth {
            // The skip connection feeds a later layer: it must exist.
            c.fail("net.skip", FieldValue::Int(net.skip as u64), format!("0..{}", net.depth));
        }
        c.int("net.pos_freqs", net.pos_freqs, 0..=24);
        c.int("net.dir_freqs", net.dir_freqs, 0..=24);
        c.int("net.dir_width", net.dir_width, 1..=1024);
        c.int("coarse_samples", n.coarse_samples, 1..=1024);
        c.int("fine_samples", n.fine_samples, 0..=1024);
        c.int("chunk_rays", n.chunk_rays, 1..=4096);
        c.unit_open("min_transmittance", n.min_transmittance);
        if let Some(o) = &n.occupancy {
            spec::check_occupancy(o, c);
            if o.dilate == Some(false) {
                // The classic sampler steps half a cell: undilated bits would
                // skip the edges of occupied cells.
                c.fail(
                    "occupancy.dilate",
                    FieldValue::Bool(false),
                    "true or null (the sampler steps half a cell)".into(),
                );
            }
        }
    }

    fn build(&self, scene: Scene, seed: u64) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(NerfModel::new(self.clone(), scene, seed)))
    }

    fn rebuild(&self, scene: Scene, params: Vec<f32>) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(NerfModel::from_parts(self.clone(), scene, params)?))
    }

    /// The paper's 5e-4 -> 5e-5.
    fn adam(&self) -> AdamConfig {
        AdamConfig::default()
    }

    /// The classic model trains on the dataset's background, as in the paper.
    fn random_background(&self) -> bool {
        false
    }

    /// One worker thread's chunk: the coarse field on the coarse samples,
    /// the fine one on all of them, with each trunk layer's output kept for
    /// backward and the same again as gradients.
    fn footprint(&self, _threads: u64) -> Footprint {
        let mut ps = ParamLayout::default();
        layout(&mut ps, self);
        let n = &self.net;
        let (xw, dw) = (3 + 6 * n.pos_freqs as u64, 3 + 6 * n.dir_freqs as u64);
        let per_sample = 2 * (xw + dw + (n.depth as u64 + 1) * n.width as u64 + n.dir_width as u64 + 8);
        let samples = self.chunk_rays as u64 * (2 * self.coarse_samples as u64 + self.fine_samples as u64);
        Footprint {
            params: ps.len as u64,
            occupancy_cells: self.occupancy.as_ref().map_or(0, |o| (o.resolution as u64).pow(3)),
            activations: samples * per_sample,
        }
    }
}

/// This kind's presets, the default first.
pub const PRESETS: &[&str] = &["nerf", "nerf-tiny"];

/// A named configuration:
/// - `nerf`: the paper's model, with occupancy-grid skipping;
/// - `nerf-tiny`: a small network and few samples, for previews and tests.
pub fn preset(name: &str) -> Option<NerfConfig> {
    match name {
        "nerf" => Some(NerfConfig::default()),
        "nerf-tiny" => Some(NerfConfig {
            net: NetConfig { pos_freqs: 4, dir_freqs: 2, width: 32, depth: 4, skip: 2, dir_width: 16 },
            coarse_samples: 16,
            fine_samples: 16,
            ..NerfConfig::default()
        }),
        _ => None,
    }
}
