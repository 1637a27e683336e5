//! The training loop: random rays from all training images, the model's
//! loss and gradients computed in parallel parts, Adam with an exponential
//! learning-rate schedule, progress through a callback and a cancel flag.
//!
//! Deterministic for a given seed and thread count: the rays of step `s`
//! depend only on `(seed, s)`, each part of a batch accumulates into its own
//! gradient buffer, and the parts are summed in order.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::adam::Adam;
use super::dataset::Dataset;
use super::model::{BatchStats, Model, StepCtx, TrainRay};
use super::rng::Rng;

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
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self { seed: 0, batch_rays: 1024, budget: Budget { steps: Some(1000), seconds: None } }
    }
}

/// Where training is, reported after every step.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Progress {
    pub step: u64,
    /// Loss of the last step (sum over passes of the mean squared error).
    pub loss: f64,
    /// PSNR of the last step's final pass on its training rays, smoothed.
    pub train_psnr: f64,
    /// Seconds of training so far (across resumes).
    pub elapsed: f64,
    /// Seconds left by the budget, when it can be estimated.
    pub eta: Option<f64>,
    pub lr: f32,
    pub rays: u64,
    pub samples: u64,
    pub skipped: u64,
    /// Steps skipped because the loss or a gradient was not finite.
    pub diverged_steps: u64,
}

/// The trainer's state, saved in checkpoints so a run resumes exactly.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainState {
    pub step: u64,
    pub elapsed: f64,
    pub rays: u64,
    pub samples: u64,
    pub skipped: u64,
    pub diverged_steps: u64,
    pub smoothed_mse: f64,
}

/// Why a run stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    Budget,
    Cancelled,
    /// The callback asked to stop.
    Callback,
}

/// Trains a model on a dataset's training split.
pub struct Trainer<'a> {
    pub model: Box<dyn Model>,
    pub adam: Adam,
    pub config: TrainConfig,
    pub state: TrainState,
    dataset: &'a Dataset,
    /// Cumulative pixel counts of the training frames.
    cumulative: Vec<u64>,
    part_grads: Vec<Vec<f32>>,
}

impl<'a> Trainer<'a> {
    pub fn new(
        model: Box<dyn Model>,
        adam: Adam,
        config: TrainConfig,
        state: TrainState,
        dataset: &'a Dataset,
    ) -> Self {
        let mut total = 0u64;
        let cumulative = dataset
            .train
            .iter()
            .map(|&i| {
                let c = &dataset.frames[i].camera;
                total += c.width as u64 * c.height as u64;
                total
            })
            .collect();
        Self { model, adam, config, state, dataset, cumulative, part_grads: Vec::new() }
    }

    /// The training rays of a step: uniform over all training pixels.
    pub fn batch(&self, step: u64) -> Vec<TrainRay> {
        let total = *self.cumulative.last().unwrap_or(&0);
        if total == 0 {
            return Vec::new();
        }
        let mut rng = Rng::stream(self.config.seed, step, u64::MAX);
        let scene = self.model.scene();
        let bg = self.dataset.background;
        (0..self.config.batch_rays as u64)
            .map(|index| {
                let p = rng.below(total);
                let k = self.cumulative.partition_point(|&c| c <= p);
                let frame = &self.dataset.frames[self.dataset.train[k]];
                let local = p - if k == 0 { 0 } else { self.cumulative[k - 1] };
                let w = frame.camera.width as u64;
                let (i, j) = ((local % w) as u32, (local / w) as u32);
                TrainRay {
                    ray: scene.to_model(&frame.camera.pixel_ray(i, j)),
                    target: frame.image.rgb_on(i, j, bg),
                    background: bg,
                    index,
                }
            })
            .collect()
    }

    /// One optimisation step. Returns the batch statistics, or `None` when
    /// the step was skipped because the loss or gradient was not finite.
    pub fn step(&mut self) -> Option<BatchStats> {
        let step = self.state.step;
        let rays = self.batch(step);
        let parts = rayon::current_num_threads().max(1);
        let nparams = self.model.params().len();
        self.part_grads.resize_with(parts, Vec::new);
        let per = rays.len().div_ceil(parts).max(1);
        let ctx = StepCtx { seed: self.config.seed, step, batch_rays: rays.len() };
        let model = &*self.model;
        let stats: Vec<BatchStats> = self
            .part_grads
            .par_iter_mut()
            .enumerate()
            .map(|(p, g)| {
                g.clear();
                g.resize(nparams, 0.0);
                let lo = (p * per).min(rays.len());
                let hi = ((p + 1) * per).min(rays.len());
                model.train_rays(&rays[lo..hi], &ctx, g)
            })
            .collect();
        let mut total = BatchStats::default();
        for s in &stats {
            total.add(s);
        }
        let (first, rest) = self.part_grads.split_at_mut(1);
        let grads = &mut first[0];
        for g in rest.iter() {
            grads.par_iter_mut().zip(g.par_iter()).for_each(|(a, b)| *a += b);
        }
        self.state.step += 1;
        self.state.rays += total.rays;
        self.state.samples += total.samples;
        self.state.skipped += total.skipped;
        let finite = total.loss.is_finite() && grads.par_iter().all(|g| g.is_finite());
        if !finite {
            self.state.diverged_steps += 1;
            return None;
        }
        let lr = self.adam.config.lr_at(self.config.budget.progress(step, self.state.elapsed));
        self.adam.step(self.model.params_mut(), grads, lr);
        self.model.after_step(self.state.step, self.config.seed);
        let mse = total.sq_err / total.rays.max(1) as f64;
        self.state.smoothed_mse =
            if self.state.smoothed_mse == 0.0 { mse } else { 0.9 * self.state.smoothed_mse + 0.1 * mse };
        Some(total)
    }

    pub fn progress(&self, loss: f64) -> Progress {
        let s = &self.state;
        let b = &self.config.budget;
        let rate = if s.elapsed > 0.0 { s.step as f64 / s.elapsed } else { 0.0 };
        let by_steps = b.steps.filter(|_| rate > 0.0).map(|n| n.saturating_sub(s.step) as f64 / rate);
        let by_time = b.seconds.map(|t| (t - s.elapsed).max(0.0));
        let eta = match (by_steps, by_time) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        Progress {
            step: s.step,
            loss,
            train_psnr: if s.smoothed_mse > 0.0 { -10.0 * s.smoothed_mse.log10() } else { 0.0 },
            elapsed: s.elapsed,
            eta,
            lr: self.adam.config.lr_at(b.progress(s.step, s.elapsed)),
            rays: s.rays,
            samples: s.samples,
            skipped: s.skipped,
            diverged_steps: s.diverged_steps,
        }
    }

    /// Trains until the budget is spent, `cancel` is set, or `on_step`
    /// returns false. `on_step` runs after every step; its time does not
    /// count as training time.
    pub fn run(&mut self, cancel: &AtomicBool, mut on_step: impl FnMut(&mut Self, &Progress) -> bool) -> StopReason {
        loop {
            if self.config.budget.done(self.state.step, self.state.elapsed) {
                return StopReason::Budget;
            }
            if cancel.load(Ordering::Relaxed) {
                return StopReason::Cancelled;
            }
            let t0 = Instant::now();
            let stats = self.step();
            self.state.elapsed += t0.elapsed().as_secs_f64();
            let loss = stats.map_or(f64::NAN, |s| s.loss / s.rays.max(1) as f64);
            let p = self.progress(loss);
            if !on_step(self, &p) {
                return StopReason::Callback;
            }
        }
    }
}
