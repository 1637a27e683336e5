//! A bake job: a trained model of the service (instant, nerf or capture)
//! becomes a new model of kind `splats` (`engine::bake`), optimised
//! against the training photos of its scene, where its training job read
//! them. Progress: optimisation steps, the Gaussians, the smoothed PSNR of
//! the training photos; then the held-out PSNR, measured as a training
//! job's is.
//!
//! Restart-safety: a bake keeps nothing while it runs (a minute by
//! default), so a job cut short (a shutdown, a killed server) bakes again
//! from the start. What it makes appears whole or not at all: the
//! checkpoint is written atomically, then the model's record, which alone
//! makes the model visible. A crash between the two leaves an orphan
//! checkpoint that the next run overwrites.
//!
//! A training job asks for a bake when it succeeds (`TrainSpec::bake`):
//! [`enqueue_after_training`] enqueues it under the id the training job was
//! given when it was posted, so a training job run twice (a crash after
//! its end) enqueues one bake.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::host::JobHost;
use super::scoring::{evaluate, load_dataset};
use super::{BakeAfter, BakeSpec, Job, JobError, JobSpec, Outcome, SchedError};
use crate::datadir::{ScenePart, now_ms};
use crate::engine::front::{
    BakeError, BakeProgress, BakeSettings, Budget, DataSize, Dataset, Estimate, MaskUse, Model, ModelConfig,
    SplatsConfig, TrainConfig, TrainState, TransientMaps, bake, estimate_bake, load_checkpoint, save_checkpoint,
};
use crate::records::ModelInfo;

/// The preset name a bake's model record gets.
pub const BAKED_MODEL: &str = "splats";

/// Longest accepted bake budget: an hour.
pub const MAX_SECONDS: f64 = 3600.0;

/// The default bake budget (seconds), as the command line's.
pub const DEFAULT_SECONDS: f64 = 60.0;

/// The enqueue-time check of a bake job (under the queue's lock, or in the
/// queue's transaction): its source model exists.
pub(crate) fn check_source(source: &Option<ModelInfo>, spec: &BakeSpec) -> Result<(), SchedError> {
    match source {
        Some(_) => Ok(()),
        None => Err(SchedError::ModelNotFound(spec.source_model_id.clone())),
    }
}

/// The splats settings of a bake job.
pub fn splats_config(spec: &BakeSpec) -> SplatsConfig {
    SplatsConfig { sh_degree: spec.sh_degree, max_gaussians: spec.max_gaussians }
}

/// Peak memory of a bake of `source` on `data` (see `engine::front::estimate_bake`),
/// placing the default number of Gaussians for its frames (every split's:
/// at least its training photos).
pub fn memory_estimate(source: &ModelConfig, spec: &BakeSpec, data: DataSize) -> Estimate {
    let splats = ModelConfig::Splats(splats_config(spec));
    let initial = BakeSettings::default().initial_for(data.frames);
    estimate_bake(source, &splats, initial, data, rayon::current_num_threads())
}

/// The bake a finished training job asked for: `spec` as the API checked
/// it when the training job was posted, of the model `model_id` just
/// trained on `scene_id`.
pub(crate) fn spec_after_training(after: &BakeAfter, model_id: &str, scene_id: &str, seed: u64) -> BakeSpec {
    let defaults = SplatsConfig::default();
    BakeSpec {
        source_model_id: model_id.to_string(),
        scene_id: scene_id.to_string(),
        seconds: after.seconds.or(if after.steps.is_none() { Some(DEFAULT_SECONDS) } else { None }),
        steps: after.steps,
        sh_degree: defaults.sh_degree,
        max_gaussians: defaults.max_gaussians,
        seed,
    }
}

/// Enqueues the bake that training job `job` asked for, of its model
/// (trained on `ds`). An error is the training job's: it says the bake
/// could not be queued.
pub(crate) fn enqueue_after_training(
    host: &dyn JobHost,
    job: &Job,
    after: &BakeAfter,
    scene_id: &str,
    config: &ModelConfig,
    data: DataSize,
    seed: u64,
) -> Result<(), JobError> {
    let spec = spec_after_training(after, &job.reserved_model_id(), scene_id, seed);
    let memory = memory_estimate(config, &spec, data).memory_bytes;
    host.enqueue(after.job_id.clone(), JobSpec::Bake(spec), memory).map_err(JobError::BakeNotQueued)?;
    tracing::info!(job = %job.id, bake = %after.job_id, "bake queued after training");
    Ok(())
}

/// The body of a bake job (see [`super::run_body`]).
pub(crate) fn run(host: &dyn JobHost, job: &Job, spec: &BakeSpec, cancel: &AtomicBool) -> Result<Outcome, JobError> {
    let started = Instant::now();
    let stage = |s: &str| host.set_progress(&job.id, &mut |j| j.progress.stage = Some(s.to_string()));
    stage("loading the model and its photos");
    let (source, model, dropped, ds) = load_source(host, spec)?;
    let settings = BakeSettings {
        budget: Budget { seconds: spec.seconds, steps: spec.steps },
        seed: spec.seed,
        splats: splats_config(spec),
        ..Default::default()
    };
    stage("placing Gaussians");
    let mut last = Instant::now();
    let baked = bake(&*model, &ds, &settings, dropped.as_ref(), cancel, |p| {
        if last.elapsed().as_secs_f64() >= 0.1 {
            last = Instant::now();
            report(host, job, spec, p);
        }
    });
    let (splats, adam, steps) = match baked {
        Ok(b) => b,
        Err(BakeError::Cancelled) => return Ok(Outcome::Stopped),
        Err(e) => return Err(e.into()),
    };
    stage("measuring on held-out views");
    let metric = evaluate(&splats, &ds, host.config().eval_views, cancel);
    if cancel.load(Ordering::SeqCst) {
        return Ok(Outcome::Stopped);
    }
    let elapsed = started.elapsed().as_secs_f64();
    let model_id = job.reserved_model_id();
    let out = host.job_checkpoint(job, &model_id)?;
    let train = TrainConfig {
        seed: spec.seed,
        budget: Budget { steps: spec.steps, seconds: spec.seconds },
        ..Default::default()
    };
    let state = TrainState { step: steps, elapsed, ..Default::default() };
    save_checkpoint(&out, &splats, &adam, &train, &state, None).map_err(JobError::SaveSplats)?;
    let gaussians = splats.layout().n as u64;
    let baked = Baked { model: &splats, gaussians, steps, elapsed, metric };
    host.publish_model(job, &baked.record(job, &source, &out), &out)?;
    host.set_progress(&job.id, &mut |j| {
        j.model_id = Some(model_id.clone());
        let g = &mut j.progress;
        (g.stage, g.step, g.elapsed, g.eta, g.gaussians) = (None, steps, elapsed, Some(0.0), Some(gaussians));
        if let Some(m) = metric {
            (g.test_psnr, g.test_psnr_step) = (Some(m.0), Some(steps));
        }
    });
    tracing::info!(job = %job.id, model = %model_id, gaussians, steps, "baked");
    Ok(Outcome::Succeeded)
}

/// The bake's source: its model record, the model (from its checkpoint)
/// and the training photos of its scene.
/// The source model's record, the model, the transient maps it was trained
/// with (if any) and its scene's photos.
type Source = (ModelInfo, Box<dyn Model>, Option<TransientMaps>, Dataset);

fn load_source(host: &dyn JobHost, spec: &BakeSpec) -> Result<Source, JobError> {
    let id = &spec.source_model_id;
    let source = host.model(id)?.ok_or_else(|| JobError::ModelGone(id.clone()))?;
    let scene = host.scene(&source.scene_id)?.ok_or_else(|| JobError::SceneGone(source.scene_id.clone()))?;
    let dir = host.scene_dir(&scene, ScenePart::Data)?;
    let ds = load_dataset(&dir.path, &scene, MaskUse::Auto)?;
    let ckpt = host.model_checkpoint(&source).map_err(JobError::ModelFile)?;
    let restored = load_checkpoint(&ckpt.path)?;
    Ok((source, restored.model, restored.transients, ds))
}

/// The job's progress while optimising.
fn report(host: &dyn JobHost, job: &Job, spec: &BakeSpec, p: &BakeProgress) {
    host.set_progress(&job.id, &mut |j| {
        let g = &mut j.progress;
        g.stage = Some("optimising".into());
        g.step = p.step;
        g.total_steps = spec.steps;
        g.train_psnr = p.psnr;
        g.elapsed = p.elapsed;
        g.eta = (p.progress > 0.0).then(|| p.elapsed * (1.0 - p.progress) / p.progress);
        g.gaussians = Some(p.gaussians as u64);
    });
}

/// What a bake made, for its model's record.
struct Baked<'a> {
    model: &'a dyn Model,
    gaussians: u64,
    steps: u64,
    elapsed: f64,
    /// The held-out PSNR and the views it was measured on.
    metric: Option<(f64, usize)>,
}

impl Baked<'_> {
    /// The record of the baked model (checkpoint `out`) of `source`.
    fn record(&self, job: &Job, source: &ModelInfo, out: &Path) -> ModelInfo {
        let now = now_ms();
        ModelInfo {
            id: job.reserved_model_id(),
            scene_id: source.scene_id.clone(),
            job_id: job.id.clone(),
            model: BAKED_MODEL.into(),
            model_reason: Some(format!("baked from model '{}' ({})", source.id, source.model)),
            config: self.model.config_json(),
            steps: self.steps,
            training_seconds: self.elapsed,
            test_psnr: self.metric.map(|m| m.0),
            test_views: self.metric.map_or(0, |m| m.1),
            size_bytes: std::fs::metadata(out).map_or(0, |m| m.len()),
            created_at: now,
            updated_at: now,
            complete: true,
            training_state: true,
            view: source.view.clone(),
            poses: None,
            gaussians: Some(self.gaussians),
            transients: None,
            // A crop set on the field carries over to its splats.
            crop: source.crop,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bake_after_training_takes_the_budget_asked_for_or_a_minute() {
        let after = BakeAfter { job_id: "job_b".into(), seconds: None, steps: None };
        let s = spec_after_training(&after, "mdl_a", "scn_a", 3);
        assert_eq!((s.seconds, s.steps, s.source_model_id.as_str()), (Some(DEFAULT_SECONDS), None, "mdl_a"));
        let after = BakeAfter { steps: Some(50), ..after };
        let s = spec_after_training(&after, "mdl_a", "scn_a", 3);
        assert_eq!((s.seconds, s.steps), (None, Some(50)));
        let splats = ModelConfig::Splats(splats_config(&s));
        assert!(splats.check().is_ok());
        assert!(check_source(&None, &s).is_err());
    }
}
