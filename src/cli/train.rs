//! `radiance train`.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use super::setup::{DEFAULT_BATCH_RAYS, model_config, new_model_and_adam, resolve_model};
use super::{Common, MaskArgs, TransientArgs};
use crate::engine::front::{
    AUTO, BakeSettings, Budget, Checkpoint, DataSize, Dataset, Event, LoadOptions, MASK_INSIDE, MaskUse, ModelChoice,
    ModelConfig, Session, SessionConfig, Split, Start, Stop, TrainConfig, TransientMaps, estimate_training, mib,
    write_atomic,
};
use crate::media::png::encode_gray;
use crate::system::peak_memory;

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Dataset folder.
    #[arg(long)]
    pub data: PathBuf,
    /// Model kind: `auto` (the dataset decides: `instant` for an object on
    /// an empty background, `capture` for opaque photographs; the choice and
    /// its reason are printed), `instant` (hash grid, fast), `nerf` (the
    /// classic model of the paper) or `capture` (real photographs); or a
    /// preset: `instant-tiny`, `nerf-tiny`, `capture-tiny` (small, for
    /// previews), `capture-360` (capture with a larger, finer hash grid and
    /// a stronger distortion loss, auto's choice when the cameras go all
    /// around). With --resume, `auto` continues the checkpoint's model.
    /// `splats` (or `splats-dc`): Gaussian splats fitted to the photos,
    /// placed from a field that `auto`'s model trains first for a third of
    /// `--seconds` (kept as OUT with `.field.ckpt` for `.ckpt`); the rest
    /// of the time optimises the splats, as `radiance bake` does.
    #[arg(long, default_value = "auto")]
    pub model: String,
    /// Training time budget in seconds (training only, not saving).
    #[arg(long, conflicts_with = "steps")]
    pub seconds: Option<f64>,
    /// Number of optimisation steps (default 1000 when no --seconds).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Random seed: same seed, data and thread count give the same model.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Rays per optimisation step for `nerf` (`instant` adapts the number of
    /// rays to a constant sample budget).
    #[arg(long, default_value_t = DEFAULT_BATCH_RAYS)]
    pub batch_rays: usize,
    /// Initial learning rate (decays exponentially to a tenth of it; to 0.3 of it for the capture models).
    #[arg(long)]
    pub lr: Option<f32>,
    /// Save a checkpoint every this many seconds of training.
    #[arg(long, default_value_t = 60.0)]
    pub checkpoint_every: f64,
    /// Continue training from this checkpoint (its model and optimiser
    /// state; the budget given here is the new total).
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// Sample the whole clipped ray, without the occupancy grid (the paper's
    /// sampling; for speed comparisons).
    #[arg(long)]
    pub no_skip: bool,
    /// Override a setting of the model's preset, as a dotted JSON path and a
    /// JSON value: `--set grid.log2_table=17 --set occupancy.sweep=8`
    /// (repeatable; ignored with --resume, which keeps the checkpoint's).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Where to write the model checkpoint.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub masks: MaskArgs,
    #[command(flatten)]
    pub transients: TransientArgs,
    /// A `capture` model (which drops transients unless --keep-transients):
    /// write each training photo's mask into this folder when training
    /// ends, as DIR/NAME.png (the photo's file stem): 255 where the pixel
    /// was trained on, 0 where it was dropped, the layout of a dataset's
    /// `masks/` folder.
    #[arg(long, conflicts_with = "keep_transients", value_name = "DIR")]
    pub transient_masks: Option<PathBuf>,
    #[command(flatten)]
    pub common: Common,
}

fn fmt_secs(s: f64) -> String {
    let s = s.max(0.0).round() as u64;
    format!("{}:{:02}", s / 60, s % 60)
}

pub fn run(a: TrainArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    anyhow::ensure!(a.batch_rays > 0, "--batch-rays must be at least 1");
    if let Some(s) = a.seconds {
        anyhow::ensure!(s.is_finite() && s > 0.0, "--seconds must be a positive number");
    }
    let budget = match (a.seconds, a.steps) {
        (None, None) => Budget { steps: Some(1000), seconds: None },
        (s, n) => Budget { steps: n, seconds: s },
    };
    let opts = LoadOptions { splits: vec![Split::Train], masks: a.masks.masks, ..Default::default() };
    let ds = Dataset::load(&a.data, &opts).with_context(|| format!("loading {}", a.data.display()))?;
    anyhow::ensure!(!ds.train.is_empty(), "{}: the dataset has no training views", a.data.display());
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    if ModelConfig::preset(&a.model).is_some_and(|c| !c.spec().trains_on_rays()) {
        return train_splats(&a, &ds, threads);
    }
    let (kind, choice) = chosen_model(&a, &ds)?;
    if let Some(c) = &choice {
        eprintln!("model '{}' (auto): {}", c.preset, c.reason);
    }
    let mut session = open_session(&a, &kind, choice, budget, &ds)?;
    describe(&a, &session, &ds, threads);
    let cancel = cancel_on_ctrl_c()?;
    let wall = Instant::now();
    let stop = train_with_bar(&mut session, budget, &cancel)?;
    match stop {
        Stop::Cancelled => eprintln!("interrupted: saved the model at step {}", session.trainer().state.step),
        Stop::Budget | Stop::TargetReached { .. } | Stop::Aborted => {}
        Stop::Diverged { .. } => {
            // The trainer restored the last good parameters: keep them.
            session.save()?;
            anyhow::bail!("{stop}; they were saved to {}", a.out.display());
        }
    }
    summary(&session, wall, &a.out);
    if let (Some(dir), Some(maps)) = (&a.transient_masks, &session.trainer().transients) {
        write_transient_masks(maps, dir)?;
    }
    Ok(())
}

/// Writes every training photo's transient mask into `dir` (created), each
/// file atomically, and says how many.
fn write_transient_masks(maps: &TransientMaps, dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let photos = maps.photos();
    for (k, p) in photos.iter().enumerate() {
        let (w, h, gray) = maps.mask_image(k).expect("one image a photo");
        // Two photos of one name (from two folders) keep their index.
        let name = match maps.index_of(&p.name) {
            Some(first) if first == k => format!("{}.png", p.name),
            _ => format!("{k}_{}.png", p.name),
        };
        let path = dir.join(name);
        let png = encode_gray(w, h, &gray).context("encoding a mask")?;
        write_atomic(&path, &png).with_context(|| format!("writing {}", path.display()))?;
    }
    println!("masks          {} in {}", photos.len(), dir.display());
    Ok(())
}

/// The share of `train --model splats`'s time that trains the field the
/// splats are placed from. At equal total time, splats fitted longer from
/// a field trained shorter score better on held-out photos: fox, 180 s in
/// all (`train --seconds F`, then `bake --seconds 180-F`, `eval --fit-steps
/// 0`, 2-core Xeon VM), 29.00 dB from a field of 120 s, 29.59 from 60 s,
/// 29.60 from 30 s (the fields themselves: 29.68, 28.94 and 27.57);
/// gold_cape 19.66 dB (SSIM 0.640) from 120 s, 19.62 (SSIM 0.663) from 60
/// s. A third keeps a field good enough to place the splats from on a
/// harder scene than fox.
pub const SPLATS_FIELD_SHARE: f64 = 1.0 / 3.0;

/// The fewest steps the field of `train --model splats` makes, past its
/// share of the time if need be: on a slow machine a few seconds' field is
/// still translucent everywhere and places no splats (the demo ball's
/// `instant` field at 47 steps did not, on a loaded 2-core machine).
pub const SPLATS_FIELD_MIN_STEPS: u64 = 200;

/// `--model splats`: the field `auto` chooses, trained for
/// [`SPLATS_FIELD_SHARE`] of `--seconds` and saved beside `--out`, then
/// baked into splats for the rest.
fn train_splats(a: &TrainArgs, ds: &Dataset, threads: usize) -> anyhow::Result<()> {
    anyhow::ensure!(a.resume.is_none(), "--model {}: splats are not resumed; train them again", a.model);
    let Some(total) = a.seconds else {
        anyhow::bail!(
            "--model {} trains by time: give --seconds (a third trains the field the splats start from, the rest \
             the splats)",
            a.model
        )
    };
    anyhow::ensure!(!a.no_skip, "--no-skip applies to the nerf model only");
    let preset = ModelConfig::preset(&a.model).expect("checked by the caller");
    let ModelConfig::Splats(splats) = super::setup::apply_sets(preset, &a.set)? else {
        unreachable!("a kind that does not train on rays is splats")
    };
    let (kind, choice) = resolve_model(AUTO, ds)?;
    let field_out = a.out.with_extension("field.ckpt");
    let field_seconds = total * SPLATS_FIELD_SHARE;
    eprintln!(
        "splats: the field '{kind}' first, {field_seconds:.0} s (saved to {}), then the splats, {:.0} s",
        field_out.display(),
        total - field_seconds
    );
    if let Some(c) = &choice {
        eprintln!("model '{}' (auto): {}", c.preset, c.reason);
    }
    let budget = Budget { steps: None, seconds: Some(field_seconds) };
    let (config, model, adam) = new_model_and_adam(&kind, ds.scene(), a.seed, true, a.lr, &[])?;
    // The checkpoint holds the kind (`capture`), not the preset (`capture-360`).
    let field_kind = config.kind().to_string();
    let train = a.transients.apply(
        config.kind(),
        TrainConfig { model_choice: choice, ..config.train_config(a.seed, a.batch_rays, budget) },
    )?;
    anyhow::ensure!(
        a.transient_masks.is_none() || train.drop_transients,
        "--transient-masks needs a capture field, which finds transients (this one is {field_kind})"
    );
    let config = SessionConfig { train, out: field_out, checkpoint_every: a.checkpoint_every, held_out: None };
    let mut session = Session::new(Start::Fresh { model, adam }, config.clone(), ds)?;
    describe(a, &session, ds, threads);
    let cancel = cancel_on_ctrl_c()?;
    field_run(&mut session, budget, &cancel)?;
    let made = session.trainer().state.step;
    if made < SPLATS_FIELD_MIN_STEPS {
        // A machine too slow for the budget: a younger field places nothing.
        eprintln!(
            "splats: the field made {made} steps in {field_seconds:.0} s; training it on to {SPLATS_FIELD_MIN_STEPS} \
             steps before placing the splats"
        );
        let budget = Budget { steps: Some(SPLATS_FIELD_MIN_STEPS), seconds: None };
        let config = SessionConfig { train: TrainConfig { budget, ..config.train }, ..config };
        let from = Start::Resume { from: config.out.clone(), kind: Some(field_kind) };
        session = Session::new(from, config, ds)?;
        field_run(&mut session, budget, &cancel)?;
    }
    let bake_seconds = total - field_seconds;
    let trainer = session.trainer();
    let settings = BakeSettings {
        budget: Budget { seconds: Some(bake_seconds), steps: None },
        splats,
        seed: a.seed,
        ..Default::default()
    };
    let (model, adam, steps, elapsed) =
        super::splats::bake_with_lines(&*trainer.model, ds, &settings, trainer.transients.as_ref(), &cancel)
            .with_context(|| {
                format!("splats from the field trained for {field_seconds:.0} s (more --seconds gives a better one)")
            })?;
    let budget = Budget { steps: None, seconds: Some(total) };
    super::splats::save_baked(&a.out, &model, &adam, a.seed, budget, steps, elapsed)?;
    println!("splats         {} Gaussians, {steps} steps in {elapsed:.1} s", model.layout().n);
    println!("model          {}", a.out.display());
    if let Some(maps) = &trainer.transients {
        println!("transients     {} (the field's)", maps.report().summary());
        if let Some(dir) = &a.transient_masks {
            write_transient_masks(maps, dir)?;
        }
    }
    Ok(())
}

/// Trains the field of `train --model splats` on `session` to `budget`.
fn field_run(session: &mut Session<'_>, budget: Budget, cancel: &AtomicBool) -> anyhow::Result<()> {
    match train_with_bar(session, budget, cancel)? {
        Stop::Budget | Stop::TargetReached { .. } => Ok(()),
        Stop::Cancelled | Stop::Aborted => anyhow::bail!("interrupted while training the field; no splats were made"),
        stop @ Stop::Diverged { .. } => anyhow::bail!("{stop}; no splats were made"),
    }
}

/// A flag that Ctrl-C sets: training then stops (and saves) at its next step.
fn cancel_on_ctrl_c() -> anyhow::Result<Arc<AtomicBool>> {
    let cancel = Arc::new(AtomicBool::new(false));
    let c = cancel.clone();
    ctrlc::set_handler(move || c.store(true, Ordering::SeqCst)).context("installing the Ctrl-C handler")?;
    Ok(cancel)
}

/// The model kind to train and, when `auto` chose it, the choice: with
/// `--resume` and `auto` the checkpoint's kind (the run goes on as it
/// began), else `--model` resolved for the dataset.
fn chosen_model(a: &TrainArgs, ds: &Dataset) -> anyhow::Result<(String, Option<ModelChoice>)> {
    match &a.resume {
        Some(p) if a.model == AUTO => {
            let c = Checkpoint::load(p).with_context(|| format!("reading {}", p.display()))?;
            Ok((c.kind, None))
        }
        _ => resolve_model(&a.model, ds),
    }
}

/// A session saving to `--out`: resumed from `--resume`, else on a fresh
/// model of `kind`; `choice` is recorded in its checkpoints.
fn open_session<'a>(
    a: &TrainArgs,
    kind: &str,
    choice: Option<ModelChoice>,
    budget: Budget,
    ds: &'a Dataset,
) -> anyhow::Result<Session<'a>> {
    let config = model_config(kind, !a.no_skip, &a.set)?;
    let train = a.transients.apply(
        config.kind(),
        TrainConfig { model_choice: choice, ..config.train_config(a.seed, a.batch_rays, budget) },
    )?;
    anyhow::ensure!(
        a.transient_masks.is_none() || train.drop_transients,
        "--transient-masks needs a capture model, which finds transients (this one is {})",
        config.kind()
    );
    let start = match &a.resume {
        Some(p) => Start::Resume { from: p.clone(), kind: Some(config.kind().to_string()) },
        None => {
            let (_, model, adam) = new_model_and_adam(kind, ds.scene(), a.seed, !a.no_skip, a.lr, &a.set)?;
            Start::Fresh { model, adam }
        }
    };
    let config = SessionConfig { train, out: a.out.clone(), checkpoint_every: a.checkpoint_every, held_out: None };
    Ok(Session::new(start, config, ds)?)
}

/// What is about to train, and the estimate of its peak memory.
fn describe(a: &TrainArgs, session: &Session<'_>, ds: &Dataset, threads: usize) {
    let model = &*session.trainer().model;
    eprintln!(
        "training '{}' on {} ({} views, {}x{}), {} parameters, {} threads",
        model.kind(),
        a.data.display(),
        ds.train.len(),
        ds.frames[ds.train[0]].camera.width,
        ds.frames[ds.train[0]].camera.height,
        model.params().len(),
        threads
    );
    if let Some(m) = describe_masks(ds) {
        eprintln!("{m}");
    }
    if let Some(note) = model.log_note() {
        eprintln!("{note}");
    }
    if let Some(c) = ModelConfig::of_model(model) {
        let e = estimate_training(&c, DataSize::of(ds), threads);
        eprintln!("estimated peak memory {} ({})", mib(e.memory_bytes), e.describe());
    }
}

/// What the masks do in this run, when masks are in effect.
fn describe_masks(ds: &Dataset) -> Option<String> {
    let from = ds.mask_folder_name().unwrap_or_else(|| "the alpha channel".into());
    let train = || ds.train.iter().filter_map(|&i| ds.frames[i].mask.as_ref());
    let (inside, all) =
        train().fold((0usize, 0usize), |(a, b), m| (a + m.iter().filter(|&&v| v >= MASK_INSIDE).count(), b + m.len()));
    let share = 100.0 * inside as f64 / all.max(1) as f64;
    let what = match ds.masks {
        MaskUse::Off | MaskUse::Auto => return None,
        MaskUse::Score => "every pixel is trained on; eval and bench also score inside the masks".to_string(),
        MaskUse::Ignore => "training draws only from the pixels inside the masks".to_string(),
        MaskUse::Composite => "the outside is transparent (the mask is the images' alpha)".to_string(),
    };
    Some(format!("masks from {from} ({share:.1}% of the training pixels inside): {}: {what}", ds.masks))
}

/// Runs the session under a progress bar: by steps, or by tenths of a
/// second when the budget is only a time.
fn train_with_bar(session: &mut Session<'_>, budget: Budget, cancel: &AtomicBool) -> anyhow::Result<Stop> {
    let bar = match budget.steps {
        Some(n) if budget.seconds.is_none() => ProgressBar::new(n),
        _ => ProgressBar::new((budget.seconds.unwrap_or(0.0) * 10.0) as u64),
    };
    bar.set_style(ProgressStyle::with_template("{bar:30} {msg}").unwrap_or_else(|_| ProgressStyle::default_bar()));
    let by_time = budget.seconds.is_some() && budget.steps.is_none();
    let stop = session.run(cancel, |event| {
        let Event::Step { progress: p, .. } = event else { return true };
        bar.set_position(if by_time { (p.elapsed * 10.0) as u64 } else { p.step });
        if p.step % 5 == 0 || p.step < 5 {
            bar.set_message(format!(
                "step {} loss {:.5} train PSNR {:.2} dB elapsed {} ETA {}",
                p.step,
                p.loss,
                p.train_psnr,
                fmt_secs(p.elapsed),
                p.eta.map_or("?".into(), fmt_secs)
            ));
        }
        true
    });
    bar.finish_and_clear();
    Ok(stop?)
}

/// What this run did: its steps, speed and training PSNR (and, for a
/// capture model that refines its cameras, how far they moved).
fn summary(session: &Session<'_>, wall: Instant, out: &Path) {
    let (s, start) = (&session.trainer().state, session.started());
    let secs = (s.elapsed - start.elapsed).max(1e-9);
    let rays = s.rays - start.rays;
    let samples = s.samples - start.samples;
    println!("steps          {}", s.step - start.step);
    println!("training time  {:.1} s (wall {:.1} s)", secs, wall.elapsed().as_secs_f64());
    println!("rays/s         {:.1}", rays as f64 / secs);
    println!("samples/s      {:.0}", samples as f64 / secs);
    println!("samples/ray    {:.1}", samples as f64 / rays.max(1) as f64);
    let proposal = s.proposal_samples - start.proposal_samples;
    if proposal > 0 {
        println!("proposal/ray   {:.1}", proposal as f64 / rays.max(1) as f64);
    }
    println!("train PSNR     {:.2} dB", session.trainer().progress(f64::NAN).train_psnr);
    if s.diverged_steps > 0 {
        println!("skipped steps  {} (non-finite loss or gradient)", s.diverged_steps);
    }
    if let Some(peak) = peak_memory() {
        println!("peak memory    {}", mib(peak));
    }
    if let Some(report) = session.trainer().model.poses().and_then(|p| p.report()) {
        println!("poses          {report}");
    }
    if let Some(maps) = &session.trainer().transients {
        println!("transients     {}", maps.report().summary());
    }
    println!("model          {}", out.display());
}
