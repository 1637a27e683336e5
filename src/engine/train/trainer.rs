//! The training loop: random rays from all training images (inside their
//! masks when the dataset says to ignore the outside, see `pixels`), the
//! model's loss and gradients computed in parallel parts, Adam with an exponential
//! learning-rate schedule, progress through a callback and a cancel flag.
//!
//! Deterministic for a given seed and thread count: the rays of step `s`
//! depend only on `(seed, s)`, each part of a batch accumulates into its own
//! gradient buffer, and the parts are summed in order.
//!
//! Divergence guard: a step whose loss or gradient is not finite is skipped
//! (the parameters are untouched). After [`DivergenceGuard::patience`] such
//! steps in a row the trainer rolls the parameters and Adam's state back to
//! its last in-memory snapshot (taken every
//! [`DivergenceGuard::snapshot_every`] good steps) and halves the learning
//! rate (`TrainState::lr_scale`); the step counter keeps going, so the next
//! steps see new rays. When it would need more than
//! [`DivergenceGuard::max_rollbacks`] rollbacks, [`Trainer::run`] restores the
//! last snapshot once more and stops with [`StopReason::Diverged`].

use std::ops::Range;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use crate::engine::batch::{BatchStats, StepCtx, TrainRay};
use crate::engine::dataset::Dataset;
use crate::engine::models::training::TrainConfig;
use crate::engine::models::{Model, RayMeasure};
use crate::engine::nn::adam::{Adam, AdamUpdate};
use crate::engine::nn::all_finite;
use crate::engine::nn::hashgrid::{GridRecord, HashGrid};
use crate::engine::rng::Rng;
use crate::engine::train::pixels::PixelPool;
use crate::engine::transient::{JUDGE_FROM, RECORD_FROM, TransientMaps};

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
    /// Evaluations of the proposal networks (capture model; 0 otherwise).
    pub proposal_samples: u64,
    pub skipped: u64,
    /// Steps skipped because the loss or a gradient was not finite.
    pub diverged_steps: u64,
    /// Rollbacks to the last good parameters (each halved the learning rate).
    pub rollbacks: u32,
}

/// The trainer's state, saved in checkpoints so a run resumes exactly.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainState {
    pub step: u64,
    /// Wall-clock seconds of training (kept out of a checkpoint's identity,
    /// see `persist::identity_bytes`).
    #[serde(default)]
    pub elapsed: f64,
    pub rays: u64,
    pub samples: u64,
    /// Evaluations of the proposal networks so far (capture model; left
    /// out of the checkpoints of the others, which have none, so their
    /// bytes stay as they were).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub proposal_samples: u64,
    pub skipped: u64,
    pub diverged_steps: u64,
    pub smoothed_mse: f64,
    /// Factor on the scheduled learning rate: halved by every rollback.
    #[serde(default = "one")]
    pub lr_scale: f32,
    /// Rollbacks to the last good parameters so far.
    #[serde(default)]
    pub rollbacks: u32,
}

fn one() -> f32 {
    1.0
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

impl Default for TrainState {
    fn default() -> Self {
        Self {
            step: 0,
            elapsed: 0.0,
            rays: 0,
            samples: 0,
            proposal_samples: 0,
            skipped: 0,
            diverged_steps: 0,
            smoothed_mse: 0.0,
            lr_scale: 1.0,
            rollbacks: 0,
        }
    }
}

/// How the trainer reacts to steps with a non-finite loss or gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DivergenceGuard {
    /// Non-finite steps in a row that trigger a rollback (5).
    pub patience: u32,
    /// Good steps between snapshots of the parameters and Adam's state (100).
    pub snapshot_every: u64,
    /// Rollbacks allowed; one more divergence stops the run (3).
    pub max_rollbacks: u32,
}

impl Default for DivergenceGuard {
    fn default() -> Self {
        Self { patience: 5, snapshot_every: 100, max_rollbacks: 3 }
    }
}

/// Parameters and optimiser state at a good step.
struct Snapshot {
    params: Vec<f32>,
    m: Vec<f32>,
    v: Vec<f32>,
    t: u64,
    step: u64,
}

/// Why a run stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    Budget,
    Cancelled,
    /// The callback asked to stop.
    Callback,
    /// Training kept producing non-finite losses or gradients after
    /// `rollbacks` rollbacks; the model holds the parameters of `good_step`.
    Diverged {
        step: u64,
        good_step: u64,
        rollbacks: u32,
    },
}

impl std::fmt::Display for StopReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Budget => f.write_str("the budget is spent"),
            Self::Cancelled => f.write_str("cancelled"),
            Self::Callback => f.write_str("stopped by the caller"),
            Self::Diverged { step, good_step, rollbacks } => write!(
                f,
                "training diverged: the loss or gradient was still not finite at step {step} after {rollbacks} \
                 rollbacks with the learning rate halved each time; the parameters are those of step {good_step}"
            ),
        }
    }
}

/// Steps between judgements of the transient cells.
const JUDGE_EVERY: u64 = 50;

/// Trains a model on a dataset's training split.
pub struct Trainer<'a> {
    pub model: Box<dyn Model>,
    pub adam: Adam,
    pub config: TrainConfig,
    pub state: TrainState,
    dataset: &'a Dataset,
    /// The training pixels rays are drawn from.
    pixels: PixelPool,
    part_grads: Vec<Vec<f32>>,
    /// Each part's deferred grid gradients ([`DeferredGrid::train_rays_deferred`](crate::engine::models::DeferredGrid::train_rays_deferred)).
    part_records: Vec<GridRecord>,
    pub guard: DivergenceGuard,
    snapshot: Option<Snapshot>,
    /// Non-finite steps in a row, and good steps since the last snapshot.
    bad_streak: u32,
    good_streak: u64,
    /// Set when the guard gives up.
    diverged: Option<StopReason>,
    /// The training photos' transient cells (robust training only).
    pub transients: Option<TransientMaps>,
    /// What the last step measured of each ray.
    errors: Vec<RayMeasure>,
}

impl<'a> Trainer<'a> {
    pub fn new(
        model: Box<dyn Model>,
        adam: Adam,
        config: TrainConfig,
        state: TrainState,
        dataset: &'a Dataset,
    ) -> Self {
        let transients = config.drop_transients.then(|| TransientMaps::for_dataset(dataset));
        Self {
            model,
            adam,
            config,
            state,
            dataset,
            pixels: PixelPool::new(dataset),
            part_grads: Vec::new(),
            part_records: Vec::new(),
            guard: DivergenceGuard::default(),
            snapshot: None,
            bad_streak: 0,
            good_streak: 0,
            diverged: None,
            errors: Vec::new(),
            transients,
        }
    }

    /// Remembers the current parameters and Adam state as the point to roll
    /// back to (when they are finite). Runs every `guard.snapshot_every`
    /// good steps and before the first step.
    pub fn snapshot(&mut self) {
        if !self.model.params().iter().all(|p| p.is_finite()) {
            return;
        }
        let s = self.snapshot.get_or_insert_with(|| Snapshot {
            params: Vec::new(),
            m: Vec::new(),
            v: Vec::new(),
            t: 0,
            step: 0,
        });
        s.params.clear();
        s.params.extend_from_slice(self.model.params());
        s.m.clone_from(&self.adam.m);
        s.v.clone_from(&self.adam.v);
        s.t = self.adam.t;
        s.step = self.state.step;
        self.good_streak = 0;
    }

    /// Restores the last snapshot; returns its step.
    fn restore(&mut self) -> u64 {
        let Some(s) = &self.snapshot else { return self.state.step };
        self.model.params_mut().copy_from_slice(&s.params);
        self.adam.m.clone_from(&s.m);
        self.adam.v.clone_from(&s.v);
        self.adam.t = s.t;
        self.good_streak = 0;
        s.step
    }

    /// Counts a non-finite step; rolls back or gives up after `patience`.
    fn on_divergence(&mut self) {
        self.state.diverged_steps += 1;
        self.bad_streak += 1;
        if self.bad_streak < self.guard.patience.max(1) {
            return;
        }
        self.bad_streak = 0;
        let good_step = self.restore();
        if self.state.rollbacks >= self.guard.max_rollbacks {
            self.diverged =
                Some(StopReason::Diverged { step: self.state.step, good_step, rollbacks: self.state.rollbacks });
        } else {
            self.state.rollbacks += 1;
            self.state.lr_scale *= 0.5;
        }
    }

    /// The training rays of a step: uniform over the training pixels (all
    /// of them, or those inside the masks).
    pub fn batch(&self, step: u64) -> Vec<TrainRay> {
        self.batch_at(step).0
    }

    /// [`Trainer::batch`], with each ray's training photo (its place in the
    /// training split) and pixel.
    fn batch_at(&self, step: u64) -> (Vec<TrainRay>, Vec<(u32, u32, u32)>) {
        let total = self.pixels.total();
        if total == 0 {
            return (Vec::new(), Vec::new());
        }
        let mut at = Vec::new();
        let mut rng = Rng::stream(self.config.seed, step, u64::MAX);
        let scene = self.model.scene();
        let bg = self.dataset.background;
        let random_bg = self.config.random_background;
        let batch = self.model.batch_rays().unwrap_or(self.config.batch_rays);
        let rays = (0..batch as u64)
            .map(|index| {
                let (k, local) = self.pixels.pixel(rng.below(total));
                let image = self.dataset.train[k];
                let frame = &self.dataset.frames[image];
                let w = frame.camera.width as u64;
                let (i, j) = ((local % w) as u32, (local / w) as u32);
                let background =
                    if random_bg && frame.image.has_alpha { [rng.f32(), rng.f32(), rng.f32()] } else { bg };
                at.push((k as u32, i, j));
                TrainRay {
                    ray: scene.to_model(&frame.camera.pixel_ray(i, j)),
                    target: frame.image.rgb_on(i, j, background),
                    background,
                    index,
                    image: image as u32,
                    weight: self.transients.as_ref().map_or(1.0, |t| t.weight(k, i, j)),
                }
            })
            .collect();
        (rays, at)
    }

    /// One optimisation step. Returns the batch statistics, or `None` when
    /// the step was skipped because the loss or gradient was not finite.
    pub fn step(&mut self) -> Option<BatchStats> {
        if self.snapshot.is_none() {
            self.snapshot();
        }
        let step = self.state.step;
        let total = self.gradients(step);
        let (first, rest) = self.part_grads.split_at_mut(1);
        let grads = &mut first[0];
        // The deferred grid's gradient is not in any buffer: it is scattered
        // level by level below, each level's straight into its Adam update.
        let grid = self.model.deferred().map(|d| d.grid());
        let deferred = grid.as_ref().map(|g| g.params.clone());
        self.state.step += 1;
        self.state.rays += total.rays;
        self.state.samples += total.samples;
        self.state.proposal_samples += total.proposal_samples;
        self.state.skipped += total.skipped;
        // The parameters too: ReLU (`f32::max`) swallows a NaN weight, which
        // leaves the loss finite but would make the model unsaveable.
        let sums_finite = sum_and_check(grads, rest, self.model.params(), deferred.clone());
        // Finite recorded gradients scatter into finite sums (short of an
        // overflow: that leaves non-finite parameters, which the next
        // step's check catches).
        let records_finite = self.part_records.par_iter().all(|r| r.finite());
        let finite = total.loss.is_finite() && sums_finite && records_finite;
        if !finite {
            grads.fill(0.0);
            self.on_divergence();
            return None;
        }
        self.bad_streak = 0;
        let lr = self.adam.config.lr_at(self.config.budget.progress(step, self.state.elapsed)) * self.state.lr_scale;
        let update = self.adam.begin(lr);
        let groups = self.model.lr_groups();
        if let Some(grid) = &grid {
            debug_assert!(groups.iter().all(|g| g.range.end <= grid.params.start || g.range.start >= grid.params.end));
            update_grid(grid, &self.part_records, &update, self.model.params_mut(), &mut self.adam);
        }
        // Adam leaves `grads` zeroed for the next step.
        self.adam.apply(&update, self.model.params_mut(), grads, &groups, deferred);
        self.model.after_step(self.state.step, self.config.seed, &total);
        let mse = total.sq_err / total.rays.max(1) as f64;
        self.state.smoothed_mse =
            if self.state.smoothed_mse == 0.0 { mse } else { 0.9 * self.state.smoothed_mse + 0.1 * mse };
        self.good_streak += 1;
        if self.good_streak >= self.guard.snapshot_every.max(1) {
            self.snapshot();
        }
        Some(total)
    }

    /// The gradients of step `step`'s batch: the batch split into one part
    /// per thread, each part's gradient in its own buffer (and its deferred
    /// grid's in its own record). Returns the batch's statistics.
    fn gradients(&mut self, step: u64) -> BatchStats {
        let (rays, at) = self.batch_at(step);
        let parts = rayon::current_num_threads().max(1);
        let nparams = self.model.params().len();
        self.part_grads.resize_with(parts, Vec::new);
        self.part_records.resize_with(parts, GridRecord::default);
        let per = rays.len().div_ceil(parts).max(1);
        // A chunk of errors for every part, the empty ones too (their
        // records must be cleared as well); those past the rays stay NaN.
        self.errors.clear();
        self.errors.resize(parts * per, RayMeasure::UNKNOWN);
        let ctx = StepCtx { seed: self.config.seed, step, batch_rays: rays.len() };
        let model = &*self.model;
        let stats: Vec<BatchStats> = self
            .part_grads
            .par_iter_mut()
            .zip(self.part_records.par_iter_mut())
            .zip(self.errors.par_chunks_mut(per))
            .enumerate()
            .map(|(p, ((g, record), errors))| {
                // The buffers are left zeroed by the previous step.
                if g.len() != nparams {
                    g.clear();
                    g.resize(nparams, 0.0);
                }
                let lo = (p * per).min(rays.len());
                let hi = ((p + 1) * per).min(rays.len());
                match model.deferred() {
                    Some(d) => d.train_rays_deferred_measured(&rays[lo..hi], &ctx, g, record, &mut errors[..hi - lo]),
                    None => {
                        record.clear();
                        model.train_rays_measured(&rays[lo..hi], &ctx, g, &mut errors[..hi - lo])
                    }
                }
            })
            .collect();
        let mut total = BatchStats::default();
        for s in &stats {
            total.add(s);
        }
        let progress = self.config.budget.progress(step, self.state.elapsed);
        if let Some(t) = self.transients.as_mut().filter(|_| progress >= RECORD_FROM) {
            let scene = self.model.scene();
            for ((&(k, i, j), e), r) in at.iter().zip(&self.errors).zip(rays.iter()) {
                // Where the ray met a surface, in world units.
                let o = r.ray.origin + r.ray.dir * e.depth;
                let point = e.depth.is_finite().then(|| scene.point_to_world(o.to_array()));
                t.record(k as usize, i, j, e.sq_err, point);
            }
            if progress >= JUDGE_FROM && step.is_multiple_of(JUDGE_EVERY) {
                t.judge();
            }
        }
        total
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
            lr: self.adam.config.lr_at(b.progress(s.step, s.elapsed)) * s.lr_scale,
            rays: s.rays,
            samples: s.samples,
            proposal_samples: s.proposal_samples,
            skipped: s.skipped,
            diverged_steps: s.diverged_steps,
            rollbacks: s.rollbacks,
        }
    }

    /// Trains until the budget is spent, `cancel` is set, `on_step` returns
    /// false, or training diverges for good ([`StopReason::Diverged`], after
    /// a last `on_step`). `on_step` runs after every step; its time does not
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
            let go_on = on_step(self, &p);
            if let Some(reason) = self.diverged {
                return reason;
            }
            if !go_on {
                return StopReason::Callback;
            }
        }
    }
}

thread_local! {
    /// A thread's buffer for one level's gradient in [`update_grid`], and
    /// whether it may hold values (zero otherwise: each use ends zeroing it).
    static LEVEL_GRAD: std::cell::RefCell<(Vec<f32>, bool)> = const { std::cell::RefCell::new((Vec::new(), false)) };
}

/// Scatters the deferred grid's gradient from `records` and applies the
/// step's Adam `update` to its parameters, level by level in parallel: each
/// level's gradient is summed into a buffer of the thread's (the table's
/// largest level fits in a core's L2 cache) and used at once, instead of
/// going through the step's gradient buffer in memory and back. The same
/// values as [`HashGrid::scatter`] into that buffer and then
/// [`Adam::apply`], bit for bit.
fn update_grid(grid: &HashGrid, records: &[GridRecord], update: &AdamUpdate, params: &mut [f32], adam: &mut Adam) {
    let scatter = grid.prepare_scatter(records);
    let ranges = grid.level_ranges();
    // Each level's slices of the parameters and moments.
    let start = grid.params.start;
    let (mut p, mut m, mut v) =
        (&mut params[grid.params.clone()], &mut adam.m[grid.params.clone()], &mut adam.v[grid.params.clone()]);
    let mut levels = Vec::with_capacity(ranges.len());
    for (l, r) in ranges.iter().enumerate() {
        debug_assert_eq!(r.start, start + ranges[..l].iter().map(|r| r.len()).sum::<usize>());
        let n = r.len();
        let (p0, p1) = std::mem::take(&mut p).split_at_mut(n);
        let (m0, m1) = std::mem::take(&mut m).split_at_mut(n);
        let (v0, v1) = std::mem::take(&mut v).split_at_mut(n);
        levels.push((l, p0, m0, v0));
        (p, m, v) = (p1, m1, v1);
    }
    levels.into_par_iter().for_each(|(l, p, m, v)| {
        LEVEL_GRAD.with(|cell| {
            let (buf, dirty) = &mut *cell.borrow_mut();
            if buf.len() < p.len() {
                buf.resize(p.len(), 0.0);
            }
            if *dirty {
                // A use that did not finish (a panic) may have left values.
                buf.fill(0.0);
            }
            *dirty = true;
            let g = &mut buf[..p.len()];
            scatter.level(l, g);
            update.update(p, g, m, v, 1.0);
            *dirty = false;
        })
    });
}

/// Adds the per-thread gradients `rest` into `grads`, zeroing them for the
/// next step, and returns whether the sum and `params` are all finite: one
/// pass over the buffers instead of three. Inside `skip` (a deferred range,
/// whose gradient is in no buffer: they all hold zeros there) the
/// gradients are neither read nor checked; the parameters are.
fn sum_and_check(grads: &mut [f32], rest: &mut [Vec<f32>], params: &[f32], skip: Option<Range<usize>>) -> bool {
    const CHUNK: usize = 1 << 14;
    let mut parts: Vec<Vec<&mut [f32]>> = (0..grads.len().div_ceil(CHUNK)).map(|_| Vec::new()).collect();
    for g in rest.iter_mut() {
        for (i, c) in g.chunks_mut(CHUNK).enumerate() {
            parts[i].push(c);
        }
    }
    // Every chunk is visited (no early exit), so `rest` always ends zeroed.
    grads
        .par_chunks_mut(CHUNK)
        .zip(parts.par_iter_mut())
        .zip(params.par_chunks(CHUNK))
        .enumerate()
        .map(|(c, ((g, others), p))| {
            // The chunk's part before `skip` and after it.
            let start = c * CHUNK;
            let (lo, hi) = match &skip {
                Some(r) => (r.start.clamp(start, start + g.len()) - start, r.end.clamp(start, start + g.len()) - start),
                None => (g.len(), g.len()),
            };
            for o in others.iter_mut() {
                for r in [0..lo, hi.max(lo)..g.len()] {
                    for (a, b) in g[r.clone()].iter_mut().zip(o[r].iter_mut()) {
                        *a += *b;
                        *b = 0.0;
                    }
                }
            }
            all_finite(&g[..lo]) && all_finite(&g[hi.max(lo)..]) && all_finite(p)
        })
        .reduce(|| true, |a, b| a && b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sum_and_check_sums_zeroes_and_flags() {
        let n = 40_000;
        let mut grads: Vec<f32> = (0..n).map(|i| i as f32).collect();
        let mut rest = vec![vec![1.0f32; n], (0..n).map(|i| -(i as f32) * 0.5).collect()];
        let params = vec![0.5f32; n];
        assert!(sum_and_check(&mut grads, &mut rest, &params, None));
        for (i, g) in grads.iter().enumerate() {
            assert_eq!(*g, i as f32 + 1.0 - i as f32 * 0.5);
        }
        assert!(rest.iter().all(|r| r.iter().all(|v| *v == 0.0)), "the parts are left zeroed");
        // A non-finite part in the last chunk, or a NaN parameter, fails the step; the parts still end zeroed.
        rest[1][n - 1] = f32::INFINITY;
        assert!(!sum_and_check(&mut grads, &mut rest, &params, None));
        assert!(rest.iter().all(|r| r.iter().all(|v| *v == 0.0)));
        grads.fill(0.0);
        let mut nan_params = params.clone();
        nan_params[17_000] = f32::NAN;
        assert!(!sum_and_check(&mut grads, &mut rest, &nan_params, None));
        assert!(sum_and_check(&mut grads, &mut rest, &params, None));
    }

    /// A deferred range spanning chunk boundaries: the parts are summed and
    /// zeroed outside it and not read inside it (their values there stay),
    /// and it is still checked for non-finite values.
    #[test]
    fn sum_and_check_skips_the_deferred_range_but_checks_its_parameters() {
        let n = 50_000;
        let skip = 10_000..33_000;
        let params = vec![0.5f32; n];
        let mut grads: Vec<f32> = (0..n).map(|i| i as f32).collect();
        let mut rest = vec![vec![2.0f32; n], vec![-0.5f32; n]];
        assert!(sum_and_check(&mut grads, &mut rest, &params, Some(skip.clone())));
        for (i, g) in grads.iter().enumerate() {
            let want = if skip.contains(&i) { i as f32 } else { i as f32 + 1.5 };
            assert_eq!(*g, want, "{i}");
        }
        for r in &rest {
            assert!(r.iter().enumerate().all(|(i, v)| (*v != 0.0) == skip.contains(&i)));
        }
        // The range's gradient is in no buffer: not checked there...
        grads[20_000] = f32::NAN;
        assert!(sum_and_check(&mut grads, &mut rest, &params, Some(skip.clone())));
        // ...but on either side of it.
        for at in [9_999, 33_000] {
            grads[at] = f32::NAN;
            assert!(!sum_and_check(&mut grads, &mut rest, &params, Some(skip.clone())), "{at}");
            grads[at] = 0.0;
        }
        grads[20_000] = 0.0;
        let mut nan_params = params.clone();
        nan_params[32_999] = f32::INFINITY;
        assert!(!sum_and_check(&mut grads, &mut rest, &nan_params, Some(skip)));
    }

    /// `update_grid` gives what scattering the records into a zeroed
    /// gradient buffer and an Adam step over it give, bit for bit, also
    /// when a thread's level buffer was left holding values.
    #[test]
    fn update_grid_is_the_scatter_then_adam() {
        use crate::engine::nn::adam::AdamConfig;
        use crate::engine::nn::hashgrid::HashGridConfig;
        use crate::engine::nn::linear::ParamLayout;
        let mut layout = ParamLayout::default();
        layout.add("before", 11);
        let grid = HashGrid::new(
            &mut layout,
            HashGridConfig { levels: 6, log2_table: 9, base_resolution: 2, finest_resolution: 64 },
        );
        layout.add("after", 5);
        let n = layout.len;
        let mut rng = Rng::new(12);
        let mut records = vec![GridRecord::default(); 2];
        for record in &mut records {
            for count in [45, 16, 3] {
                let pts: Vec<f32> = (0..3 * count).map(|_| rng.f32() * 1.1 - 0.05).collect();
                let dout: Vec<f32> = (0..count * grid.width()).map(|_| rng.f32() - 0.5).collect();
                grid.record(&pts, &dout, record);
            }
        }
        let params: Vec<f32> = (0..n).map(|_| rng.f32() - 0.5).collect();
        let config = AdamConfig { lr: 1e-2, lr_end: 1e-3, beta1: 0.9, beta2: 0.99, eps: 1e-15 };
        // A step done before, so that the moments are not zero.
        let mut adam = Adam::new(config, n);
        let mut first: Vec<f32> = (0..n).map(|_| rng.f32() - 0.5).collect();
        let mut p0 = params.clone();
        adam.step(&mut p0, &mut first, 0.01);

        let (mut want_adam, mut want) = (adam.clone(), p0.clone());
        let mut grads = vec![0.0f32; n];
        grid.scatter(&records, &mut grads);
        assert!(grads[grid.params.clone()].iter().filter(|v| **v != 0.0).count() > 100);
        // The other parameters get a gradient too.
        for (i, g) in grads.iter_mut().enumerate().filter(|(i, _)| !grid.params.contains(i)) {
            *g = 0.01 * i as f32;
        }
        let mut other = grads.clone();
        other[grid.params.clone()].fill(0.0);
        want_adam.step(&mut want, &mut grads, 0.005);

        for dirty in [false, true] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            let (mut got_adam, mut got) = (adam.clone(), p0.clone());
            let mut g = other.clone();
            pool.install(|| {
                if dirty {
                    LEVEL_GRAD.with(|c| *c.borrow_mut() = (vec![3.0; 4096], true));
                }
                let update = got_adam.begin(0.005);
                update_grid(&grid, &records, &update, &mut got, &mut got_adam);
                got_adam.apply(&update, &mut got, &mut g, &[], Some(grid.params.clone()));
                LEVEL_GRAD.with(|c| {
                    let (buf, left) = &*c.borrow();
                    assert!(!left && buf.iter().all(|v| *v == 0.0), "the level buffer is left zeroed");
                });
            });
            assert!(g.iter().all(|v| *v == 0.0));
            assert_eq!(got_adam.t, want_adam.t);
            for i in 0..n {
                assert_eq!(got[i].to_bits(), want[i].to_bits(), "parameter {i} (dirty: {dirty})");
                assert_eq!(got_adam.m[i].to_bits(), want_adam.m[i].to_bits(), "m {i}");
                assert_eq!(got_adam.v[i].to_bits(), want_adam.v[i].to_bits(), "v {i}");
            }
        }
    }
}
