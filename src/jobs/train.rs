//! A training job: load the scene, run a training session on the job's
//! checkpoint (resumed when the job was interrupted), report its progress
//! and keep the model record beside the checkpoint, then measure the result
//! on held-out views.

use std::io;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::host::JobHost;
use super::scoring::{evaluate, load_dataset};
use super::{Job, JobError, Outcome, TrainSpec};
use crate::datadir::{ScenePart, now_ms};
use crate::engine::front::{
    DataSize, Dataset, Event, HeldOut, ModelChoice, PoseReport, Progress, Session, SessionConfig, Start, Stop,
    TrainConfig, TrainState, TransientReport,
};
use crate::records::{ModelInfo, SceneInfo};

/// Held-out pixels rendered for each estimate of the test PSNR during training.
const HELD_OUT_PIXELS: usize = 1024;

/// The body of a training job (see [`super::run_body`]).
pub(crate) fn run(host: &dyn JobHost, job: &Job, spec: &TrainSpec, cancel: &AtomicBool) -> Result<Outcome, JobError> {
    let scene = host.scene(&spec.scene_id)?.ok_or_else(|| JobError::SceneGone(spec.scene_id.clone()))?;
    let dir = host.scene_dir(&scene, ScenePart::Data)?;
    let ds = load_dataset(&dir.path, &scene, spec.masks)?;
    if ds.train.is_empty() {
        return Err(JobError::NoTrainingViews);
    }
    if let Some(reason) = &spec.model_reason {
        tracing::info!(job = %job.id, model = %spec.model, reason = %reason, "model chosen automatically");
    }
    let model_id = job.reserved_model_id();
    let ckpt = host.job_checkpoint(job, &model_id)?;
    let mut session = open_session(host, job, spec, &ds, ckpt.clone())?;
    let record = ModelRecord {
        host,
        ckpt,
        job,
        spec,
        model_id: &model_id,
        scene: &scene,
        config: session.trainer().model.config_json(),
        created_at: now_ms(),
    };
    let mut report = Report::new(host, job, spec, &session.trainer().state);
    let mut record_error = None;
    let stop = session.run(cancel, |event| match event {
        Event::Step { progress, held_out_psnr } => {
            report.step(&progress, held_out_psnr);
            true
        }
        Event::Saved { progress } => {
            record.write(&progress, false, None, None, None).map_err(|e| record_error = Some(e)).is_ok()
        }
    });
    let stop = stop?;
    if let Some(e) = record_error {
        return Err(JobError::Io(e));
    }
    finish(host, &session, &record, &ds, stop, cancel)
}

/// A session on the job's checkpoint: resumed from it when it exists (a job
/// that was interrupted), else on a fresh model.
fn open_session<'a>(
    host: &dyn JobHost,
    job: &Job,
    spec: &TrainSpec,
    ds: &'a Dataset,
    ckpt: PathBuf,
) -> Result<Session<'a>, JobError> {
    let resume = ckpt.is_file();
    let start = if resume {
        Start::Resume { from: ckpt.clone(), kind: None }
    } else {
        let (model, adam) = spec.config.build_with_adam(ds.scene(), spec.seed, None)?;
        Start::Fresh { model, adam }
    };
    let choice =
        spec.model_reason.as_ref().map(|reason| ModelChoice { preset: spec.model.clone(), reason: reason.clone() });
    let config = SessionConfig {
        train: TrainConfig {
            model_choice: choice,
            drop_transients: spec.drop_transients,
            ..spec.config.train_config(spec.seed, spec.batch_rays, spec.budget.engine())
        },
        out: ckpt,
        checkpoint_every: host.config().checkpoint_every,
        held_out: Some(HeldOut {
            pixels: HELD_OUT_PIXELS,
            every: host.config().heldout_every,
            target_psnr: spec.budget.target_psnr,
        }),
    };
    let session = Session::new(start, config, ds)?;
    if resume {
        tracing::info!(job = %job.id, step = session.started().step, "resuming from checkpoint");
    }
    Ok(session)
}

/// After the session: fails a diverged job, keeps a cancelled one's model,
/// and measures a finished one on held-out views.
fn finish(
    host: &dyn JobHost,
    session: &Session<'_>,
    record: &ModelRecord<'_>,
    ds: &Dataset,
    stop: Stop,
    cancel: &AtomicBool,
) -> Result<Outcome, JobError> {
    let job = record.job;
    match stop {
        // Repeated divergence fails the job; the last periodic checkpoint stays.
        Stop::Diverged { .. } => return Err(JobError::Diverged(stop)),
        Stop::TargetReached { psnr } => {
            tracing::info!(job = %job.id, step = session.trainer().state.step, psnr, "target PSNR reached");
        }
        // Aborted: only when a model record could not be written, which
        // `train` returned as the job's error before coming here.
        Stop::Budget | Stop::Cancelled | Stop::Aborted => {}
    }
    let p = session.trainer().progress(f64::NAN);
    let poses = session.trainer().model.poses().and_then(|p| p.report());
    let transients = session.trainer().transients.as_ref().map(|t| t.report());
    if let Some(t) = &transients {
        tracing::info!(job = %job.id, "transients: {}", t.summary());
    }
    let transients = transients.as_ref();
    host.set_progress(&job.id, &mut |j| {
        j.progress.step = p.step;
        j.progress.elapsed = p.elapsed;
        j.progress.eta = p.eta;
        j.progress.diverged_steps = p.diverged_steps;
        j.progress.rollbacks = p.rollbacks;
    });
    if stop == Stop::Cancelled {
        // Canceled or shut down: keep what was learnt as a usable model.
        record.write(&p, true, None, poses, transients)?;
        return Ok(Outcome::Stopped);
    }
    record.write(&p, false, None, poses, transients)?;
    let metric = evaluate(&*session.trainer().model, ds, host.config().eval_views, cancel);
    if cancel.load(Ordering::SeqCst) {
        record.write(&p, true, None, poses, transients)?;
        return Ok(Outcome::Stopped);
    }
    host.set_progress(&job.id, &mut |j| {
        if let Some(m) = metric {
            (j.progress.test_psnr, j.progress.test_psnr_step) = (Some(m.0), Some(p.step));
        }
    });
    record.write(&p, true, metric, poses, transients)?;
    if let Some(after) = &record.spec.bake {
        let data = DataSize::of(ds);
        let config = &record.spec.config;
        super::bake::enqueue_after_training(host, job, after, &record.scene.id, config, data, record.spec.seed)?;
    }
    Ok(Outcome::Succeeded)
}

/// The job's side of the session's step events: the service's counters on
/// every step, and the job's progress at most every 0.1 s (and with every
/// held-out estimate).
struct Report<'a> {
    host: &'a dyn JobHost,
    job: &'a Job,
    total_steps: Option<u64>,
    last: Instant,
    /// Rays and training time at the last report.
    rays0: u64,
    t0: f64,
}

impl<'a> Report<'a> {
    fn new(host: &'a dyn JobHost, job: &'a Job, spec: &TrainSpec, state: &TrainState) -> Self {
        let total_steps = spec.budget.steps;
        Self { host, job, total_steps, last: Instant::now(), rays0: state.rays, t0: state.elapsed }
    }

    fn step(&mut self, p: &Progress, estimate: Option<f64>) {
        let c = self.host.counters();
        c.train_steps.fetch_add(1, Ordering::Relaxed);
        if estimate.is_none() && self.last.elapsed().as_secs_f64() < 0.1 {
            return;
        }
        self.last = Instant::now();
        let dt = (p.elapsed - self.t0).max(1e-9);
        let rate = (p.rays - self.rays0) as f64 / dt;
        c.train_rays.fetch_add(p.rays - self.rays0, Ordering::Relaxed);
        c.train_micros.fetch_add((dt * 1e6) as u64, Ordering::Relaxed);
        (self.rays0, self.t0) = (p.rays, p.elapsed);
        self.host.set_progress(&self.job.id, &mut |j| {
            let g = &mut j.progress;
            g.step = p.step;
            g.total_steps = self.total_steps;
            g.loss = p.loss;
            g.train_psnr = p.train_psnr;
            g.elapsed = p.elapsed;
            g.eta = p.eta;
            g.rays_per_second = rate;
            g.diverged_steps = p.diverged_steps;
            g.rollbacks = p.rollbacks;
            if let Some(v) = estimate {
                (g.test_psnr, g.test_psnr_step) = (Some(v), Some(p.step));
            }
        });
    }
}

/// The model record beside the job's checkpoint (which the session saves).
struct ModelRecord<'a> {
    host: &'a dyn JobHost,
    /// The job's checkpoint (see [`JobHost::job_checkpoint`]).
    ckpt: PathBuf,
    job: &'a Job,
    spec: &'a TrainSpec,
    model_id: &'a str,
    scene: &'a SceneInfo,
    /// The model's configuration, as its checkpoint stores it.
    config: serde_json::Value,
    created_at: u64,
}

impl ModelRecord<'_> {
    /// Writes the record of the checkpoint saved at `p.step`; `poses` is
    /// the pose report of a model that refines its cameras and
    /// `transients` what a run that drops transients dropped (both given
    /// when training has ended).
    fn write(
        &self,
        p: &Progress,
        complete: bool,
        metric: Option<(f64, usize)>,
        poses: Option<PoseReport>,
        transients: Option<&TransientReport>,
    ) -> io::Result<()> {
        let previous = self.host.model(self.model_id).ok().flatten();
        let info = ModelInfo {
            id: self.model_id.to_string(),
            scene_id: self.scene.id.clone(),
            job_id: self.job.id.clone(),
            model: self.spec.model.clone(),
            model_reason: self.spec.model_reason.clone(),
            config: self.config.clone(),
            steps: p.step,
            training_seconds: p.elapsed,
            test_psnr: metric.map(|m| m.0),
            test_views: metric.map_or(0, |m| m.1),
            size_bytes: std::fs::metadata(&self.ckpt).map_or(0, |m| m.len()),
            created_at: previous.as_ref().map_or(self.created_at, |p| p.created_at),
            updated_at: now_ms(),
            complete,
            training_state: true,
            view: self.scene.view.clone(),
            poses,
            gaussians: None,
            transients: transients.cloned(),
            crop: previous.as_ref().and_then(|p| p.crop),
        };
        self.host.publish_model(self.job, &info, &self.ckpt)?;
        self.host.set_progress(&self.job.id, &mut |j| j.model_id = Some(info.id.clone()));
        Ok(())
    }
}
