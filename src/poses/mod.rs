//! Camera poses for photos that have none: photos (or a video's frames)
//! in, a COLMAP-format dataset out, which the engine's loader reads as is.
//!
//! [`estimate`] prepares the photos (upright, downscaled to `max_size`),
//! runs COLMAP's feature extraction, matching and mapping as subprocesses
//! under one time limit, keeps the largest model if it is good enough
//! ([`outcome`]), loads the result with the engine's loader to prove it
//! trains, and only then moves it into place: the output folder appears
//! whole or not at all, and COLMAP's working files (its database, candidate
//! frames) are removed either way.
//!
//! Like `media`, this is a sibling of the engine: the engine knows nothing
//! of subprocesses, and this module nothing of ray marching.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::engine::dataset::{Dataset, LoadOptions, colmap_model};
use crate::engine::io::fsio::write_atomic;

pub mod colmap;
mod gather;
pub mod outcome;
pub mod photos;
pub mod process;
pub mod video;

pub use colmap::{Colmap, Matcher};
use gather::{GatherStep, Gathered};
pub use video::Ffmpeg;

/// Where the report is written in the dataset.
pub const REPORT_FILE: &str = "poses.json";

/// What an estimation in a kept working folder (`PoseOptions::resume_in`)
/// has finished, in that folder; rewritten (atomically) as each stage ends.
pub const PROGRESS_FILE: &str = "progress.json";

/// The contents of [`PROGRESS_FILE`].
#[derive(Debug, Default, Serialize, Deserialize)]
struct Saved {
    /// The photos (or frames) in `dataset/images`, once all are there.
    gathered: Option<SavedGather>,
    /// COLMAP's steps done, in order.
    done: Vec<Stage>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct SavedGather {
    source: String,
    names: Vec<String>,
    size: (u32, u32),
}

/// Default longest side of the photos given to COLMAP (and kept for training).
pub const DEFAULT_MAX_SIZE: u32 = 800;

/// Default time limit of a whole estimation.
pub const DEFAULT_TIME_LIMIT: Duration = Duration::from_secs(30 * 60);

/// Up to this many photos every pair is matched; beyond, neighbours in name
/// order (photos from a phone are numbered in the order they were taken).
pub const EXHAUSTIVE_UP_TO: usize = 100;

/// Why an estimation did not give a dataset.
#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    /// The photos or the video: none, too few, unreadable, mixed sizes.
    #[error("{0}")]
    Input(String),
    /// COLMAP (or ffmpeg) is missing, crashed or failed.
    #[error("{0}")]
    Tool(String),
    /// COLMAP ran but could not pose enough of the photos.
    #[error("{0}")]
    Reconstruction(String),
    #[error("pose estimation took longer than its time limit during {stage} ({seconds:.0} s); COLMAP was stopped")]
    TimedOut { stage: &'static str, seconds: f64 },
    #[error("pose estimation was cancelled")]
    Cancelled,
    #[error("{}: {message}", path.display())]
    Io { path: PathBuf, message: String },
}

impl PoseError {
    pub fn io(path: &Path, e: std::io::Error) -> Self {
        Self::Io { path: path.to_path_buf(), message: e.to_string() }
    }

    /// The error as a client may read it: the folder the photos were in
    /// (`input`) left out of the paths it names, and the rest of `work`
    /// shown relative to it (`./...`), so no server path is shown.
    pub fn relative_to(self, work: &Path, input: &Path) -> Self {
        let strip = |m: String| {
            let (input, work) = (input.display().to_string(), work.display().to_string());
            m.replace(&format!("{input}/"), "").replace(&input, ".").replace(&work, ".")
        };
        match self {
            Self::Input(m) => Self::Input(strip(m)),
            Self::Tool(m) => Self::Tool(strip(m)),
            Self::Reconstruction(m) => Self::Reconstruction(strip(m)),
            Self::Io { path, message } => {
                Self::Io { path: PathBuf::from(strip(path.display().to_string())), message: strip(message) }
            }
            e @ (Self::TimedOut { .. } | Self::Cancelled) => e,
        }
    }

    /// A short machine-readable kind, for the API.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Input(_) => "input",
            Self::Tool(_) => "tool",
            Self::Reconstruction(_) => "reconstruction",
            Self::TimedOut { .. } => "timed_out",
            Self::Cancelled => "cancelled",
            Self::Io { .. } => "io",
        }
    }
}

/// The programs an estimation runs.
#[derive(Debug, Clone)]
pub struct Tools {
    pub colmap: Colmap,
    /// Needed only for videos.
    pub ffmpeg: Option<Ffmpeg>,
}

/// An estimation's settings.
#[derive(Debug, Clone)]
pub struct PoseOptions {
    /// Longest side of the photos, in pixels.
    pub max_size: u32,
    pub threads: usize,
    pub time_limit: Duration,
    /// `None`: exhaustive up to [`EXHAUSTIVE_UP_TO`] photos, sequential
    /// beyond and for videos.
    pub matcher: Option<Matcher>,
    /// Frames taken from a video.
    pub frames: usize,
    /// A working folder that outlives a crash of the process: the stages an
    /// estimation finished there (photos or frames prepared, features,
    /// matching, mapping; [`PROGRESS_FILE`]) are not run again by the next
    /// estimation given it. It is removed when an estimation ends, unless
    /// cancelled (a shutdown: the next run goes on). `None`: a fresh folder
    /// beside the output, removed at the end.
    pub resume_in: Option<PathBuf>,
}

impl Default for PoseOptions {
    fn default() -> Self {
        Self {
            max_size: DEFAULT_MAX_SIZE,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            time_limit: DEFAULT_TIME_LIMIT,
            matcher: None,
            frames: video::DEFAULT_FRAMES,
            resume_in: None,
        }
    }
}

/// The stages of an estimation, in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Photos,
    Frames,
    Features,
    Matching,
    Mapping,
    Checking,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Self::Photos => "preparing photos",
            Self::Frames => "extracting video frames",
            Self::Features => "feature extraction",
            Self::Matching => "matching",
            Self::Mapping => "mapping",
            Self::Checking => "checking the result",
        }
    }

    /// The share of the whole run before this stage and this stage's share
    /// (rough: matching and mapping dominate).
    fn span(self) -> (f32, f32) {
        match self {
            Self::Photos | Self::Frames => (0.0, 0.05),
            Self::Features => (0.05, 0.15),
            Self::Matching => (0.20, 0.45),
            Self::Mapping => (0.65, 0.32),
            Self::Checking => (0.97, 0.03),
        }
    }
}

/// Where an estimation is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Progress {
    pub stage: Stage,
    /// Of this stage, 0 to 1.
    pub stage_fraction: f32,
    /// Of the whole estimation, 0 to 1.
    pub fraction: f32,
}

/// Wall time of each stage, seconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StageSeconds {
    pub prepare: f64,
    pub features: f64,
    pub matching: f64,
    pub mapping: f64,
    pub total: f64,
}

/// What an estimation found; written as `poses.json` into the dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseReport {
    /// `photos` or `video`.
    pub source: String,
    /// Photos (or frames) given to COLMAP.
    pub images: usize,
    /// Of those, posed in the model kept.
    pub registered: usize,
    pub unregistered: Vec<String>,
    /// Sparse points of the model kept.
    pub points: usize,
    /// COLMAP's mean reprojection error of the model kept, pixels.
    pub mean_reprojection_error_px: Option<f64>,
    /// Models the mapper made (1 unless the photos fell apart into groups).
    pub models: usize,
    pub matcher: Matcher,
    /// Size of the images as given to COLMAP and kept for training.
    pub width: u32,
    pub height: u32,
    pub seconds: StageSeconds,
    pub colmap_version: String,
    pub warnings: Vec<String>,
}

/// Estimates poses for the photos (or the one video) in `input`, a folder or
/// a video file, and writes a COLMAP-format dataset to `out`, which must not
/// exist or be an empty folder. `progress` is called as stages advance;
/// setting `cancel` stops COLMAP and removes its files.
pub fn estimate(
    input: &Path,
    out: &Path,
    tools: &Tools,
    opts: &PoseOptions,
    progress: &mut dyn FnMut(Progress),
    cancel: &AtomicBool,
) -> Result<PoseReport, PoseError> {
    check_output(out)?;
    let mut work = match &opts.resume_in {
        Some(dir) => Work::kept(dir)?,
        None => Work::new(out)?,
    };
    let result = estimate_in(&work, input, out, tools, opts, progress, cancel);
    // A cancelled run of a kept folder (a shutdown) leaves it for the next.
    work.keep = opts.resume_in.is_some() && matches!(result, Err(PoseError::Cancelled));
    result
}

/// [`estimate`] in the working folder `work`.
fn estimate_in(
    work: &Work,
    input: &Path,
    out: &Path,
    tools: &Tools,
    opts: &PoseOptions,
    progress: &mut dyn FnMut(Progress),
    cancel: &AtomicBool,
) -> Result<PoseReport, PoseError> {
    let started = Instant::now();
    let deadline = started + opts.time_limit;
    let dataset = work.dir.join("dataset");
    // Fractions never go back, even when COLMAP's counts do (the mapper
    // starts over from another image pair when a start fails).
    let mut last = Progress { stage: Stage::Photos, stage_fraction: 0.0, fraction: 0.0 };
    let mut report_stage = |stage: Stage, f: f32| {
        let (a, b) = stage.span();
        let f = if stage == last.stage { f.max(last.stage_fraction) } else { f };
        let p = Progress { stage, stage_fraction: f, fraction: (a + b * f).max(last.fraction) };
        last = p;
        progress(p);
    };

    // What a run before a crash finished here (kept folders only).
    let progress_file = work.dir.join(PROGRESS_FILE);
    let mut saved = saved_progress(opts, &progress_file, &dataset);
    let save = |saved: &Saved| save_progress(opts, &progress_file, saved);

    // 1. Photos, or a video's frames, into dataset/images.
    let step = GatherStep { work, input, dataset: &dataset, tools, opts, deadline, cancel };
    let gathered = step.gather_or_resume(&mut saved, &save, &mut report_stage)?;
    let mut seconds = StageSeconds { prepare: started.elapsed().as_secs_f64(), ..Default::default() };

    // 2. COLMAP.
    let matcher = opts.matcher.unwrap_or(if gathered.source == "video" || gathered.names.len() > EXHAUSTIVE_UP_TO {
        Matcher::Sequential
    } else {
        Matcher::Exhaustive
    });
    let mut sorted_names = gathered.names.clone();
    sorted_names.sort();
    let images = dataset.join("images");
    let run = colmap::Run {
        colmap: &tools.colmap,
        work: &work.dir.join("colmap"),
        images: &images,
        names: &sorted_names,
        threads: opts.threads.max(1),
        matcher,
        deadline,
        cancel,
    };
    std::fs::create_dir_all(run.work).map_err(|e| PoseError::io(run.work, e))?;
    run_steps(&run, started, &mut seconds, &mut report_stage, &mut saved, &save)?;

    // 3. and 4. The model to keep, and the dataset it makes.
    let report = keep_model(&run, &dataset, &gathered, tools, started, seconds, &mut report_stage)?;
    Work::finish(&dataset, out)?;
    Ok(report)
}

/// What a run before a crash finished in the work folder (`opts.resume_in`
/// only; nothing otherwise). A run cut short while the model it kept was
/// moved into the dataset maps again.
fn saved_progress(opts: &PoseOptions, progress_file: &Path, dataset: &Path) -> Saved {
    let mut saved: Saved = match &opts.resume_in {
        Some(_) => std::fs::read(progress_file).ok().and_then(|b| serde_json::from_slice(&b).ok()).unwrap_or_default(),
        None => Saved::default(),
    };
    if dataset.join("sparse").exists() {
        let _ = std::fs::remove_dir_all(dataset.join("sparse"));
        saved.done.retain(|s| *s != Stage::Mapping);
    }
    saved
}

/// Saves what is finished, for a run after a crash (`opts.resume_in` only).
fn save_progress(opts: &PoseOptions, progress_file: &Path, saved: &Saved) -> Result<(), PoseError> {
    if opts.resume_in.is_none() {
        return Ok(());
    }
    let json = serde_json::to_vec(saved).map_err(|e| PoseError::io(progress_file, e.into()))?;
    write_atomic(progress_file, &json).map_err(|e| PoseError::io(progress_file, e))
}

/// dataset as `sparse/0`, COLMAP's other files removed; then the dataset
/// checked to load as `train` will load it, and the report written beside it.
fn keep_model(
    run: &colmap::Run<'_>,
    dataset: &Path,
    gathered: &Gathered,
    tools: &Tools,
    started: Instant,
    mut seconds: StageSeconds,
    report_stage: &mut dyn FnMut(Stage, f32),
) -> Result<PoseReport, PoseError> {
    report_stage(Stage::Checking, 0.0);
    let candidates = read_models(run)?;
    let verdict = outcome::judge(&gathered.names, &candidates)?;
    let best = &candidates[verdict.chosen];
    let mean_error = run.mean_reprojection_error(&best.dir);
    let sparse = dataset.join("sparse");
    std::fs::create_dir_all(&sparse).map_err(|e| PoseError::io(&sparse, e))?;
    std::fs::rename(&best.dir, sparse.join("0")).map_err(|e| PoseError::io(&best.dir, e))?;
    // The database and other models go now: the dataset is what remains.
    let _ = std::fs::remove_dir_all(run.work);

    Dataset::load(dataset, &LoadOptions::default())
        .map_err(|e| PoseError::Reconstruction(format!("the posed photos do not make a usable dataset: {e}")))?;
    seconds.total = started.elapsed().as_secs_f64();
    let report = PoseReport {
        source: gathered.source.to_string(),
        images: gathered.names.len(),
        registered: best.images.len(),
        unregistered: verdict.unregistered,
        points: best.points,
        mean_reprojection_error_px: mean_error,
        models: candidates.len(),
        matcher: run.matcher,
        width: gathered.size.0,
        height: gathered.size.1,
        seconds,
        colmap_version: tools.colmap.version.clone(),
        warnings: verdict.warnings,
    };
    let json = serde_json::to_vec_pretty(&report).map_err(|e| PoseError::io(dataset, e.into()))?;
    write_atomic(&dataset.join(REPORT_FILE), &json).map_err(|e| PoseError::io(dataset, e))?;
    report_stage(Stage::Checking, 1.0);
    Ok(report)
}

/// COLMAP's three steps, each timed into `seconds`, skipping those `saved`
/// holds as done (each one done is added and saved). A mapper that found no
/// pair of photos to start from is not an error here: it leaves no model,
/// which [`outcome::judge`] explains.
fn run_steps(
    run: &colmap::Run<'_>,
    started: Instant,
    seconds: &mut StageSeconds,
    report_stage: &mut dyn FnMut(Stage, f32),
    saved: &mut Saved,
    save: &dyn Fn(&Saved) -> Result<(), PoseError>,
) -> Result<(), PoseError> {
    for (step, stage) in [
        (colmap::Step::Features, Stage::Features),
        (colmap::Step::Matching, Stage::Matching),
        (colmap::Step::Mapping, Stage::Mapping),
    ] {
        if saved.done.contains(&stage) {
            report_stage(stage, 1.0);
            continue;
        }
        // What a run cut short left of this step: features are extracted
        // again into a new database; matching goes on in the database
        // (COLMAP skips the pairs it holds); mapping starts over.
        let stale: &[&str] = match step {
            colmap::Step::Features => &["database.db", "database.db-journal", "database.db-wal", "database.db-shm"],
            colmap::Step::Matching => &[],
            colmap::Step::Mapping => &["sparse"],
        };
        for name in stale {
            let p = run.work.join(name);
            let _ = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
        }
        let t = Instant::now();
        report_stage(stage, 0.0);
        let result = run.step(step, &mut |f| report_stage(stage, f));
        if let Err(process::RunError::Failed { tail, .. }) = &result
            && step == colmap::Step::Mapping
            && tail.iter().any(|l| l.contains("failed to create sparse model"))
        {
            saved.done.push(stage);
            return save(saved);
        }
        result.map_err(|e| match e {
            process::RunError::Cancelled => PoseError::Cancelled,
            process::RunError::TimedOut { .. } => {
                PoseError::TimedOut { stage: step.name(), seconds: started.elapsed().as_secs_f64() }
            }
            e => PoseError::Tool(format!("COLMAP's {} failed: {e}", step.name())),
        })?;
        let s = t.elapsed().as_secs_f64();
        match step {
            colmap::Step::Features => seconds.features = s,
            colmap::Step::Matching => seconds.matching = s,
            colmap::Step::Mapping => seconds.mapping = s,
        }
        saved.done.push(stage);
        save(saved)?;
    }
    Ok(())
}

/// The models the mapper wrote, read back.
fn read_models(run: &colmap::Run<'_>) -> Result<Vec<outcome::Candidate>, PoseError> {
    run.models()
        .into_iter()
        .map(|dir| {
            let model = colmap_model::read(&dir)
                .map_err(|e| PoseError::Tool(format!("COLMAP wrote a model that does not read back: {e}")))?;
            let images = model.images.iter().map(|i| i.name.clone()).collect();
            Ok(outcome::Candidate { dir, images, points: model.points.len() })
        })
        .collect()
}

fn check_output(out: &Path) -> Result<(), PoseError> {
    match std::fs::read_dir(out).map(|mut entries| entries.next().is_none()) {
        Ok(true) => Ok(()),
        Ok(false) => {
            Err(PoseError::Input(format!("'{}' already exists and is not empty; choose a new folder", out.display())))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(_) if out.exists() => Err(PoseError::Input(format!("'{}' exists and is not a folder", out.display()))),
        Err(e) => Err(PoseError::io(out, e)),
    }
}

/// The working folder beside the output (same file system, so the finished
/// dataset is renamed into place); removed when dropped unless `keep`.
struct Work {
    dir: PathBuf,
    keep: bool,
}

impl Work {
    fn new(out: &Path) -> Result<Self, PoseError> {
        let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "dataset".into());
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
        let dir = out.with_file_name(format!(".{name}.posing-{}-{nanos}", std::process::id()));
        Self::kept(&dir)
    }

    /// `dir`, made if missing, with what it holds.
    fn kept(dir: &Path) -> Result<Self, PoseError> {
        std::fs::create_dir_all(dir).map_err(|e| PoseError::io(dir, e))?;
        Ok(Self { dir: dir.to_path_buf(), keep: false })
    }

    /// Moves the finished `dataset` to `out` (replacing an empty folder).
    fn finish(dataset: &Path, out: &Path) -> Result<(), PoseError> {
        if out.is_dir() {
            std::fs::remove_dir(out).map_err(|e| PoseError::io(out, e))?;
        }
        std::fs::rename(dataset, out).map_err(|e| PoseError::io(out, e))
    }
}

impl Drop for Work {
    fn drop(&mut self) {
        if !self.keep {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}
