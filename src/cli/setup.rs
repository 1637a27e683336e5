//! How the commands that train (`train`, `bench`) build a fresh model, its
//! optimiser and the training settings, so they train the same way.

use crate::engine::adam::{Adam, AdamConfig};
use crate::engine::instant::{InstantConfig, InstantModel};
use crate::engine::model::Model;
use crate::engine::nerf::{NerfConfig, NerfModel};
use crate::engine::scene::Scene;
use crate::engine::trainer::{Budget, TrainConfig};

/// Rays per optimisation step for `nerf` (`instant` picks its own).
pub const DEFAULT_BATCH_RAYS: usize = 1024;

/// The model kinds `--model` accepts.
pub const MODEL_KINDS: [&str; 2] = ["instant", "nerf"];

/// A freshly initialised model of `kind`. `skip: false` samples the whole
/// clipped ray, without the occupancy grid (nerf only).
pub fn new_model(kind: &str, scene: Scene, seed: u64, skip: bool) -> anyhow::Result<Box<dyn Model>> {
    match kind {
        "nerf" => {
            let mut cfg = NerfConfig::default();
            if !skip {
                cfg.occupancy = None;
            }
            Ok(Box::new(NerfModel::new(cfg, scene, seed)))
        }
        "instant" => {
            anyhow::ensure!(skip, "--no-skip applies to the nerf model only");
            Ok(Box::new(InstantModel::new(InstantConfig::default(), scene, seed)))
        }
        other => anyhow::bail!("unknown model '{other}' (available: {})", MODEL_KINDS.join(", ")),
    }
}

/// Adam's settings for `kind`; `lr` replaces the initial learning rate and
/// scales the final one with it.
pub fn adam_config(kind: &str, lr: Option<f32>) -> anyhow::Result<AdamConfig> {
    let mut cfg = if kind == "instant" {
        AdamConfig { lr: 1e-2, lr_end: 1e-3, beta1: 0.9, beta2: 0.99, eps: 1e-15 }
    } else {
        AdamConfig::default()
    };
    if let Some(lr) = lr {
        anyhow::ensure!(lr.is_finite() && lr > 0.0, "--lr must be positive");
        cfg.lr_end = lr * cfg.lr_end / cfg.lr;
        cfg.lr = lr;
    }
    Ok(cfg)
}

/// A fresh model of `kind` and its optimiser.
pub fn new_model_and_adam(
    kind: &str,
    scene: Scene,
    seed: u64,
    skip: bool,
    lr: Option<f32>,
) -> anyhow::Result<(Box<dyn Model>, Adam)> {
    let model = new_model(kind, scene, seed, skip)?;
    let adam = Adam::new(adam_config(kind, lr)?, model.params().len());
    Ok((model, adam))
}

/// Training settings for `kind`.
pub fn train_config(kind: &str, seed: u64, batch_rays: usize, budget: Budget) -> TrainConfig {
    // The fast model learns transparency from random backgrounds (Instant-NGP);
    // the classic model trains on white as in the paper.
    let random_background = kind == "instant";
    TrainConfig { seed, batch_rays, budget, random_background }
}
