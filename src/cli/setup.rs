//! How the commands that train (`train`, `bench`) build a fresh model, its
//! optimiser and the training settings: through the engine's
//! [`ModelConfig`], as the service's jobs do.

use crate::engine::adam::Adam;
use crate::engine::model::Model;
use crate::engine::model_config::ModelConfig;
use crate::engine::scene::Scene;

pub use crate::engine::model_config::DEFAULT_BATCH_RAYS;

/// The model kinds `--model` accepts.
pub const MODEL_KINDS: [&str; 2] = ["instant", "nerf"];

/// The configuration of `kind`. `skip: false` samples the whole clipped ray,
/// without the occupancy grid (nerf only).
pub fn model_config(kind: &str, skip: bool) -> anyhow::Result<ModelConfig> {
    anyhow::ensure!(MODEL_KINDS.contains(&kind), "unknown model '{kind}' (available: {})", MODEL_KINDS.join(", "));
    let mut cfg = ModelConfig::preset(kind).expect("every model kind is a preset");
    match &mut cfg {
        ModelConfig::Nerf(c) if !skip => c.occupancy = None,
        ModelConfig::Instant(_) => anyhow::ensure!(skip, "--no-skip applies to the nerf model only"),
        ModelConfig::Nerf(_) => {}
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
) -> anyhow::Result<(ModelConfig, Box<dyn Model>, Adam)> {
    let cfg = model_config(kind, skip)?;
    let (model, adam) = cfg.build_with_adam(scene, seed, lr).map_err(|e| anyhow::anyhow!("--lr: {e}"))?;
    Ok((cfg, model, adam))
}
