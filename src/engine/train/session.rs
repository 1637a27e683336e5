//! One training session, as `radiance train` and the service's training jobs
//! run it: start from a fresh model or resume a checkpoint, train to the
//! budget, save atomically every `checkpoint_every` seconds of training and
//! at the end, estimate the held-out PSNR now and then (stopping early at a
//! target), report every step through a callback, and stop when a cancel
//! flag is set.
//!
//! The session knows no jobs, storage or terminals: its caller maps the
//! [`Event`]s to its own world (a job's progress and model record, the CLI's
//! progress bar) and the [`Stop`] to its outcome.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use crate::engine::dataset::Dataset;
use crate::engine::io::checkpoint::CheckpointError;
use crate::engine::models::Model;
use crate::engine::models::config::ModelConfig;
use crate::engine::models::training::TrainConfig;
use crate::engine::nn::adam::Adam;
use crate::engine::train::heldout::HeldOutPixels;
use crate::engine::train::persist;
use crate::engine::train::trainer::{Progress, StopReason, TrainState, Trainer};

/// Where a session's model and optimiser come from.
pub enum Start {
    /// A fresh model and its optimiser; training starts at step 0.
    Fresh { model: Box<dyn Model>, adam: Adam },
    /// The model, optimiser and trainer state saved at `from`, which must
    /// keep its optimiser state (not render-only) and, when `kind` is
    /// given, hold a model of that kind. The session's [`TrainConfig`]
    /// replaces the checkpoint's: its budget is the new total (the
    /// checkpoint's `model_choice` is kept when the session gives none).
    Resume { from: PathBuf, kind: Option<String> },
}

/// Estimates of the held-out PSNR while training goes on (see
/// [`HeldOutPixels`]).
#[derive(Clone, Copy, Debug)]
pub struct HeldOut {
    /// Pixels rendered for each estimate.
    pub pixels: usize,
    /// Seconds of training between estimates; spaced out further when an
    /// estimate would cost more than a fifth of the training time.
    pub every: f64,
    /// Stop once an estimate reaches this PSNR (dB).
    pub target_psnr: Option<f64>,
}

/// How a session trains and where it saves.
#[derive(Clone, Debug)]
pub struct SessionConfig {
    pub train: TrainConfig,
    /// The checkpoint file, written atomically (a reader sees the previous
    /// checkpoint or the new one, never part of one).
    pub out: PathBuf,
    /// Seconds of training between periodic checkpoints (0: every step).
    pub checkpoint_every: f64,
    /// Held-out estimates; none are made when the dataset has no test or
    /// validation views.
    pub held_out: Option<HeldOut>,
}

/// What a session tells its caller while it runs.
#[derive(Clone, Copy, Debug)]
pub enum Event {
    /// After every step; `held_out_psnr` when an estimate was made at it.
    Step { progress: Progress, held_out_psnr: Option<f64> },
    /// A periodic checkpoint was saved at `progress.step`. The final one is
    /// not an event: [`Session::run`] returning says it.
    Saved { progress: Progress },
}

/// Why a session stopped, and whether it saved at the end.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Stop {
    /// The budget is spent; saved.
    Budget,
    /// The cancel flag was set; saved.
    Cancelled,
    /// A held-out estimate reached the target PSNR; saved.
    TargetReached { psnr: f64 },
    /// The event callback returned `false`; nothing more was saved.
    Aborted,
    /// Training kept diverging (see [`StopReason::Diverged`]); the model
    /// holds the parameters of `good_step` and nothing more was saved.
    Diverged { step: u64, good_step: u64, rollbacks: u32 },
}

impl std::fmt::Display for Stop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Stop::Budget => StopReason::Budget.fmt(f),
            Stop::Cancelled => StopReason::Cancelled.fmt(f),
            Stop::TargetReached { psnr } => write!(f, "the held-out PSNR reached {psnr:.2} dB"),
            Stop::Aborted => StopReason::Callback.fmt(f),
            Stop::Diverged { step, good_step, rollbacks } => StopReason::Diverged { step, good_step, rollbacks }.fmt(f),
        }
    }
}

/// What went wrong in a session. The messages carry their cause, since
/// callers show them as they are (a job's error, the CLI's last line).
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The checkpoint to resume from is unreadable, or render-only.
    #[error("resuming from the checkpoint: {0}")]
    Resume(CheckpointError),
    #[error("{} holds a '{found}' model, not '{expected}'", .path.display())]
    WrongKind { path: PathBuf, expected: String, found: String },
    #[error("saving the checkpoint: {0}")]
    Save(CheckpointError),
    /// The checkpoint holds a kind the trainer cannot train from rays
    /// (splats: they are baked).
    #[error("{} holds a '{kind}' model, which is made by `radiance bake`, not trained from rays", .path.display())]
    NotTrainable { path: PathBuf, kind: String },
}

/// The held-out pixels and when to render them next.
struct Estimator {
    pixels: HeldOutPixels,
    every: f64,
    target_psnr: Option<f64>,
    /// Training time of the last estimate.
    last: f64,
}

impl Estimator {
    /// The held-out PSNR when `every` seconds of training passed since the
    /// last estimate.
    fn due(&mut self, model: &dyn Model, elapsed: f64) -> Option<f64> {
        if elapsed - self.last < self.every {
            return None;
        }
        self.last = elapsed;
        let started = Instant::now();
        let psnr = self.pixels.psnr(model);
        self.every = self.every.max(4.0 * started.elapsed().as_secs_f64());
        Some(psnr)
    }
}

/// A model training on a dataset, saving to one checkpoint file.
pub struct Session<'a> {
    trainer: Trainer<'a>,
    out: PathBuf,
    checkpoint_every: f64,
    estimator: Option<Estimator>,
    started: TrainState,
}

impl<'a> Session<'a> {
    /// Builds the trainer from `start`; trains nothing yet.
    pub fn new(start: Start, mut config: SessionConfig, ds: &'a Dataset) -> Result<Self, SessionError> {
        let (model, adam, state, saved) = match start {
            Start::Fresh { model, adam } => (model, adam, TrainState::default(), None),
            Start::Resume { from, kind } => {
                let r = persist::load_resumable(&from).map_err(SessionError::Resume)?;
                if let Some(expected) = kind
                    && r.model.kind() != expected
                {
                    return Err(SessionError::WrongKind { path: from, expected, found: r.model.kind().into() });
                }
                if ModelConfig::of_model(&*r.model).is_some_and(|c| !c.spec().trains_on_rays()) {
                    return Err(SessionError::NotTrainable { path: from, kind: r.model.kind().into() });
                }
                // Why the model is what it is stays with it, and a run
                // that dropped transients goes on dropping them.
                if config.train.model_choice.is_none() {
                    config.train.model_choice = r.train.model_choice;
                }
                config.train.drop_transients |= r.transients.is_some();
                (r.model, r.adam, r.state, r.transients.map(|t| (from, t)))
            }
        };
        let estimator = config.held_out.and_then(|h| {
            Some(Estimator {
                pixels: HeldOutPixels::new(ds, h.pixels, config.train.seed)?,
                every: h.every,
                target_psnr: h.target_psnr,
                last: state.elapsed,
            })
        });
        let started = state.clone();
        let mut trainer = Trainer::new(model, adam, config.train, state, ds);
        if let (Some(maps), Some((from, saved))) = (trainer.transients.as_mut(), saved) {
            maps.resume_from(&saved)
                .map_err(|message| SessionError::Resume(CheckpointError::Header { path: Some(from), message }))?;
        }
        Ok(Self { trainer, out: config.out, checkpoint_every: config.checkpoint_every, estimator, started })
    }

    pub fn trainer(&self) -> &Trainer<'a> {
        &self.trainer
    }

    /// The trainer's state when the session began (the checkpoint's when
    /// resuming): what this session added is the difference.
    pub fn started(&self) -> &TrainState {
        &self.started
    }

    /// Saves the model, optimiser and trainer state to the checkpoint file.
    pub fn save(&self) -> Result<(), SessionError> {
        save(&self.out, &self.trainer)
    }

    /// Trains until the budget is spent, `cancel` is set, a held-out
    /// estimate reaches the target, training diverges for good or
    /// `on_event` returns `false`; saves periodically and at the end (see
    /// [`Stop`] for which stops save). `on_event`'s time and the estimates'
    /// do not count as training time.
    pub fn run(&mut self, cancel: &AtomicBool, mut on_event: impl FnMut(Event) -> bool) -> Result<Stop, SessionError> {
        let Self { trainer, out, checkpoint_every, estimator, .. } = self;
        let mut last_save = trainer.state.elapsed;
        let (mut reached, mut aborted, mut save_error) = (None, false, None);
        let reason = trainer.run(cancel, |t, p| {
            let held_out_psnr = estimator.as_mut().and_then(|e| {
                let psnr = e.due(&*t.model, p.elapsed)?;
                if e.target_psnr.is_some_and(|goal| psnr >= goal) {
                    reached = Some(psnr);
                }
                Some(psnr)
            });
            if !on_event(Event::Step { progress: *p, held_out_psnr }) {
                aborted = true;
                return false;
            }
            if p.elapsed - last_save >= *checkpoint_every {
                last_save = p.elapsed;
                if let Err(e) = save(out, t) {
                    save_error = Some(e);
                    return false;
                }
                if !on_event(Event::Saved { progress: *p }) {
                    aborted = true;
                    return false;
                }
            }
            reached.is_none()
        });
        if let Some(e) = save_error {
            return Err(e);
        }
        let stop = match reason {
            StopReason::Budget => Stop::Budget,
            StopReason::Cancelled => Stop::Cancelled,
            StopReason::Diverged { step, good_step, rollbacks } => {
                return Ok(Stop::Diverged { step, good_step, rollbacks });
            }
            StopReason::Callback => match reached {
                Some(psnr) if !aborted => Stop::TargetReached { psnr },
                _ => return Ok(Stop::Aborted),
            },
        };
        self.save()?;
        Ok(stop)
    }
}

fn save(out: &Path, t: &Trainer<'_>) -> Result<(), SessionError> {
    persist::save(out, &*t.model, &t.adam, &t.config, &t.state, t.transients.as_ref()).map_err(SessionError::Save)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;

    use crate::engine::io::checkpoint::Checkpoint;
    use crate::engine::models::config::ModelConfig;
    use crate::engine::models::training::Budget;

    fn ball() -> Dataset {
        BallScene { size: 8, views: 4, ..Default::default() }.dataset()
    }

    fn fresh(ds: &Dataset) -> Start {
        let c = ModelConfig::preset("nerf-tiny").unwrap();
        let (model, adam) = c.build_with_adam(ds.scene(), 5, None).unwrap();
        Start::Fresh { model, adam }
    }

    fn config(out: &Path, steps: u64, checkpoint_every: f64) -> SessionConfig {
        let budget = Budget { steps: Some(steps), seconds: None };
        let train = TrainConfig { seed: 5, batch_rays: 32, budget, ..Default::default() };
        SessionConfig { train, out: out.to_path_buf(), checkpoint_every, held_out: None }
    }

    /// Steps of every `Step` and `Saved` event of a run.
    fn run(s: &mut Session<'_>, cancel: &AtomicBool) -> (Stop, Vec<u64>, Vec<u64>) {
        let (mut steps, mut saved) = (Vec::new(), Vec::new());
        let stop = s
            .run(cancel, |e| {
                match e {
                    Event::Step { progress, .. } => steps.push(progress.step),
                    Event::Saved { progress } => saved.push(progress.step),
                }
                true
            })
            .unwrap();
        (stop, steps, saved)
    }

    fn identity(path: &Path) -> Vec<u8> {
        persist::identity_bytes(&Checkpoint::load(path).unwrap())
    }

    #[test]
    fn resuming_a_cancelled_session_equals_a_straight_run() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let (straight, cut, resumed) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("c"));
        let mut s = Session::new(fresh(&ds), config(&straight, 12, 1e9), &ds).unwrap();
        assert_eq!(run(&mut s, &AtomicBool::new(false)).0, Stop::Budget);

        let cancel = AtomicBool::new(false);
        let mut s = Session::new(fresh(&ds), config(&cut, 12, 1e9), &ds).unwrap();
        let stop = s
            .run(&cancel, |e| {
                if let Event::Step { progress, .. } = e {
                    cancel.store(progress.step == 5, std::sync::atomic::Ordering::Relaxed);
                }
                true
            })
            .unwrap();
        assert_eq!(stop, Stop::Cancelled);

        let from = Start::Resume { from: cut, kind: Some("nerf".into()) };
        let mut s = Session::new(from, config(&resumed, 12, 1e9), &ds).unwrap();
        assert_eq!(s.started().step, 5);
        let (stop, steps, _) = run(&mut s, &AtomicBool::new(false));
        assert_eq!((stop, steps), (Stop::Budget, (6..=12).collect()));
        assert!(identity(&resumed) == identity(&straight), "the resumed run saved another model");
    }

    /// The automatic choice is saved in the checkpoint's `meta.train` and
    /// stays with the model when a session resumes without one.
    #[test]
    fn the_model_choice_is_saved_and_kept_on_resume() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let (first, second) = (dir.path().join("a"), dir.path().join("b"));
        let choice = crate::engine::models::auto::choose(&ds);
        let mut c = config(&first, 2, 1e9);
        c.train.model_choice = Some(choice.clone());
        let mut s = Session::new(fresh(&ds), c, &ds).unwrap();
        run(&mut s, &AtomicBool::new(false));
        let meta = Checkpoint::load(&first).unwrap().meta;
        assert_eq!(meta["train"]["model_choice"]["preset"], "instant", "{meta}");
        assert_eq!(persist::load(&first).unwrap().train.model_choice.as_ref(), Some(&choice));
        let from = Start::Resume { from: first, kind: None };
        let mut s = Session::new(from, config(&second, 4, 1e9), &ds).unwrap();
        run(&mut s, &AtomicBool::new(false));
        assert_eq!(persist::load(&second).unwrap().train.model_choice, Some(choice));
        // Without a choice (and without proposal networks) nothing new is
        // written: the checkpoints of named models keep their bytes.
        let mut s = Session::new(fresh(&ds), config(&dir.path().join("c"), 1, 1e9), &ds).unwrap();
        run(&mut s, &AtomicBool::new(false));
        let meta = Checkpoint::load(&dir.path().join("c")).unwrap().meta;
        assert!(
            meta["train"].get("model_choice").is_none() && meta["state"].get("proposal_samples").is_none(),
            "{meta}"
        );
    }

    #[test]
    fn checkpoints_are_saved_periodically_and_at_the_end() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ckpt");
        let mut s = Session::new(fresh(&ds), config(&out, 4, 0.0), &ds).unwrap();
        let mut saved = Vec::new();
        s.run(&AtomicBool::new(false), |e| {
            if let Event::Saved { progress } = e {
                // The event comes once the file holds this step.
                assert_eq!(persist::load(&out).unwrap().state.step, progress.step);
                saved.push(progress.step);
            }
            true
        })
        .unwrap();
        assert_eq!(saved, vec![1, 2, 3, 4]);

        // With no periodic checkpoint due, the end still saves.
        let out = dir.path().join("end.ckpt");
        let mut s = Session::new(fresh(&ds), config(&out, 3, 1e9), &ds).unwrap();
        let (stop, steps, saved) = run(&mut s, &AtomicBool::new(false));
        assert_eq!((stop, steps, saved), (Stop::Budget, vec![1, 2, 3], vec![]));
        assert_eq!(persist::load(&out).unwrap().state.step, 3);
        assert_eq!(dir.path().read_dir().unwrap().count(), 2, "no temporary file is left");
    }

    #[test]
    fn cancel_stops_and_saves() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ckpt");
        let cancel = AtomicBool::new(true);
        let mut s = Session::new(fresh(&ds), config(&out, 10, 1e9), &ds).unwrap();
        let (stop, steps, _) = run(&mut s, &cancel);
        assert_eq!((stop, steps), (Stop::Cancelled, vec![]));
        assert_eq!(persist::load_resumable(&out).unwrap().state.step, 0, "saved before any step");
    }

    #[test]
    fn an_aborting_callback_stops_without_saving() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ckpt");
        let mut s = Session::new(fresh(&ds), config(&out, 10, 1e9), &ds).unwrap();
        let stop = s.run(&AtomicBool::new(false), |e| !matches!(e, Event::Step { progress, .. } if progress.step == 2));
        assert_eq!(stop.unwrap(), Stop::Aborted);
        assert_eq!(s.trainer().state.step, 2);
        assert!(!out.exists());
    }

    #[test]
    fn held_out_estimates_are_reported_and_stop_at_the_target() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ckpt");
        let mut c = config(&out, 3, 1e9);
        c.held_out = Some(HeldOut { pixels: 64, every: 0.0, target_psnr: Some(f64::INFINITY) });
        let mut s = Session::new(fresh(&ds), c.clone(), &ds).unwrap();
        let mut estimates = Vec::new();
        let stop = s.run(&AtomicBool::new(false), |e| {
            if let Event::Step { held_out_psnr, .. } = e {
                estimates.push(held_out_psnr);
            }
            true
        });
        assert_eq!(stop.unwrap(), Stop::Budget);
        // The first is due at once; later ones are spaced by four times
        // what an estimate costs, which depends on this machine.
        assert_eq!(estimates.len(), 3);
        assert!(estimates[0].is_some_and(|v| v.is_finite() && v > 0.0), "{estimates:?}");

        // An untrained model's PSNR is above 0 dB: the first estimate stops.
        c.held_out = Some(HeldOut { pixels: 64, every: 0.0, target_psnr: Some(0.0) });
        let mut s = Session::new(fresh(&ds), c, &ds).unwrap();
        let (stop, steps, _) = run(&mut s, &AtomicBool::new(false));
        assert!(matches!(stop, Stop::TargetReached { psnr } if psnr > 0.0), "{stop:?}");
        assert_eq!(steps, vec![1]);
        assert_eq!(persist::load(&out).unwrap().state.step, 1, "saved at the end");
    }

    #[test]
    fn divergence_stops_without_saving() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ckpt");
        let Start::Fresh { mut model, adam } = fresh(&ds) else { unreachable!() };
        // Not finite from the start: every step is skipped, no rollback helps.
        model.params_mut()[0] = f32::NAN;
        let mut s = Session::new(Start::Fresh { model, adam }, config(&out, 100, 1e9), &ds).unwrap();
        let (stop, steps, _) = run(&mut s, &AtomicBool::new(false));
        assert!(matches!(stop, Stop::Diverged { rollbacks: 3, .. }), "{stop:?}");
        assert!(stop.to_string().contains("diverged"), "{stop}");
        assert_eq!(steps, (1..=20).collect::<Vec<_>>(), "four bursts of five bad steps");
        assert!(!out.exists(), "nothing is saved at the end of a diverged run");
    }

    #[test]
    fn resuming_refuses_a_render_only_checkpoint_or_another_kind() {
        let ds = ball();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ckpt");
        let mut s = Session::new(fresh(&ds), config(&out, 1, 1e9), &ds).unwrap();
        run(&mut s, &AtomicBool::new(false));
        let resume = |kind: &str| Start::Resume { from: out.clone(), kind: Some(kind.into()) };
        let e = Session::new(resume("instant"), config(&out, 2, 1e9), &ds).err().unwrap();
        assert!(matches!(&e, SessionError::WrongKind { found, .. } if found == "nerf"), "{e}");
        assert!(e.to_string().contains("holds a 'nerf' model, not 'instant'"), "{e}");

        assert!(persist::strip_training_state(&out).unwrap());
        let e = Session::new(resume("nerf"), config(&out, 2, 1e9), &ds).err().unwrap();
        assert!(matches!(e, SessionError::Resume(_)), "{e}");
        assert!(e.to_string().contains("m.ckpt") && e.to_string().contains("render-only"), "{e}");
    }
}
