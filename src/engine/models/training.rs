//! What a training run of a model is asked for besides the model itself:
//! when to stop ([`Budget`]) and the trainer's settings ([`TrainConfig`]).
//! Each kind's defaults come from `config::ModelConfig::train_config`; the
//! trainer (`train::trainer`) reads them and checkpoints keep them.

use crate::engine::models::auto::ModelChoice;

/// When to stop.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Budget {
    pub steps: Option<u64>,
    pub seconds: Option<f64>,
}

impl Budget {
    /// Fraction of the budget used, for the learning-rate schedule.
    pub fn progress(&self, step: u64, elapsed: f64) -> f64 {
        let a = self.steps.map_or(0.0, |s| step as f64 / s.max(1) as f64);
        let b = self.seconds.map_or(0.0, |s| elapsed / s.max(1e-9));
        a.max(b).min(1.0)
    }
    pub fn done(&self, step: u64, elapsed: f64) -> bool {
        self.steps.is_some_and(|s| step >= s) || self.seconds.is_some_and(|s| elapsed >= s)
    }
}

/// Training settings that are not the model's.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainConfig {
    pub seed: u64,
    /// Rays per step (1024).
    pub batch_rays: usize,
    pub budget: Budget,
    /// Composite RGBA training images on a random colour per ray, so the
    /// model learns transparency instead of the background colour.
    #[serde(default)]
    pub random_background: bool,
    /// Why the model is the one it is, when `auto` chose it (kept in the
    /// checkpoint's `meta.train`; absent in checkpoints from before).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_choice: Option<ModelChoice>,
    /// Find transient occluders from the training residuals and stop
    /// training on them (`engine::transient`); a model that does not
    /// measure its rays' errors finds none. Off unless asked for (and then
    /// not written: a run without it saves what it saved before).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub drop_transients: bool,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            batch_rays: 1024,
            budget: Budget { steps: Some(1000), seconds: None },
            random_background: false,
            model_choice: None,
            drop_transients: false,
        }
    }
}
