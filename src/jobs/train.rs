//! A training job: load the scene, build or restore the model, train with
//! periodic checkpoints, measure the result on held-out views.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::{Job, Outcome, Shared, TrainSpec, set_progress};
use crate::engine::dataset::{Dataset, LoadOptions, Split};
use crate::engine::geometry::scene::Scene;
use crate::engine::io::persist;
use crate::engine::metrics::psnr;
use crate::engine::models::Model;
use crate::engine::render::render_view;
use crate::engine::train::heldout::HeldOutPixels;
use crate::engine::train::trainer::{StopReason, TrainState, Trainer};
use crate::storage::{ModelInfo, SceneInfo, Storage, now_ms, write_json};

/// Held-out pixels rendered for each estimate of the test PSNR during training.
const HELD_OUT_PIXELS: usize = 1024;

/// Loads a stored scene's dataset (all splits).
pub fn load_dataset(storage: &Storage, scene: &SceneInfo) -> Result<Dataset, String> {
    let root = storage.scene_dir(&scene.id).join(&scene.root);
    Dataset::load(&root, &LoadOptions::default()).map_err(|e| e.to_string())
}

pub(crate) fn run(shared: &Shared, job: &Job, spec: &TrainSpec, cancel: &AtomicBool) -> Outcome {
    match train(shared, job, spec, cancel) {
        Ok(o) => o,
        Err(e) => Outcome::Failed(e),
    }
}

fn train(shared: &Shared, job: &Job, spec: &TrainSpec, cancel: &AtomicBool) -> Result<Outcome, String> {
    let storage = &shared.storage;
    let scene = storage
        .load_scene(&spec.scene_id)
        .map_err(|e| e.to_string())?
        .ok_or_else(|| format!("scene '{}' no longer exists", spec.scene_id))?;
    let ds = load_dataset(storage, &scene)?;
    if ds.train.is_empty() {
        return Err("the scene has no training views".into());
    }
    let model_id = job.reserved_model_id();
    let ckpt = storage.checkpoint(&model_id);
    let config = spec.config.train_config(spec.seed, spec.batch_rays, spec.budget.engine());
    let (model, adam, state) = if ckpt.is_file() {
        let r = persist::load_resumable(&ckpt).map_err(|e| format!("resuming from the checkpoint: {e}"))?;
        tracing::info!(job = %job.id, step = r.state.step, "resuming from checkpoint");
        (r.model, r.adam, r.state)
    } else {
        let (model, adam) = spec.config.build_with_adam(Scene::from_dataset(&ds), spec.seed, None)?;
        (model, adam, TrainState::default())
    };
    let mut trainer = Trainer::new(model, adam, config, state, &ds);
    let record = ModelRecord { shared, job, spec, model_id: &model_id, scene: &scene, created_at: now_ms() };
    let held_out = HeldOutPixels::new(&ds, HELD_OUT_PIXELS, spec.seed);
    let target = spec.budget.target_psnr;
    let mut heldout_every = shared.config.heldout_every;
    let mut last_heldout = trainer.state.elapsed;
    let mut last_save = trainer.state.elapsed;
    let mut last_report = Instant::now();
    let mut save_error = None;
    let mut reached = None;
    let (mut rays0, mut t0) = (trainer.state.rays, trainer.state.elapsed);
    let reason = trainer.run(cancel, |t, p| {
        let c = &shared.counters;
        c.train_steps.fetch_add(1, Ordering::Relaxed);
        // The held-out estimate: every `heldout_every` seconds of training,
        // spaced so that it never costs more than a fifth of the training time.
        let mut estimate = None;
        if let Some(h) = &held_out
            && p.elapsed - last_heldout >= heldout_every
        {
            last_heldout = p.elapsed;
            let started = Instant::now();
            let v = h.psnr(&*t.model);
            heldout_every = heldout_every.max(4.0 * started.elapsed().as_secs_f64());
            estimate = Some(v);
            if target.is_some_and(|goal| v >= goal) {
                reached = Some(v);
            }
        }
        if estimate.is_some() || reached.is_some() || last_report.elapsed().as_secs_f64() >= 0.1 {
            last_report = Instant::now();
            let dt = (p.elapsed - t0).max(1e-9);
            let rate = (p.rays - rays0) as f64 / dt;
            c.train_rays.fetch_add(p.rays - rays0, Ordering::Relaxed);
            c.train_micros.fetch_add((dt * 1e6) as u64, Ordering::Relaxed);
            (rays0, t0) = (p.rays, p.elapsed);
            set_progress(shared, &job.id, |j| {
                let g = &mut j.progress;
                g.step = p.step;
                g.total_steps = spec.budget.steps;
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
        if p.elapsed - last_save >= shared.config.checkpoint_every {
            last_save = p.elapsed;
            if let Err(e) = record.save(t, false, None) {
                save_error = Some(e);
                return false;
            }
        }
        reached.is_none()
    });
    if let Some(e) = save_error {
        return Err(e);
    }
    if let StopReason::Diverged { .. } = reason {
        // Repeated divergence fails the job; the last periodic checkpoint stays.
        return Err(reason.to_string());
    }
    if let Some(v) = reached {
        tracing::info!(job = %job.id, step = trainer.state.step, psnr = v, "target PSNR reached");
    }
    let p = trainer.progress(f64::NAN);
    set_progress(shared, &job.id, |j| {
        j.progress.step = p.step;
        j.progress.elapsed = p.elapsed;
        j.progress.eta = p.eta;
        j.progress.diverged_steps = p.diverged_steps;
        j.progress.rollbacks = p.rollbacks;
    });
    if reason == StopReason::Cancelled {
        // Canceled or shut down: keep what was learnt as a usable model.
        record.save(&trainer, true, None)?;
        return Ok(Outcome::Stopped);
    }
    record.save(&trainer, false, None)?;
    let metric = evaluate(&*trainer.model, &ds, shared.config.eval_views, cancel);
    if cancel.load(Ordering::SeqCst) {
        record.save(&trainer, true, None)?;
        return Ok(Outcome::Stopped);
    }
    set_progress(shared, &job.id, |j| {
        if let Some(m) = metric {
            (j.progress.test_psnr, j.progress.test_psnr_step) = (Some(m.0), Some(p.step));
        }
    });
    record.save(&trainer, true, metric)?;
    Ok(Outcome::Succeeded)
}

/// Mean PSNR over up to `max_views` held-out views (test split, else val).
fn evaluate(model: &dyn Model, ds: &Dataset, max_views: usize, cancel: &AtomicBool) -> Option<(f64, usize)> {
    let split = if ds.test.is_empty() { Split::Val } else { Split::Test };
    let mut sum = 0.0;
    let mut n = 0;
    for f in ds.split_frames(split).take(max_views) {
        if cancel.load(Ordering::Relaxed) {
            return None;
        }
        let v = render_view(model, &f.camera, ds.background);
        let gt: Vec<f32> = (0..f.camera.height)
            .flat_map(|j| (0..f.camera.width).map(move |i| (i, j)))
            .flat_map(|(i, j)| f.image.rgb_on(i, j, ds.background))
            .collect();
        sum += psnr(&v.rgb, &gt);
        n += 1;
    }
    (n > 0).then(|| (sum / n as f64, n))
}

/// Writes the checkpoint and the model record beside it.
struct ModelRecord<'a> {
    shared: &'a Shared,
    job: &'a Job,
    spec: &'a TrainSpec,
    model_id: &'a str,
    scene: &'a SceneInfo,
    created_at: u64,
}

impl ModelRecord<'_> {
    fn save(&self, t: &Trainer<'_>, complete: bool, metric: Option<(f64, usize)>) -> Result<(), String> {
        let storage = &self.shared.storage;
        let path = storage.checkpoint(self.model_id);
        persist::save(&path, &*t.model, &t.adam, &t.config, &t.state)
            .map_err(|e| format!("saving the checkpoint: {e}"))?;
        let previous = storage.load_model(self.model_id).ok().flatten();
        let info = ModelInfo {
            id: self.model_id.to_string(),
            scene_id: self.scene.id.clone(),
            job_id: self.job.id.clone(),
            model: self.spec.model.clone(),
            config: t.model.config_json(),
            steps: t.state.step,
            training_seconds: t.state.elapsed,
            test_psnr: metric.map(|m| m.0),
            test_views: metric.map_or(0, |m| m.1),
            size_bytes: std::fs::metadata(&path).map_or(0, |m| m.len()),
            created_at: previous.as_ref().map_or(self.created_at, |p| p.created_at),
            updated_at: now_ms(),
            complete,
            training_state: true,
            view: self.scene.view.clone(),
        };
        write_json(&storage.model_record(self.model_id), &info).map_err(|e| format!("saving the model record: {e}"))?;
        let id = self.model_id.to_string();
        set_progress(self.shared, &self.job.id, |j| j.model_id = Some(id));
        Ok(())
    }
}
