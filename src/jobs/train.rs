//! A training job: load the scene, build or restore the model, train with
//! periodic checkpoints, measure the result on held-out views.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::{Job, Outcome, Shared, set_progress};
use crate::engine::adam::{Adam, AdamConfig};
use crate::engine::dataset::{Dataset, LoadOptions, Split};
use crate::engine::metrics::psnr;
use crate::engine::model::Model;
use crate::engine::nerf::{NerfConfig, NerfModel};
use crate::engine::nerf_net::NetConfig;
use crate::engine::persist;
use crate::engine::render::render_view;
use crate::engine::scene::Scene;
use crate::engine::trainer::{StopReason, TrainConfig, TrainState, Trainer};
use crate::storage::{ModelInfo, SceneInfo, Storage, now_ms, write_json};

/// Model presets a job may name.
pub const PRESETS: [&str; 2] = ["nerf", "nerf-tiny"];

/// The configuration of a preset: `nerf` is the paper's model (the engine's
/// default); `nerf-tiny` is a small network for previews and tests.
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

/// Refuses configurations that would allocate absurdly or not run.
pub fn check_config(c: &NerfConfig) -> Result<(), String> {
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
        && c.occupancy.as_ref().is_none_or(|o| (1..=256).contains(&o.resolution) && o.sweep >= 1);
    if ok {
        Ok(())
    } else {
        Err("model config out of range (width, dir_width 1..=1024, depth 1..=32, skip < depth, \
             freqs <= 24, samples <= 1024, chunk_rays 1..=4096, occupancy resolution 1..=256)"
            .into())
    }
}

/// Loads a stored scene's dataset (all splits).
pub fn load_dataset(storage: &Storage, scene: &SceneInfo) -> Result<Dataset, String> {
    let root = storage.scene_dir(&scene.id).join(&scene.root);
    Dataset::load(&root, &LoadOptions::default()).map_err(|e| e.to_string())
}

pub(crate) fn run(shared: &Shared, job: &Job, cancel: &AtomicBool) -> Outcome {
    match train(shared, job, cancel) {
        Ok(o) => o,
        Err(e) => Outcome::Failed(e),
    }
}

fn train(shared: &Shared, job: &Job, cancel: &AtomicBool) -> Result<Outcome, String> {
    let storage = &shared.storage;
    let spec = &job.spec;
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
    let mut config = TrainConfig::default();
    (config.seed, config.batch_rays, config.budget) = (spec.seed, spec.batch_rays, spec.budget);
    let (model, adam, state) = if ckpt.is_file() {
        let r = persist::load(&ckpt).map_err(|e| format!("resuming from the checkpoint: {e}"))?;
        tracing::info!(job = %job.id, step = r.state.step, "resuming from checkpoint");
        (r.model, r.adam, r.state)
    } else {
        let model: Box<dyn Model> = Box::new(NerfModel::new(spec.config.clone(), Scene::from_dataset(&ds), spec.seed));
        let n = model.params().len();
        (model, Adam::new(AdamConfig::default(), n), TrainState::default())
    };
    let mut trainer = Trainer::new(model, adam, config, state, &ds);
    let record = ModelRecord { shared, job, model_id: &model_id, scene: &scene, created_at: now_ms() };
    let mut last_save = trainer.state.elapsed;
    let mut last_report = Instant::now();
    let mut save_error = None;
    let (mut rays0, mut t0) = (trainer.state.rays, trainer.state.elapsed);
    let reason = trainer.run(cancel, |t, p| {
        let c = &shared.counters;
        c.train_steps.fetch_add(1, Ordering::Relaxed);
        if last_report.elapsed().as_secs_f64() >= 0.1 {
            last_report = Instant::now();
            let dt = (p.elapsed - t0).max(1e-9);
            let rate = (p.rays - rays0) as f64 / dt;
            c.train_rays.fetch_add(p.rays - rays0, Ordering::Relaxed);
            c.train_micros.fetch_add((dt * 1e6) as u64, Ordering::Relaxed);
            (rays0, t0) = (p.rays, p.elapsed);
            set_progress(shared, &job.id, |j| {
                j.progress.step = p.step;
                j.progress.loss = p.loss;
                j.progress.train_psnr = p.train_psnr;
                j.progress.elapsed = p.elapsed;
                j.progress.eta = p.eta;
                j.progress.rays_per_second = rate;
            });
        }
        if p.elapsed - last_save >= shared.config.checkpoint_every {
            last_save = p.elapsed;
            if let Err(e) = record.save(t, false, None) {
                save_error = Some(e);
                return false;
            }
        }
        true
    });
    if let Some(e) = save_error {
        return Err(e);
    }
    if let StopReason::Diverged { .. } = reason {
        // Repeated divergence fails the job; the last periodic checkpoint stays.
        return Err(reason.to_string());
    }
    let p = trainer.progress(f64::NAN);
    set_progress(shared, &job.id, |j| {
        j.progress.step = p.step;
        j.progress.elapsed = p.elapsed;
        j.progress.eta = p.eta;
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
    set_progress(shared, &job.id, |j| j.progress.test_psnr = metric.map(|m| m.0));
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
            model: self.job.spec.model.clone(),
            config: t.model.config_json(),
            steps: t.state.step,
            training_seconds: t.state.elapsed,
            test_psnr: metric.map(|m| m.0),
            test_views: metric.map_or(0, |m| m.1),
            size_bytes: std::fs::metadata(&path).map_or(0, |m| m.len()),
            created_at: previous.as_ref().map_or(self.created_at, |p| p.created_at),
            updated_at: now_ms(),
            complete,
            view: self.scene.view.clone(),
        };
        write_json(&storage.model_record(self.model_id), &info).map_err(|e| format!("saving the model record: {e}"))?;
        let id = self.model_id.to_string();
        set_progress(self.shared, &self.job.id, |j| j.model_id = Some(id));
        Ok(())
    }
}
