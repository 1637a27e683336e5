//! `radiance bench`: quality against training time. One training run per
//! model; at each time budget training pauses (the trainer does not count
//! the pause as training time), the first test views are rendered and scored
//! the way `eval` scores them, and training goes on.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::Args;
use serde::{Deserialize, Serialize};

use super::eval::{FitArgs, Scored, appearance_fit, render_and_score};
use super::setup::{DEFAULT_BATCH_RAYS, check_model_name, new_model_and_adam, resolve_model};
use super::{AppearanceArgs, Common, MaskArgs, TransientArgs};
use crate::engine::front::{
    Budget, CAPTURE_KIND, Dataset, FoundMasks, LoadOptions, MaskUse, Model, ModelChoice, ModelConfig, Pasted, Progress,
    Split, StopReason, TrainState, Trainer, write_atomic,
};
use crate::system::{peak_memory, reset_peak_memory};
pub use occluded::OccludedPhoto;
use occluded::{occlude_photos, occluders};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Dataset folder (its test split is scored).
    #[arg(long)]
    pub data: PathBuf,
    /// Models to benchmark, comma-separated: `auto` (the model `radiance
    /// train` would choose for the dataset; its rows are labelled with it),
    /// `instant`, `nerf`, `capture`, or another preset (`capture-360`, the
    /// `-tiny` ones).
    #[arg(long, value_delimiter = ',', default_value = "auto")]
    pub model: Vec<String>,
    /// Seconds of training at which to score, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "10,30,60,120,300")]
    pub budgets: Vec<f64>,
    /// Score the first N test views.
    #[arg(long, default_value_t = 25)]
    pub test_views: usize,
    /// Random seed of every training run.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Initial learning rate, instead of each model's default.
    #[arg(long)]
    pub lr: Option<f32>,
    /// Override a setting of the models' presets (`KEY=VALUE`, as for
    /// `radiance train --set`; repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Also write the rows as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also draw test PSNR against training time (log scale) to this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Also bake each model, after its last budget, into splats for this
    /// many seconds and score them on the same views (a `splats` row: its
    /// seconds and steps are the bake's).
    #[arg(long)]
    pub bake: Option<f64>,
    /// Paste occluders into this share of the training photos (0 to 1),
    /// leaving the scored views clean: what a passer-by does to a capture.
    #[arg(long, value_name = "SHARE")]
    pub occlude: Option<f32>,
    /// Each occluder's area as a share of its photo: LEAST,MOST (one
    /// number: that area).
    #[arg(long, value_delimiter = ',', default_values_t = [0.05, 0.2], requires = "occlude")]
    pub occluder_area: Vec<f32>,
    /// Occluders in each occluded photo: LEAST,MOST (one number: that
    /// many).
    #[arg(long, value_delimiter = ',', default_values_t = [1, 2], requires = "occlude")]
    pub occluders_per_photo: Vec<u32>,
    /// A folder of cut-outs (images with an alpha matte) to paste instead
    /// of generated shapes.
    #[arg(long, requires = "occlude")]
    pub occluder_cutouts: Option<PathBuf>,
    /// Write what was scored into this folder, to look at: each scored
    /// view's render (MODEL_STEP_NAME.png: the model's kind, its steps, the
    /// view's name) and, with --occlude, each occluded training photo
    /// (NAME.occluded.png) with, where training dropped transients, the mask training
    /// found for it (NAME.found.png: 255 trained on, 0 dropped).
    #[arg(long, value_name = "DIR")]
    pub save: Option<PathBuf>,
    #[command(flatten)]
    pub masks: MaskArgs,
    #[command(flatten)]
    pub transients: TransientArgs,
    #[command(flatten)]
    pub appearance: AppearanceArgs,
    #[command(flatten)]
    pub fit: FitArgs,
    #[command(flatten)]
    pub common: Common,
}

/// One measurement: a model after a training budget.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BenchRow {
    pub model: String,
    /// The budget asked for, in seconds of training.
    pub budget_seconds: f64,
    /// Seconds of training actually done (the step that crossed the budget
    /// included; scoring excluded).
    pub train_seconds: f64,
    pub steps: u64,
    /// Training rays and network samples processed so far.
    pub rays: u64,
    pub samples: u64,
    /// Training samples per ray marched, and skipped (samples a dense
    /// marcher would have taken).
    pub samples_per_ray: f64,
    pub skipped_per_ray: f64,
    /// Proposal-network evaluations in training so far, and per training
    /// ray (the capture model's sampling; 0 for the others).
    #[serde(default)]
    pub proposal_samples: u64,
    #[serde(default)]
    pub proposal_samples_per_ray: f64,
    /// Mean over the scored test views, on the 8-bit renders (a capture
    /// model's views with the nearest training camera's appearance, or
    /// `--appearance`).
    pub psnr: f64,
    pub ssim: f64,
    /// For a model with per-image appearance (capture), the mean PSNR of
    /// the same views with the mean appearance.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_mean: Option<f64>,
    /// With `--fit-steps` above 0, for a model with per-image appearance:
    /// the mean PSNR of the views' right halves with an appearance fitted
    /// on their left halves (NeRF in the Wild's protocol).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_fit: Option<f64>,
    /// With it, the mean PSNR of the whole views, each half rendered with
    /// the appearance fitted on the other half (`cross dB`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_fit_whole: Option<f64>,
    /// The same inside the views' masks, when masks are in effect (means
    /// over the views with pixels inside).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_mask: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ssim_mask: Option<f64>,
    /// Mean milliseconds to render one test view.
    pub render_ms: f64,
    /// Network samples per ray when rendering the test views.
    pub render_samples_per_ray: f64,
    /// Proposal-network evaluations per ray when rendering them.
    #[serde(default)]
    pub render_proposal_samples_per_ray: f64,
    /// Peak resident memory (VmHWM) in MiB since this model's run started;
    /// `None` where /proc/self/status is unavailable.
    pub peak_memory_mib: Option<f64>,
    /// A baked row's Gaussians (its `.splat` is 32 bytes each).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussians: Option<usize>,
    /// A baked row's file: the `.ply`'s bytes (`splats`, `cleaned`) or the
    /// `.spz`'s (`spz`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bytes: Option<u64>,
}

/// What `--json` writes.
#[derive(Debug, Serialize, Deserialize)]
pub struct BenchReport {
    pub data: String,
    pub threads: usize,
    pub seed: u64,
    pub test_views: usize,
    /// `--lr`, when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lr: Option<f32>,
    /// `--set` overrides, as given.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub set: Vec<String>,
    /// What the masks did, when masks were in effect.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub masks: Option<MaskUse>,
    /// What `--model auto` chose, and why, when it was asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_choice: Option<ModelChoice>,
    /// With `--occlude`: each occluded photo and the share of it covered.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub occluded: Vec<OccludedPhoto>,
    /// With robust training: the transient masks found, against those
    /// pasted (none pasted: how much of the static scene was dropped).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub found: Option<FoundMasks>,
    pub rows: Vec<BenchRow>,
}

const HEADER: &str = "model    budget s  train s    steps          rays        samples  smp/ray prop/ray  skip/ray  PSNR dB    \
                      SSIM  ms/view  peak MiB";

/// The header's columns from PSNR on, with the scores inside the masks.
const MASKED_TAIL: (&str, &str) =
    ("PSNR dB    SSIM  ms/view  peak MiB", "PSNR dB    SSIM  mask dB  mask SSIM  ms/view  peak MiB");

/// The PSNR column, and with the mean appearance's and the fitted one's
/// beside it.
const MEAN_COLUMN: (&str, &str) = ("PSNR dB ", "PSNR dB  mean dB   fit dB cross dB ");

/// The table's header, with the columns inside the masks when `masked`,
/// and the mean and fitted appearances' PSNR when `mean` (a capture model
/// is benched).
fn header(masked: bool, mean: bool) -> String {
    let h = if masked { HEADER.replace(MASKED_TAIL.0, MASKED_TAIL.1) } else { HEADER.to_string() };
    if mean { h.replacen(MEAN_COLUMN.0, MEAN_COLUMN.1, 1) } else { h }
}

fn format_row(r: &BenchRow, masked: bool, mean: bool) -> String {
    let psnr_mean = match mean {
        true => {
            let col = |v: Option<f64>| format!(" {:>8}", v.map_or("-".into(), |p| format!("{p:.2}")));
            col(r.psnr_mean) + &col(r.psnr_fit) + &col(r.psnr_fit_whole)
        }
        false => String::new(),
    };
    let mem = r.peak_memory_mib.map_or("n/a".to_string(), |m| format!("{m:.0}"));
    let mask = if masked {
        let p = r.psnr_mask.map_or("-".into(), |p| format!("{p:.2}"));
        let s = r.ssim_mask.map_or("-".into(), |s| format!("{s:.4}"));
        format!(" {p:>8} {s:>10}")
    } else {
        String::new()
    };
    format!(
        "{:<8} {:>8} {:>8.1} {:>8} {:>13} {:>14} {:>8.1} {:>8.1} {:>9.1} {:>7.2}{psnr_mean} {:>7.4}{mask} {:>8.0} {:>9}",
        r.model,
        format!("{}", r.budget_seconds),
        r.train_seconds,
        r.steps,
        r.rays,
        r.samples,
        r.samples_per_ray,
        r.proposal_samples_per_ray,
        r.skipped_per_ray,
        r.psnr,
        r.ssim,
        r.render_ms,
        mem
    )
}

/// The test views' scores summed ([`score_views`]).
#[derive(Default)]
pub(super) struct ViewScores {
    psnr: f64,
    ssim: f64,
    secs: f64,
    mask_p: Vec<f64>,
    mask_s: Vec<f64>,
    mean_p: Vec<f64>,
    fit_p: Vec<f64>,
    fit_whole: Vec<f64>,
    rays: u64,
    samples: u64,
    proposal: u64,
}

/// Renders and scores the test views `views` with `model` (trained `step`
/// steps), as `eval` does (`render_and_score`).
pub(super) fn score_views(
    model: &dyn Model,
    step: u64,
    ds: &Dataset,
    views: &[usize],
    args: &BenchArgs,
) -> anyhow::Result<ViewScores> {
    let mut fit = appearance_fit(model, step, args.fit.fit_steps)?;
    let mut v = ViewScores::default();
    for &i in views {
        let f = &ds.frames[i];
        let Scored { view, secs, scores: sc, psnr_mean, fit: fitted } =
            render_and_score(model, f, ds.background, &args.appearance, fit.as_mut())?;
        if let Some(dir) = &args.save {
            occluded::save_rgb(&dir.join(format!("{}_{step}_{}.png", model.kind(), f.name)), &view)?;
        }
        v.secs += secs;
        v.rays += view.stats.rays;
        v.samples += view.stats.samples;
        v.proposal += view.stats.proposal_samples;
        v.psnr += sc.psnr;
        v.ssim += sc.ssim;
        v.mask_p.extend(sc.psnr_mask);
        v.mask_s.extend(sc.ssim_mask);
        v.mean_p.extend(psnr_mean);
        v.fit_p.extend(fitted.as_ref().map(|f| f.right_half));
        v.fit_whole.extend(fitted.map(|f| f.whole));
    }
    Ok(v)
}

/// A row of `v`'s scores over `n` views; the training columns are the
/// caller's.
pub(super) fn scored_row(model: &str, budget: f64, v: &ViewScores, n: usize) -> BenchRow {
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let n = n as f64;
    BenchRow {
        model: model.to_string(),
        budget_seconds: budget,
        train_seconds: 0.0,
        steps: 0,
        rays: 0,
        samples: 0,
        samples_per_ray: 0.0,
        skipped_per_ray: 0.0,
        proposal_samples: 0,
        proposal_samples_per_ray: 0.0,
        psnr: v.psnr / n,
        ssim: v.ssim / n,
        psnr_mean: mean(&v.mean_p),
        psnr_fit: mean(&v.fit_p),
        psnr_fit_whole: mean(&v.fit_whole),
        psnr_mask: mean(&v.mask_p),
        ssim_mask: mean(&v.mask_s),
        render_ms: v.secs / n * 1000.0,
        render_samples_per_ray: v.samples as f64 / v.rays.max(1) as f64,
        render_proposal_samples_per_ray: v.proposal as f64 / v.rays.max(1) as f64,
        peak_memory_mib: peak_memory().map(|b| b as f64 / (1024.0 * 1024.0)),
        gaussians: None,
        bytes: None,
    }
}

/// Renders and scores the test views with the trainer's current model.
fn measure(
    t: &Trainer<'_>,
    p: &Progress,
    ds: &Dataset,
    views: &[usize],
    kind: &str,
    args: &BenchArgs,
    budget: f64,
) -> anyhow::Result<BenchRow> {
    let v = score_views(&*t.model, p.step, ds, views, args)?;
    let per_ray = |x: u64| x as f64 / p.rays.max(1) as f64;
    Ok(BenchRow {
        train_seconds: p.elapsed,
        steps: p.step,
        rays: p.rays,
        samples: p.samples,
        samples_per_ray: per_ray(p.samples),
        skipped_per_ray: per_ray(p.skipped),
        proposal_samples: p.proposal_samples,
        proposal_samples_per_ray: per_ray(p.proposal_samples),
        ..scored_row(kind, budget, &v, views.len())
    })
}

/// The model column of a baked row.
pub(super) const SPLATS_LABEL: &str = "splats";

fn write_json(path: &Path, report: &BenchReport) -> anyhow::Result<()> {
    let mut bytes = serde_json::to_vec_pretty(report)?;
    bytes.push(b'\n');
    write_atomic(path, &bytes).with_context(|| format!("writing {}", path.display()))
}

/// The arguments checked before anything is loaded: the budgets, sorted
/// and without repeats.
fn checked_budgets(a: &BenchArgs) -> anyhow::Result<Vec<f64>> {
    let mut budgets = a.budgets.clone();
    anyhow::ensure!(!budgets.is_empty(), "--budgets needs at least one number of seconds");
    anyhow::ensure!(budgets.iter().all(|b| b.is_finite() && *b > 0.0), "--budgets must be positive numbers of seconds");
    budgets.sort_by(f64::total_cmp);
    budgets.dedup();
    anyhow::ensure!(!a.model.is_empty(), "--model needs at least one model");
    for m in &a.model {
        check_model_name(m)?;
    }
    anyhow::ensure!(a.test_views > 0, "--test-views must be at least 1");
    if let Some(b) = a.bake {
        anyhow::ensure!(b.is_finite() && b > 0.0, "--bake must be a positive number of seconds");
    }
    Ok(budgets)
}

pub fn run(a: BenchArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    let budgets = checked_budgets(&a)?;

    let occluders = a.occlude.map(|share| occluders(&a, share)).transpose()?;
    if let Some(dir) = &a.save {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }

    let opts = LoadOptions { splits: vec![Split::Train, Split::Test], background: [1.0; 3], masks: a.masks.masks };
    let mut ds = Dataset::load(&a.data, &opts).with_context(|| format!("loading {}", a.data.display()))?;
    anyhow::ensure!(!ds.train.is_empty(), "{}: the dataset has no training views", a.data.display());
    let (occluded, pasted) = match &occluders {
        Some(o) => occlude_photos(&mut ds, o)?,
        None => (Vec::new(), Vec::new()),
    };
    anyhow::ensure!(!ds.test.is_empty(), "{}: the dataset has no test views", a.data.display());
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    let views: Vec<usize> = ds.test.iter().copied().take(a.test_views).collect();
    let mut kinds = Vec::with_capacity(a.model.len());
    let mut model_choice = None;
    for m in &a.model {
        let (kind, choice) = resolve_model(m, &ds)?;
        if let Some(c) = choice {
            eprintln!("model '{}' (auto): {}", c.preset, c.reason);
            model_choice = Some(c);
        }
        kinds.push(kind);
    }

    let cancel = Arc::new(AtomicBool::new(false));
    {
        let c = cancel.clone();
        ctrlc::set_handler(move || c.store(true, Ordering::SeqCst)).context("installing the Ctrl-C handler")?;
    }
    let mut report = BenchReport {
        data: a.data.display().to_string(),
        threads,
        seed: a.seed,
        lr: a.lr,
        set: a.set.clone(),
        masks: (ds.masks != MaskUse::Off).then_some(ds.masks),
        model_choice,
        occluded,
        found: None,
        test_views: views.len(),
        rows: Vec::new(),
    };
    let mut failure: Option<anyhow::Error> = None;
    let with_mean = kinds.iter().any(|m| ModelConfig::preset(m).is_some_and(|c| c.kind() == CAPTURE_KIND));
    println!("{}", header(ds.masks != MaskUse::Off, with_mean));
    for kind in &kinds {
        let run = Run {
            args: &a,
            ds: &ds,
            views: &views,
            budgets: &budgets,
            threads,
            cancel: &cancel,
            with_mean,
            pasted: &pasted,
        };
        if let Err(e) = run.model(kind, &mut report) {
            failure = Some(e);
            break;
        }
    }
    if let Some(path) = &a.json {
        write_json(path, &report)?;
    }
    if let Some(path) = &a.plot {
        plot::psnr_vs_time(path, &report.rows).with_context(|| format!("drawing {}", path.display()))?;
    }
    match failure {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// One bench invocation's inputs.
struct Run<'a> {
    args: &'a BenchArgs,
    ds: &'a Dataset,
    views: &'a [usize],
    budgets: &'a [f64],
    threads: usize,
    cancel: &'a AtomicBool,
    /// Whether the table has the mean appearance's column (a capture model
    /// is benched, named or chosen by `auto`).
    with_mean: bool,
    /// The occluders `--occlude` pasted.
    pasted: &'a [Pasted],
}

impl Run<'_> {
    /// Trains model `kind` once, scoring it each time the training clock
    /// passes a budget (scoring is not training time); rows go to stdout
    /// and `report` (and its JSON file after each row).
    fn model(&self, kind: &str, report: &mut BenchReport) -> anyhow::Result<()> {
        let (a, ds, budgets) = (self.args, self.ds, self.budgets);
        reset_peak_memory();
        let (cfg, model, adam) = new_model_and_adam(kind, ds.scene(), a.seed, true, a.lr, &a.set)?;
        let budget = Budget { steps: None, seconds: Some(*budgets.last().unwrap_or(&0.0)) };
        let config = a.transients.apply(cfg.kind(), cfg.train_config(a.seed, DEFAULT_BATCH_RAYS, budget))?;
        eprintln!(
            "bench '{}' on {} ({} training views, {} test views scored), {} parameters, {} threads",
            kind,
            a.data.display(),
            ds.train.len(),
            self.views.len(),
            model.params().len(),
            self.threads
        );
        let mut trainer = Trainer::new(model, adam, config, TrainState::default(), ds);
        let mut next = 0;
        let mut error = None;
        let reason = trainer.run(self.cancel, |t, p| {
            if next >= budgets.len() || p.elapsed < budgets[next] {
                return true;
            }
            let row = match measure(t, p, ds, self.views, kind, a, budgets[next]) {
                Ok(r) => r,
                Err(e) => {
                    error = Some(e);
                    return false;
                }
            };
            // A step that crosses several budgets scores once for all of them.
            while next < budgets.len() && p.elapsed >= budgets[next] {
                let r = BenchRow { budget_seconds: budgets[next], ..row.clone() };
                println!("{}", format_row(&r, ds.masks != MaskUse::Off, self.with_mean));
                report.rows.push(r);
                next += 1;
            }
            if let Some(path) = &a.json
                && let Err(e) = write_json(path, report)
            {
                error = Some(e);
                return false;
            }
            true
        });
        if let Some(e) = error {
            return Err(e.context(format!("benchmarking '{kind}'")));
        }
        if let Some(dir) = &a.save {
            occluded::save_photos(dir, ds, self.pasted, trainer.transients.as_ref())?;
        }
        if let Some(f) = trainer.transients.as_ref().map(|t| t.score(ds, self.pasted)) {
            println!(
                "transient masks: {:.1}% of the pasted occluders' pixels, {:.2}% of the static pixels",
                100.0 * f.recall,
                100.0 * f.static_share
            );
            report.found = Some(f);
        }
        if let (Some(seconds), StopReason::Budget | StopReason::Callback) = (a.bake, &reason) {
            eprintln!("baking '{kind}' into splats for {seconds} s");
            let rows = baked::measure_bake(&*trainer.model, ds, self.views, a, seconds, trainer.transients.as_ref())
                .with_context(|| format!("baking '{kind}'"))?;
            for row in &rows {
                println!("{}", format_row(row, ds.masks != MaskUse::Off, self.with_mean));
            }
            baked::print_sizes(&rows);
            report.rows.extend(rows);
            if let Some(path) = &a.json {
                write_json(path, report)?;
            }
        }
        match reason {
            StopReason::Budget | StopReason::Callback => {}
            StopReason::Cancelled => anyhow::bail!("interrupted during '{kind}'"),
            StopReason::Diverged { .. } => {
                eprintln!("warning: '{kind}': {reason}; its remaining budgets are not scored");
            }
        }
        Ok(())
    }
}

mod baked;
mod occluded;
mod plot;

#[cfg(test)]
mod tests {
    use super::*;

    fn row(psnr_mean: Option<f64>) -> BenchRow {
        BenchRow {
            model: "capture".into(),
            budget_seconds: 10.0,
            train_seconds: 10.2,
            steps: 100,
            rays: 409_600,
            samples: 13_107_200,
            samples_per_ray: 32.0,
            skipped_per_ray: 1.5,
            proposal_samples: 9_830_400,
            proposal_samples_per_ray: 24.0,
            psnr: 27.104,
            ssim: 0.8123,
            psnr_mean,
            psnr_fit: psnr_mean.map(|p| p + 1.0),
            psnr_fit_whole: psnr_mean.map(|p| p + 0.5),
            psnr_mask: Some(29.5),
            ssim_mask: Some(0.9),
            render_ms: 1130.0,
            render_samples_per_ray: 30.0,
            render_proposal_samples_per_ray: 24.0,
            peak_memory_mib: Some(512.0),
            gaussians: None,
            bytes: None,
        }
    }

    /// The mean appearance's column sits under its header as the PSNR's
    /// does (the same offset), with or without the mask columns; without
    /// it the table is as before.
    #[test]
    fn the_mean_appearance_column_lines_up() {
        let end = |s: &str, word: &str| (s.find(word).map(|i| i + word.len()).unwrap()) as i64;
        for masked in [false, true] {
            let (plain_h, plain_r) = (header(masked, false), format_row(&row(Some(26.5)), masked, false));
            assert!(!plain_h.contains("mean dB") && !plain_r.contains("26.50"), "{plain_h}\n{plain_r}");
            let offset = end(&plain_h, "PSNR dB") - end(&plain_r, "27.10");
            let (h, r) = (header(masked, true), format_row(&row(Some(26.5)), masked, true));
            assert_eq!(end(&h, "PSNR dB") - end(&r, "27.10"), offset, "{h}\n{r}");
            assert_eq!(end(&h, "mean dB") - end(&r, "26.50"), offset, "{h}\n{r}");
            assert_eq!(end(&h, "fit dB") - end(&r, "27.50"), offset, "{h}\n{r}");
            assert_eq!(end(&h, "cross dB") - end(&r, "27.00"), offset, "{h}\n{r}");
            assert_eq!(end(&h, "SSIM") - end(&r, "0.8123"), end(&plain_h, "SSIM") - end(&plain_r, "0.8123"));
            assert_eq!(h.len() - r.len(), plain_h.len() - plain_r.len(), "{h}\n{r}");
            let r = format_row(&row(None), masked, true);
            assert_eq!(end(&h, "mean dB") - end(&r, "27.10") - 9, offset, "{h}\n{r}");
            assert_eq!(end(&h, "fit dB") - end(&r, "27.10") - 18, offset, "{h}\n{r}");
            assert_eq!(end(&h, "cross dB") - end(&r, "27.10") - 27, offset, "{h}\n{r}");
        }
        assert_eq!(header(false, false), HEADER);
    }

    /// `psnr_mean` is in the JSON of models that have it only.
    #[test]
    fn psnr_mean_is_written_when_there_is_one() {
        let with = serde_json::to_value(row(Some(26.5))).unwrap();
        assert_eq!(with["psnr_mean"], 26.5);
        let without = serde_json::to_value(row(None)).unwrap();
        assert!(without.get("psnr_mean").is_none(), "{without}");
        let back: BenchRow = serde_json::from_value(without).unwrap();
        assert_eq!(back.psnr_mean, None);
    }
}
