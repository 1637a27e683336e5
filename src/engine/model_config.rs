//! Which model to train and how: the configuration of either model kind,
//! the named presets, and everything that differs between the kinds when a
//! fresh model is built (its optimiser settings, its training settings).
//! The CLI and the job runner both build models through this, so they train
//! the same way.

use super::adam::{Adam, AdamConfig};
use super::hashgrid::HashGridConfig;
use super::instant::{InstantConfig, InstantModel};
use super::model::Model;
use super::nerf::{NerfConfig, NerfModel};
use super::nerf_net::NetConfig;
use super::scene::Scene;
use super::trainer::{Budget, TrainConfig};

/// A model configuration of either kind, tagged by `kind` in JSON.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ModelConfig {
    /// The fast model: hash grid, tiny MLPs, occupancy-grid marching.
    Instant(InstantConfig),
    /// The classic NeRF of the paper.
    Nerf(NerfConfig),
}

/// The names [`ModelConfig::preset`] knows, the default first.
pub const PRESETS: [&str; 4] = ["instant", "instant-tiny", "nerf", "nerf-tiny"];

/// Rays per optimisation step for `nerf` (the fast model adapts its number of
/// rays to a constant sample budget and ignores this).
pub const DEFAULT_BATCH_RAYS: usize = 1024;

impl ModelConfig {
    /// A named configuration:
    /// - `instant`: the fast model (the default);
    /// - `instant-tiny`: a small hash grid and narrow MLPs, for previews and tests;
    /// - `nerf`: the paper's model, with occupancy-grid skipping;
    /// - `nerf-tiny`: a small network and few samples, for previews and tests.
    pub fn preset(name: &str) -> Option<Self> {
        Some(match name {
            "instant" => ModelConfig::Instant(InstantConfig::default()),
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
                ModelConfig::Instant(c)
            }
            "nerf" => ModelConfig::Nerf(NerfConfig::default()),
            "nerf-tiny" => ModelConfig::Nerf(NerfConfig {
                net: NetConfig { pos_freqs: 4, dir_freqs: 2, width: 32, depth: 4, skip: 2, dir_width: 16 },
                coarse_samples: 16,
                fine_samples: 16,
                ..NerfConfig::default()
            }),
            _ => return None,
        })
    }

    /// The configuration a built model runs with (as its checkpoint stores it).
    pub fn of_model(model: &dyn Model) -> Option<Self> {
        Self::from_kind_json(model.kind(), model.config_json())
    }

    /// A configuration from a model kind and its untagged JSON (as
    /// `Model::config_json` writes it).
    pub fn from_kind_json(kind: &str, json: serde_json::Value) -> Option<Self> {
        match kind {
            "instant" => serde_json::from_value(json).ok().map(ModelConfig::Instant),
            "nerf" => serde_json::from_value(json).ok().map(ModelConfig::Nerf),
            _ => None,
        }
    }

    /// `instant` or `nerf`.
    pub fn kind(&self) -> &'static str {
        match self {
            ModelConfig::Instant(_) => "instant",
            ModelConfig::Nerf(_) => "nerf",
        }
    }

    /// Refuses configurations that would allocate absurdly or not run,
    /// naming the allowed ranges.
    pub fn check(&self) -> Result<(), String> {
        match self {
            ModelConfig::Nerf(c) => {
                let n = &c.net;
                let ok = (1..=1024).contains(&n.width)
                    && (1..=32).contains(&n.depth)
                    && n.skip < n.depth
                    && n.pos_freqs <= 24
                    && n.dir_freqs <= 24
                    && (1..=1024).contains(&n.dir_width)
                    && (1..=1024).contains(&c.coarse_samples)
                    && c.fine_samples <= 1024
                    && (1..=4096).contains(&c.chunk_rays)
                    && c.min_transmittance.is_finite()
                    && (0.0..1.0).contains(&c.min_transmittance)
                    && c.occupancy.as_ref().is_none_or(|o| occupancy_ok(o) && o.dilate != Some(false));
                ok.then_some(()).ok_or_else(|| {
                    "nerf config out of range (net.width, net.dir_width 1..=1024, net.depth 1..=32, \
                     net.skip < net.depth, freqs <= 24, coarse_samples 1..=1024, fine_samples <= 1024, \
                     chunk_rays 1..=4096, min_transmittance in [0, 1), occupancy resolution 1..=256, \
                     sweep >= 1, update_every >= 1, occupancy.dilate not false: the sampler steps half a cell)"
                        .into()
                })
            }
            ModelConfig::Instant(c) => {
                let g = &c.grid;
                let ok = (1..=32).contains(&g.levels)
                    && (8..=24).contains(&g.log2_table)
                    && (2..=4096).contains(&g.base_resolution)
                    && (g.base_resolution..=8192).contains(&g.finest_resolution)
                    && (1..=256).contains(&c.hidden)
                    && (1..=64).contains(&c.geo_features)
                    && occupancy_ok(&c.occupancy)
                    && (16..=8192).contains(&c.steps_per_diagonal)
                    && (1..=8192).contains(&c.max_samples)
                    && ((1 << 8)..=(1 << 20)).contains(&c.samples_per_step)
                    && c.min_transmittance.is_finite()
                    && (0.0..1.0).contains(&c.min_transmittance)
                    && (1..=4096).contains(&c.chunk_rays);
                ok.then_some(()).ok_or_else(|| {
                    "instant config out of range (grid.levels 1..=32, grid.log2_table 8..=24, \
                     grid.base_resolution 2..=4096, grid.finest_resolution base..=8192, hidden 1..=256, \
                     geo_features 1..=64, occupancy resolution 1..=256, sweep >= 1, update_every >= 1, \
                     steps_per_diagonal 16..=8192, max_samples 1..=8192, samples_per_step 256..=1048576, \
                     min_transmittance in [0, 1), chunk_rays 1..=4096)"
                        .into()
                })
            }
        }
    }

    /// A freshly initialised model for `scene`.
    pub fn build(&self, scene: Scene, seed: u64) -> Box<dyn Model> {
        match self {
            ModelConfig::Instant(c) => Box::new(InstantModel::new(c.clone(), scene, seed)),
            ModelConfig::Nerf(c) => Box::new(NerfModel::new(c.clone(), scene, seed)),
        }
    }

    /// Adam's settings: the paper's 5e-4 -> 5e-5 for `nerf`; Instant-NGP's
    /// 1e-2 with beta2 0.99 and a tiny epsilon for the hash grid.
    pub fn adam(&self) -> AdamConfig {
        match self {
            ModelConfig::Instant(_) => AdamConfig { lr: 1e-2, lr_end: 1e-3, beta1: 0.9, beta2: 0.99, eps: 1e-15 },
            ModelConfig::Nerf(_) => AdamConfig::default(),
        }
    }

    /// A fresh model and its optimiser; `lr` replaces the initial learning
    /// rate and scales the final one with it.
    pub fn build_with_adam(&self, scene: Scene, seed: u64, lr: Option<f32>) -> Result<(Box<dyn Model>, Adam), String> {
        let mut cfg = self.adam();
        if let Some(lr) = lr {
            if !(lr.is_finite() && lr > 0.0) {
                return Err(format!("the learning rate must be a positive number, not {lr}"));
            }
            cfg.lr_end = lr * cfg.lr_end / cfg.lr;
            cfg.lr = lr;
        }
        let model = self.build(scene, seed);
        let adam = Adam::new(cfg, model.params().len());
        Ok((model, adam))
    }

    /// Training settings. The fast model learns transparency from random
    /// backgrounds (Instant-NGP); the classic model trains on the dataset's
    /// background as in the paper.
    pub fn train_config(&self, seed: u64, batch_rays: usize, budget: Budget) -> TrainConfig {
        let random_background = matches!(self, ModelConfig::Instant(_));
        TrainConfig { seed, batch_rays, budget, random_background }
    }
}

fn occupancy_ok(o: &super::occupancy::OccupancyConfig) -> bool {
    (1..=256).contains(&o.resolution)
        && o.sweep >= 1
        && o.update_every >= 1
        && o.threshold.is_finite()
        && o.decay.is_finite()
        && (0.0..=1.0).contains(&o.decay)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::synthetic::BallScene;

    #[test]
    fn presets_are_valid_and_build() {
        let ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        for name in PRESETS {
            let c = ModelConfig::preset(name).unwrap();
            c.check().unwrap_or_else(|e| panic!("{name}: {e}"));
            let (m, adam) = c.build_with_adam(Scene::from_dataset(&ds), 1, None).unwrap();
            assert_eq!(m.kind(), c.kind());
            assert_eq!(adam.m.len(), m.params().len());
        }
        assert!(ModelConfig::preset("nope").is_none());
    }

    #[test]
    fn json_is_tagged_by_kind_and_round_trips() {
        let c = ModelConfig::preset("instant-tiny").unwrap();
        let v = serde_json::to_value(&c).unwrap();
        assert_eq!(v["kind"], "instant");
        assert_eq!(v["hidden"], 32);
        assert_eq!(serde_json::from_value::<ModelConfig>(v).unwrap(), c);
    }

    #[test]
    fn out_of_range_configs_are_refused() {
        let ModelConfig::Instant(mut c) = ModelConfig::preset("instant").unwrap() else { unreachable!() };
        c.grid.log2_table = 40;
        assert!(ModelConfig::Instant(c).check().unwrap_err().contains("log2_table"));
        let ModelConfig::Nerf(mut n) = ModelConfig::preset("nerf").unwrap() else { unreachable!() };
        n.net.skip = n.net.depth;
        assert!(ModelConfig::Nerf(n).check().unwrap_err().contains("skip"));
        // The classic sampler steps half a cell: its grid must be dilated.
        let ModelConfig::Nerf(mut n) = ModelConfig::preset("nerf").unwrap() else { unreachable!() };
        let mut o = n.occupancy.clone().expect("the preset skips");
        for (dilate, ok) in [(Some(false), false), (None, true), (Some(true), true)] {
            o.dilate = dilate;
            n.occupancy = Some(o.clone());
            let r = ModelConfig::Nerf(n.clone()).check();
            assert_eq!(r.is_ok(), ok, "{dilate:?}: {r:?}");
            assert!(ok || r.unwrap_err().contains("occupancy.dilate"));
        }
        let ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        let c = ModelConfig::preset("nerf-tiny").unwrap();
        assert!(c.build_with_adam(Scene::from_dataset(&ds), 0, Some(f32::NAN)).is_err());
    }
}
