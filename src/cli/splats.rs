//! `radiance bake` (a trained model becomes Gaussian splats) and
//! `radiance export` (splats in the files other tools read).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::Common;
use crate::api::site;
use crate::engine::front::{
    Adam, BakeSettings, Budget, CleanupSettings, CropBox, DataSize, Dataset, LoadOptions, Model, ModelConfig,
    SplatsFormat as Format, SplatsModel, Split, TrainConfig, TrainState, TransientMaps, auto_crop_any, bake, cleanup,
    crop, estimate_bake, load_checkpoint, mib, save_checkpoint, splats_of, write_atomic, write_splats,
};
use crate::system::peak_memory;

#[derive(Args, Debug)]
pub struct BakeArgs {
    /// A trained instant, nerf or capture model's checkpoint.
    #[arg(long)]
    pub model: PathBuf,
    /// The dataset the model was trained on (its training photos are what
    /// the splats are optimised against).
    #[arg(long)]
    pub data: PathBuf,
    /// The splats' checkpoint to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Time budget in seconds (placing and optimising); 60 when neither
    /// this nor `--steps` is given.
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Optimisation steps (one photo each). Alone, the bake follows no
    /// clock, so it is reproducible; with `--seconds`, the first budget
    /// reached ends it.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Gaussians placed from the field within the photos' frames before
    /// optimising (default: 1500 for each training photo, at most
    /// 200,000); the margins past their edges add those no photo saw.
    #[arg(long)]
    pub initial: Option<usize>,
    /// Spherical-harmonic degree of the colours (0-3).
    #[arg(long, default_value_t = crate::engine::front::SplatsConfig::default().sh_degree)]
    pub sh_degree: u32,
    /// The most Gaussians.
    #[arg(long, default_value_t = crate::engine::front::SplatsConfig::default().max_gaussians)]
    pub max_gaussians: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub common: Common,
}

pub fn bake_cmd(a: BakeArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    let seconds = match (a.seconds, a.steps) {
        (None, None) => Some(60.0),
        (s, _) => s,
    };
    if let Some(s) = seconds {
        anyhow::ensure!(s.is_finite() && s > 0.0, "--seconds must be a positive number");
    }
    anyhow::ensure!(a.steps != Some(0), "--steps must be at least 1");
    let source = load_checkpoint(&a.model)?;
    let opts = LoadOptions { splits: vec![Split::Train], ..Default::default() };
    let ds = Dataset::load(&a.data, &opts).with_context(|| format!("loading {}", a.data.display()))?;
    let mut settings = BakeSettings {
        budget: Budget { seconds, steps: a.steps },
        initial: a.initial,
        seed: a.seed,
        ..Default::default()
    };
    settings.splats.sh_degree = a.sh_degree;
    settings.splats.max_gaussians = a.max_gaussians;
    let splats = ModelConfig::Splats(settings.splats.clone());
    splats.check().map_err(|e| anyhow::anyhow!("{e}"))?;
    eprintln!(
        "baking {} ({}) into splats on {threads} threads, {}",
        a.model.display(),
        source.model.kind(),
        match (seconds, a.steps) {
            (Some(s), None) => format!("{s} s"),
            (None, Some(n)) => format!("{n} steps"),
            (s, n) => format!("{} s or {} steps", s.unwrap_or_default(), n.unwrap_or_default()),
        }
    );
    if let Some(c) = ModelConfig::of_model(&*source.model) {
        let initial = settings.initial_for(ds.split(Split::Train).len());
        let e = estimate_bake(&c, &splats, initial, DataSize::of(&ds), threads);
        eprintln!("estimated peak memory {} ({})", mib(e.memory_bytes), e.describe());
    }
    if let Some(t) = &source.transients {
        eprintln!("the photos' transient masks from training stay out of the fit ({})", t.report().summary());
    }
    let no = AtomicBool::new(false);
    let (model, adam, steps, elapsed) =
        bake_with_lines(&*source.model, &ds, &settings, source.transients.as_ref(), &no)?;
    save_baked(&a.out, &model, &adam, a.seed, Budget { steps: a.steps, seconds }, steps, elapsed)?;
    eprintln!("wrote {}: {} Gaussians, {steps} steps in {elapsed:.1} s", a.out.display(), model.layout().n);
    if let Some(peak) = peak_memory() {
        println!("peak memory    {}", mib(peak));
    }
    Ok(())
}

/// Saves baked splats as a checkpoint: their optimiser, the seed and
/// budget they were baked with, and the steps made in the seconds taken.
pub fn save_baked(
    out: &Path,
    model: &SplatsModel,
    adam: &Adam,
    seed: u64,
    budget: Budget,
    steps: u64,
    elapsed: f64,
) -> anyhow::Result<()> {
    let train = TrainConfig { seed, budget, ..Default::default() };
    let state = TrainState { step: steps, elapsed, ..Default::default() };
    Ok(save_checkpoint(out, model, adam, &train, &state, None)?)
}

/// Bakes `source` into splats (the pixels in `dropped` left out), a line on
/// standard error every 5 s; the splats, their optimiser, the steps made
/// and the seconds taken.
pub fn bake_with_lines(
    source: &dyn Model,
    ds: &Dataset,
    settings: &BakeSettings,
    dropped: Option<&TransientMaps>,
    cancel: &AtomicBool,
) -> anyhow::Result<(SplatsModel, Adam, u64, f64)> {
    let started = Instant::now();
    let mut last = 0.0;
    let (model, adam, steps) = bake(source, ds, settings, dropped, cancel, |p| {
        if p.elapsed - last >= 5.0 {
            last = p.elapsed;
            eprintln!(
                "  {:5.1} s  step {:5}  {:7} Gaussians  {:.2} dB (training photos)",
                p.elapsed, p.step, p.gaussians, p.psnr
            );
        }
    })?;
    Ok((model, adam, steps, started.elapsed().as_secs_f64()))
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// A splats checkpoint written by `radiance bake`.
    #[arg(long)]
    pub model: PathBuf,
    /// `ply` (the 3DGS paper's layout), `splat` (antimatter15's 32 bytes a
    /// Gaussian), `spz` (Niantic's SPZ, version 3), `glb` (glTF 2.0 with
    /// `KHR_gaussian_splatting`) or `html` (a static web site showing the
    /// splats: a folder, or a zip when `--out` ends in `.zip`).
    #[arg(long, value_parser = parse_format)]
    pub format: ExportFormat,
    /// The file to write (`html`: the folder, or the `.zip`).
    #[arg(long)]
    pub out: PathBuf,
    /// The dataset the model was baked from: `html`'s opening view and
    /// `--crop auto`'s cameras.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Export only what is inside a box: `auto` (the box around what the
    /// training cameras all see, found from `--data`; printed as JSON) or
    /// a JSON file of one (`{"centre": [x, y, z], "axes": [[..], [..],
    /// [..]], "half": [hx, hy, hz]}`, world units, axes orthonormal rows).
    #[arg(long)]
    pub crop: Option<String>,
    #[command(flatten)]
    pub cleanup: CleanupArgs,
}

/// The floater cleanup every export applies first (`engine::models::splats::cleanup`).
#[derive(Args, Debug, Clone)]
pub struct CleanupArgs {
    /// Export every Gaussian: no floater cleanup.
    #[arg(long)]
    pub no_cleanup: bool,
    /// Remove Gaussians of a lower opacity (0 to 1; 1/255 draws nothing).
    #[arg(long, default_value_t = CleanupSettings::default().min_opacity)]
    pub min_opacity: f32,
    /// Remove a Gaussian whose `--neighbours`-th nearest is farther than
    /// this many times their reach (3 deviations each) together; 0: off.
    #[arg(long, default_value_t = CleanupSettings::default().isolation)]
    pub isolation: f32,
    /// The neighbour `--isolation` counts.
    #[arg(long, default_value_t = CleanupSettings::default().neighbours)]
    pub neighbours: usize,
    /// Remove a Gaussian outside the central 90% of centres whose reach is
    /// over this many radii of the central 99%; 0: off.
    #[arg(long, default_value_t = CleanupSettings::default().max_reach)]
    pub max_reach: f32,
}

impl CleanupArgs {
    pub fn settings(&self) -> anyhow::Result<CleanupSettings> {
        if self.no_cleanup {
            return Ok(CleanupSettings::OFF);
        }
        let s = CleanupSettings {
            min_opacity: self.min_opacity,
            isolation: self.isolation,
            neighbours: self.neighbours,
            max_reach: self.max_reach,
        };
        s.check().map_err(|(field, why)| anyhow::anyhow!("--{}: {why}", field.replace('_', "-")))?;
        Ok(s)
    }
}

/// What `export --format` takes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ExportFormat {
    File(Format),
    Html,
}

fn parse_format(s: &str) -> Result<ExportFormat, String> {
    match s {
        "html" => Ok(ExportFormat::Html),
        s => Format::parse(s)
            .map(ExportFormat::File)
            .ok_or_else(|| format!("unknown format '{s}' (known: ply, splat, spz, glb, html)")),
    }
}

pub fn export_cmd(a: ExportArgs) -> anyhow::Result<()> {
    let settings = a.cleanup.settings()?;
    let restored = load_checkpoint(&a.model)?;
    let Some(splats) = splats_of(&*restored.model) else {
        anyhow::bail!(
            "{} holds a '{}' model: export takes splats (make them with `radiance bake`)",
            a.model.display(),
            restored.model.kind()
        );
    };
    let (cleaned, removed) = cleanup(splats, &settings)?;
    eprintln!("cleanup: {removed}");
    // The dataset, read once where `--crop auto` or the site needs it.
    let needs_data = a.format == ExportFormat::Html || a.crop.as_deref() == Some("auto");
    let ds = match (&a.data, needs_data) {
        (Some(data), true) => {
            let opts = LoadOptions { splits: vec![Split::Train], ..Default::default() };
            Some(Dataset::load(data, &opts).with_context(|| format!("loading {}", data.display()))?)
        }
        _ => None,
    };
    let cropped = match &a.crop {
        Some(c) => {
            let b = crop_box(c, ds.as_ref(), &cleaned)?;
            let (kept, gone) = crop(&cleaned, &b)?;
            eprintln!("crop: {gone} Gaussians outside the box removed, {} kept", kept.layout().n);
            kept
        }
        None => cleaned,
    };
    let splats = &cropped;
    let format = match a.format {
        ExportFormat::File(f) => f,
        ExportFormat::Html => return export_site(&a, ds.as_ref(), splats),
    };
    let mut bytes = Vec::new();
    write_splats(splats, format, &mut bytes)?;
    write_atomic(&a.out, &bytes).with_context(|| format!("writing {}", a.out.display()))?;
    eprintln!("wrote {} ({} Gaussians, {} bytes)", a.out.display(), splats.layout().n, bytes.len());
    Ok(())
}

/// The box `--crop` names: `auto` (from `model`: a splats model's Gaussians,
/// another's views), or a JSON file.
pub(super) fn crop_box(arg: &str, ds: Option<&Dataset>, model: &dyn Model) -> anyhow::Result<CropBox> {
    let b = if arg == "auto" {
        let Some(ds) = ds else {
            anyhow::bail!("--crop auto needs --data DIR: the box is found from the training cameras");
        };
        let Some(b) = auto_crop_any(model, ds, &AtomicBool::new(false))? else {
            anyhow::bail!(
                "--crop auto: {} is not a capture taken around an object (its cameras face one way); give the box as a JSON file",
                ds.root.display()
            );
        };
        eprintln!("crop: {}", serde_json::to_string(&b)?);
        b
    } else {
        let text = std::fs::read_to_string(arg).with_context(|| format!("--crop {arg}: reading the box"))?;
        serde_json::from_str(&text)
            .with_context(|| format!("--crop {arg}: not a box ({{\"centre\", \"axes\", \"half\"}})"))?
    };
    b.check()?;
    Ok(b)
}

/// `export --format html`: the site of `api::site`, as a folder or a zip.
fn export_site(a: &ExportArgs, ds: Option<&Dataset>, splats: &SplatsModel) -> anyhow::Result<()> {
    let Some(ds) = ds else {
        anyhow::bail!("--format html needs --data DIR: the dataset's training cameras give the view the page opens at");
    };
    let view = crate::records::ViewDefaults::from_dataset(ds);
    let mut spz = Vec::new();
    write_splats(splats, Format::Spz, &mut spz)?;
    let stem = a.out.file_stem().and_then(|s| s.to_str()).unwrap_or("splats").to_string();
    let files = site::files(&stem, &view, spz)?;
    if a.out.extension().is_some_and(|e| e.eq_ignore_ascii_case("zip")) {
        let mut zip = std::io::Cursor::new(Vec::new());
        site::write_zip(&stem, &files, &mut zip)?;
        write_atomic(&a.out, zip.get_ref()).with_context(|| format!("writing {}", a.out.display()))?;
    } else {
        site::write_dir(&a.out, &files).with_context(|| format!("writing {}", a.out.display()))?;
    }
    eprintln!(
        "wrote {} ({} Gaussians): serve it with any static web server and open index.html",
        a.out.display(),
        splats.layout().n
    );
    Ok(())
}
