//! `radiance bench`: quality against training time. One training run per
//! model; at each time budget training pauses (the trainer does not count
//! the pause as training time), the first test views are rendered and scored
//! the way `eval` scores them, and training goes on.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use serde::{Deserialize, Serialize};

use super::eval::score;
use super::setup::{DEFAULT_BATCH_RAYS, MODEL_KINDS, new_model_and_adam};
use super::{Common, MaskArgs};
use crate::engine::dataset::{Dataset, LoadOptions, MaskUse, Split};
use crate::engine::geometry::scene::Scene;
use crate::engine::io::fsio;
use crate::engine::render::render_heldout_view;
use crate::engine::train::trainer::{Budget, Progress, StopReason, TrainState, Trainer};
use crate::system::{peak_memory, reset_peak_memory};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Dataset folder (its test split is scored).
    #[arg(long)]
    pub data: PathBuf,
    /// Models to benchmark, comma-separated: `instant`, `nerf`.
    #[arg(long, value_delimiter = ',', default_value = "instant,nerf")]
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
    #[command(flatten)]
    pub masks: MaskArgs,
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
    /// Mean over the scored test views, on the 8-bit renders.
    pub psnr: f64,
    pub ssim: f64,
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
    /// Peak resident memory (VmHWM) in MiB since this model's run started;
    /// `None` where /proc/self/status is unavailable.
    pub peak_memory_mib: Option<f64>,
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
    pub rows: Vec<BenchRow>,
}

const HEADER: &str = "model    budget s  train s    steps          rays        samples  smp/ray  skip/ray  PSNR dB    \
                      SSIM  ms/view  peak MiB";

/// The header's columns from PSNR on, with the scores inside the masks.
const MASKED_TAIL: (&str, &str) =
    ("PSNR dB    SSIM  ms/view  peak MiB", "PSNR dB    SSIM  mask dB  mask SSIM  ms/view  peak MiB");

/// The table's header, with the columns inside the masks when `masked`.
fn header(masked: bool) -> String {
    if masked { HEADER.replace(MASKED_TAIL.0, MASKED_TAIL.1) } else { HEADER.to_string() }
}

fn format_row(r: &BenchRow, masked: bool) -> String {
    let mem = r.peak_memory_mib.map_or("n/a".to_string(), |m| format!("{m:.0}"));
    let mask = if masked {
        let p = r.psnr_mask.map_or("-".into(), |p| format!("{p:.2}"));
        let s = r.ssim_mask.map_or("-".into(), |s| format!("{s:.4}"));
        format!(" {p:>8} {s:>10}")
    } else {
        String::new()
    };
    format!(
        "{:<8} {:>8} {:>8.1} {:>8} {:>13} {:>14} {:>8.1} {:>9.1} {:>7.2} {:>7.4}{mask} {:>8.0} {:>9}",
        r.model,
        format!("{}", r.budget_seconds),
        r.train_seconds,
        r.steps,
        r.rays,
        r.samples,
        r.samples_per_ray,
        r.skipped_per_ray,
        r.psnr,
        r.ssim,
        r.render_ms,
        mem
    )
}

/// Renders and scores the test views with the trainer's current model.
fn measure(
    t: &Trainer<'_>,
    p: &Progress,
    ds: &Dataset,
    views: &[usize],
    kind: &str,
    budget: f64,
) -> anyhow::Result<BenchRow> {
    let (mut sum_p, mut sum_s, mut secs) = (0.0, 0.0, 0.0);
    let (mut mask_p, mut mask_s) = (Vec::new(), Vec::new());
    let (mut rays, mut samples) = (0u64, 0u64);
    for &i in views {
        let f = &ds.frames[i];
        let t0 = Instant::now();
        let v = render_heldout_view(&*t.model, &f.camera, ds.background);
        secs += t0.elapsed().as_secs_f64();
        rays += v.stats.rays;
        samples += v.stats.samples;
        let sc = score(&v, f, ds.background)?;
        sum_p += sc.psnr;
        sum_s += sc.ssim;
        mask_p.extend(sc.psnr_mask);
        mask_s.extend(sc.ssim_mask);
    }
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let n = views.len() as f64;
    let per_ray = |x: u64| x as f64 / p.rays.max(1) as f64;
    Ok(BenchRow {
        model: kind.to_string(),
        budget_seconds: budget,
        train_seconds: p.elapsed,
        steps: p.step,
        rays: p.rays,
        samples: p.samples,
        samples_per_ray: per_ray(p.samples),
        skipped_per_ray: per_ray(p.skipped),
        psnr: sum_p / n,
        ssim: sum_s / n,
        psnr_mask: mean(&mask_p),
        ssim_mask: mean(&mask_s),
        render_ms: secs / n * 1000.0,
        render_samples_per_ray: samples as f64 / rays.max(1) as f64,
        peak_memory_mib: peak_memory().map(|b| b as f64 / (1024.0 * 1024.0)),
    })
}

fn write_json(path: &Path, report: &BenchReport) -> anyhow::Result<()> {
    let mut bytes = serde_json::to_vec_pretty(report)?;
    bytes.push(b'\n');
    fsio::write_atomic(path, &bytes).with_context(|| format!("writing {}", path.display()))
}

pub fn run(a: BenchArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    let mut budgets = a.budgets.clone();
    anyhow::ensure!(!budgets.is_empty(), "--budgets needs at least one number of seconds");
    anyhow::ensure!(budgets.iter().all(|b| b.is_finite() && *b > 0.0), "--budgets must be positive numbers of seconds");
    budgets.sort_by(f64::total_cmp);
    budgets.dedup();
    anyhow::ensure!(!a.model.is_empty(), "--model needs at least one model");
    for m in &a.model {
        anyhow::ensure!(
            MODEL_KINDS.contains(&m.as_str()),
            "unknown model '{m}' (available: {})",
            MODEL_KINDS.join(", ")
        );
    }
    anyhow::ensure!(a.test_views > 0, "--test-views must be at least 1");

    let opts = LoadOptions { splits: vec![Split::Train, Split::Test], background: [1.0; 3], masks: a.masks.masks };
    let ds = Dataset::load(&a.data, &opts).with_context(|| format!("loading {}", a.data.display()))?;
    anyhow::ensure!(!ds.train.is_empty(), "{}: the dataset has no training views", a.data.display());
    anyhow::ensure!(!ds.test.is_empty(), "{}: the dataset has no test views", a.data.display());
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    let views: Vec<usize> = ds.test.iter().copied().take(a.test_views).collect();

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
        test_views: views.len(),
        rows: Vec::new(),
    };
    let mut failure: Option<anyhow::Error> = None;
    println!("{}", header(ds.masks != MaskUse::Off));
    for kind in &a.model {
        let run = Run { args: &a, ds: &ds, views: &views, budgets: &budgets, threads, cancel: &cancel };
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
}

impl Run<'_> {
    /// Trains model `kind` once, scoring it each time the training clock
    /// passes a budget (scoring is not training time); rows go to stdout
    /// and `report` (and its JSON file after each row).
    fn model(&self, kind: &str, report: &mut BenchReport) -> anyhow::Result<()> {
        let (a, ds, budgets) = (self.args, self.ds, self.budgets);
        reset_peak_memory();
        let (cfg, model, adam) = new_model_and_adam(kind, Scene::from_dataset(ds), a.seed, true, a.lr, &a.set)?;
        let budget = Budget { steps: None, seconds: Some(*budgets.last().unwrap_or(&0.0)) };
        let config = cfg.train_config(a.seed, DEFAULT_BATCH_RAYS, budget);
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
            let row = match measure(t, p, ds, self.views, kind, budgets[next]) {
                Ok(r) => r,
                Err(e) => {
                    error = Some(e);
                    return false;
                }
            };
            // A step that crosses several budgets scores once for all of them.
            while next < budgets.len() && p.elapsed >= budgets[next] {
                let r = BenchRow { budget_seconds: budgets[next], ..row.clone() };
                println!("{}", format_row(&r, ds.masks != MaskUse::Off));
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

mod plot {
    //! The PSNR-against-training-time chart, drawn with plotters into a
    //! buffer, encoded as PNG and written atomically.

    use std::path::Path;
    use std::sync::Once;

    use plotters::coord::combinators::BindKeyPoints;
    use plotters::prelude::*;
    use plotters::style::{FontStyle, register_font};

    use super::BenchRow;
    use crate::engine::io::fsio;
    use crate::media::png;

    const WIDTH: u32 = 800;
    const HEIGHT: u32 = 500;

    /// Plotters draws text with fonts registered at run time (no system
    /// fonts): DejaVu Sans, embedded in the binary.
    fn register_fonts() {
        static ONCE: Once = Once::new();
        ONCE.call_once(|| {
            // The embedded font is valid; a failure would only lose the labels.
            let _ = register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
        });
    }

    /// Ticks at 1, 2 and 5 times the powers of ten in `[lo, hi]`.
    fn ticks(lo: f64, hi: f64) -> Vec<f64> {
        let mut out = Vec::new();
        let mut decade = 10f64.powf(lo.log10().floor());
        while decade <= hi && out.len() < 64 {
            for m in [1.0, 2.0, 5.0] {
                // Rounded so that labels read 0.2, not 0.20000000000000001.
                let t = format!("{:.6}", m * decade).parse().unwrap_or(m * decade);
                if (lo..=hi).contains(&t) {
                    out.push(t);
                }
            }
            decade *= 10.0;
        }
        out
    }

    pub fn psnr_vs_time(path: &Path, rows: &[BenchRow]) -> anyhow::Result<()> {
        register_fonts();
        let mut models: Vec<&str> = Vec::new();
        for r in rows {
            if !models.contains(&r.model.as_str()) {
                models.push(&r.model);
            }
        }
        let pts = |m: &str| -> Vec<(f64, f64)> {
            rows.iter()
                .filter(|r| r.model == m && r.psnr.is_finite() && r.train_seconds > 0.0)
                .map(|r| (r.train_seconds, r.psnr))
                .collect()
        };
        let all: Vec<(f64, f64)> = models.iter().flat_map(|m| pts(m)).collect();
        let (mut x0, mut x1) = all.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| (a.min(p.0), b.max(p.0)));
        let (mut y0, mut y1) =
            all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.1), b.max(p.1)));
        if all.is_empty() {
            (x0, x1, y0, y1) = (1.0, 10.0, 0.0, 40.0);
        }
        // Some room around the data; a decade at least on the x axis.
        (x0, x1) = (x0 / 1.2, (x1 * 1.2).max(x0 * 10.0));
        (y0, y1) = ((y0 - 1.0).floor(), (y1 + 1.0).ceil());

        let mut buf = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
            root.fill(&WHITE)?;
            let mut chart = ChartBuilder::on(&root)
                .caption("Test PSNR against training time", ("sans-serif", 22))
                .margin(15)
                .x_label_area_size(45)
                .y_label_area_size(55)
                .build_cartesian_2d((x0..x1).log_scale().with_key_points(ticks(x0, x1)), y0..y1)?;
            chart
                .configure_mesh()
                .max_light_lines(0)
                .x_label_formatter(&|x| format!("{x}"))
                .y_label_formatter(&|y| format!("{y:.0}"))
                .x_desc("training time (s, log scale)")
                .y_desc("test PSNR (dB)")
                .label_style(("sans-serif", 14))
                .draw()?;
            let colours =
                [RGBColor(31, 119, 180), RGBColor(214, 39, 40), RGBColor(44, 160, 44), RGBColor(148, 103, 189)];
            for (k, m) in models.iter().enumerate() {
                let c = colours[k % colours.len()];
                let p = pts(m);
                chart
                    .draw_series(LineSeries::new(p.clone(), c.stroke_width(2)))?
                    .label(*m)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
                chart.draw_series(p.into_iter().map(|xy| Circle::new(xy, 4, c.filled())))?;
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::LowerRight)
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .label_font(("sans-serif", 14))
                .draw()?;
            root.present()?;
        }
        let bytes = png::encode_rgb(WIDTH, HEIGHT, &buf)?;
        fsio::write_atomic(path, &bytes)?;
        Ok(())
    }
}
