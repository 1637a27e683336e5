//! The tests' tiny models: small enough to train in seconds on the tiny
//! generated scenes. Tests that build variants of them take the engine's
//! config types from this module too, so a change of engine paths is fixed
//! here. (render_fixture.rs's ignored fixture writer keeps its own configs:
//! it records how the fixtures were made.)
#![allow(unused_imports)] // the re-exports: each test binary uses its own

use radiance::engine::dataset::Dataset;
use radiance::engine::geometry::scene::Scene;
use radiance::engine::models::config::ModelConfig;
pub use radiance::engine::models::instant::{InstantConfig, InstantModel};
pub use radiance::engine::models::nerf::{NerfConfig, NerfModel};
use radiance::engine::models::training::{Budget, TrainConfig};
pub use radiance::engine::nn::hashgrid::HashGridConfig;
pub use radiance::engine::nn::nerf_net::NetConfig;
pub use radiance::engine::sampling::occupancy::OccupancyConfig;
use radiance::engine::train::trainer::{TrainState, Trainer};

/// The smallest classic model that still learns something: for long runs.
pub fn nerf_nano() -> NerfConfig {
    NerfConfig {
        net: NetConfig { pos_freqs: 2, dir_freqs: 1, width: 8, depth: 2, skip: 0, dir_width: 4 },
        coarse_samples: 4,
        fine_samples: 4,
        occupancy: None,
        ..Default::default()
    }
}

/// A very small classic model, with or without an 8³ occupancy grid that
/// starts after 8 steps.
pub fn nerf_micro(occupancy: bool) -> NerfConfig {
    NerfConfig {
        net: NetConfig { pos_freqs: 3, dir_freqs: 1, width: 16, depth: 3, skip: 1, dir_width: 8 },
        coarse_samples: 8,
        fine_samples: 8,
        occupancy: occupancy.then(|| OccupancyConfig {
            resolution: 8,
            update_every: 4,
            sweep: 2,
            warmup_steps: 8,
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// A small classic model that learns the ball scene well in a few hundred
/// steps.
pub fn nerf_small() -> NerfConfig {
    NerfConfig {
        net: NetConfig { pos_freqs: 4, dir_freqs: 2, width: 32, depth: 4, skip: 2, dir_width: 16 },
        coarse_samples: 16,
        fine_samples: 16,
        ..Default::default()
    }
}

/// A small fast model: 8 hash-grid levels up to 64³, a 32³ occupancy grid.
pub fn instant_small() -> InstantConfig {
    let mut config = InstantConfig {
        grid: HashGridConfig { levels: 8, log2_table: 14, base_resolution: 4, finest_resolution: 64 },
        hidden: 32,
        steps_per_diagonal: 256,
        samples_per_step: 1 << 13,
        chunk_rays: 32,
        ..Default::default()
    };
    config.occupancy.resolution = 32;
    config.occupancy.update_every = 8;
    config.occupancy.sweep = 2;
    config
}

/// `steps` steps of `batch_rays` rays, seeded with `seed`.
pub fn train_config(seed: u64, batch_rays: usize, steps: u64) -> TrainConfig {
    TrainConfig { seed, batch_rays, budget: Budget { steps: Some(steps), seconds: None }, ..Default::default() }
}

/// A fresh trainer of `config` on `ds`, seeded `seed`, for `steps` steps of
/// 1024 rays (models that choose their own batch keep theirs).
pub fn trainer<'a>(config: &ModelConfig, ds: &'a Dataset, seed: u64, steps: u64) -> Trainer<'a> {
    let (model, adam) = config.build_with_adam(ds.scene(), seed, None).unwrap();
    let train = config.train_config(seed, 1024, Budget { steps: Some(steps), seconds: None });
    Trainer::new(model, adam, train, TrainState::default(), ds)
}

/// Runs `f` on a pool of `threads` threads (results are deterministic per
/// thread count).
pub fn in_pool<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(f)
}
