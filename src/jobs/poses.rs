//! A pose-estimation job: the photos (or video) of a scene uploaded without
//! camera poses, in `scenes/ID/upload/`, become a COLMAP dataset in
//! `scenes/ID/data/` (`crate::poses::estimate`, which writes it whole or
//! not at all), and the scene record becomes `ready` with the estimation's
//! report, or `failed` with the reason.
//!
//! Restart-safe like every job: an interrupted run leaves at most a working
//! folder beside `data/`, removed when the job runs again; a run that
//! finished the dataset but not the record finds `data/poses.json` and only
//! writes the record. A job that ends without success (failed, canceled,
//! or lost before it was queued) marks its scene `failed` ([`settle`]).

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use super::host::JobHost;
use super::{Job, JobError, Outcome, PosesSpec, Status};
use crate::datadir::{DataDir, ScenePart, read_json_opt, tree_bytes, write_json};
use crate::engine::front::{Dataset, LoadOptions};
use crate::poses::{self, PoseError, PoseOptions, PoseReport, Tools};
use crate::records::{SceneInfo, SceneStatus};

/// The folder of a posing scene holding the photos as uploaded.
pub const UPLOAD_DIR: &str = ScenePart::Upload.dir_name();

/// The folder the posed dataset is written to.
pub const DATA_DIR: &str = ScenePart::Data.dir_name();

/// COLMAP's share of a pose estimation's memory (its CPU SIFT and mapper
/// on photos of at most `max_size` pixels stay well below it); a job's
/// estimate adds what decoding its input takes ([`memory_estimate`]).
pub const MEMORY_ESTIMATE_BYTES: u64 = 1 << 30;

/// The memory a pose estimation is counted for: COLMAP's share, and the
/// server's own while it prepares the input, `input_bytes` (for photos,
/// [`crate::poses::photos::prepare_memory`] of the largest one's decoded
/// size, which their headers tell at upload).
pub fn memory_estimate(input_bytes: u64) -> u64 {
    MEMORY_ESTIMATE_BYTES.saturating_add(input_bytes)
}

/// What the service runs photo-only uploads with.
#[derive(Clone, Debug)]
pub struct PosesSetup {
    pub tools: Tools,
    pub max_size: u32,
    pub time_limit: Duration,
}

/// The body of a pose estimation job (see [`super::run_body`], which
/// answers a [`PoseError::Cancelled`] as stopped).
pub(crate) fn run(host: &dyn JobHost, job: &Job, spec: &PosesSpec, cancel: &AtomicBool) -> Result<Outcome, JobError> {
    pose(host, job, spec, cancel)?;
    Ok(Outcome::Succeeded)
}

fn pose(host: &dyn JobHost, job: &Job, spec: &PosesSpec, cancel: &AtomicBool) -> Result<(), PoseError> {
    let scene = host
        .scene(&spec.scene_id)
        .map_err(|e| PoseError::Io { path: format!("scene '{}'", spec.scene_id).into(), message: e.to_string() })?
        .ok_or_else(|| PoseError::Input(format!("scene '{}' no longer exists", spec.scene_id)))?;
    if scene.status == SceneStatus::Ready {
        return Ok(()); // finished before a restart
    }
    let setup = host.config().poses.as_ref().ok_or_else(|| {
        PoseError::Tool("COLMAP is not available on this server (it was not found at start-up)".into())
    })?;
    let dir = host
        .posing_workdir(job, &scene)
        .map_err(|e| PoseError::Io { path: format!("scene '{}'", scene.id).into(), message: e.to_string() })?;
    posed(host, job, &scene, setup, &dir, cancel).map_err(|e| e.relative_to(&dir, &dir.join(UPLOAD_DIR)))
}

/// [`pose`] in the scene's folder `dir`.
fn posed(
    host: &dyn JobHost,
    job: &Job,
    scene: &SceneInfo,
    setup: &PosesSetup,
    dir: &Path,
    cancel: &AtomicBool,
) -> Result<(), PoseError> {
    let fail = |m: String| PoseError::Io { path: dir.to_path_buf(), message: m };
    remove_leftovers(dir);
    let data = dir.join(DATA_DIR);
    let report_file = data.join(poses::REPORT_FILE);
    let report: PoseReport = match read_json_opt(&report_file).map_err(|e| fail(e.to_string()))? {
        Some(r) => r,
        None => {
            let opts = PoseOptions {
                max_size: setup.max_size,
                threads: rayon::current_num_threads(),
                time_limit: setup.time_limit,
                resume_in: Some(dir.join(RESUME_DIR)),
                ..PoseOptions::default()
            };
            let started = Instant::now();
            let mut on_progress = |p: poses::Progress| {
                let elapsed = started.elapsed().as_secs_f64();
                let f = p.fraction as f64;
                host.set_progress(&job.id, &mut |j| {
                    j.progress.step = (f * 1000.0).round() as u64;
                    j.progress.total_steps = Some(1000);
                    j.progress.elapsed = elapsed;
                    j.progress.eta = (f > 0.05).then(|| elapsed * (1.0 - f) / f);
                    j.progress.stage = Some(p.stage.name().to_string());
                });
            };
            let registry = dir.join(PROCESS_DIR);
            let estimated = poses::process::with_registry(&registry, || {
                poses::estimate(&dir.join(UPLOAD_DIR), &data, &setup.tools, &opts, &mut on_progress, cancel)
            });
            let _ = std::fs::remove_dir(&registry);
            estimated?
        }
    };
    let ds = Dataset::load(&data, &LoadOptions::default())
        .map_err(|e| PoseError::Reconstruction(format!("the posed dataset does not load: {e}")))?;
    let size = tree_bytes(&data).map_err(|e| fail(e.to_string()))?;
    let mut ready = SceneInfo::from_dataset(&scene.id, &ds, size, DATA_DIR.into());
    ready.created_at = scene.created_at;
    ready.warnings.extend(report.warnings.iter().cloned());
    ready.poses = scene.poses.clone().map(|p| crate::records::ScenePoses { report: Some(report), ..p });
    host.publish_posed_scene(job, &ready, dir).map_err(|e| fail(e.to_string()))?;
    tracing::info!(scene = %scene.id, registered = ready.images.train + ready.images.test, "scene posed");
    Ok(())
}

/// The working folder of a scene's pose estimation, kept across a crash of
/// the server so the next run goes on from the last stage it finished
/// (`PoseOptions::resume_in`); removed when the job ends.
pub const RESUME_DIR: &str = ".data.posing";

/// Whether the pose estimation of `scene_id` saved progress (finished a
/// stage) after `since` (ms since the epoch): the crash rule's "progress in
/// between" for a `poses` job, so two kills cost two stages, and only two
/// crashes in the same stage fail the job.
pub(crate) fn saved_progress_since(storage: &DataDir, scene_id: &str, since: Option<u64>) -> bool {
    let file = storage.scene_dir(scene_id).join(RESUME_DIR).join(poses::PROGRESS_FILE);
    let modified = std::fs::metadata(file).and_then(|m| m.modified()).ok();
    let ms = modified.and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_millis() as u64);
    matches!((ms, since), (Some(m), Some(s)) if m > s)
}

/// The folder of a posing scene listing the programs its job runs
/// (`poses::process::with_registry`), for [`clean_up_after_crash`].
pub const PROCESS_DIR: &str = ".processes";

/// At start-up, before any job runs: kills the COLMAP and ffmpeg process
/// groups that a server killed mid-job left running (`poses::process::reap`;
/// the parent-death signal stops them already, this catches what escaped
/// it), and removes the working folders of estimations cut short, whatever
/// becomes of their jobs. Returns the groups killed and folders removed.
pub(crate) fn clean_up_after_crash(storage: &DataDir) -> (usize, usize) {
    let (mut killed, mut removed) = (0, 0);
    for e in std::fs::read_dir(storage.scenes_dir()).into_iter().flatten().flatten() {
        let dir = e.path();
        let registry = dir.join(PROCESS_DIR);
        if registry.is_dir() {
            let groups = poses::process::reap(&registry);
            if !groups.is_empty() {
                tracing::warn!(scene_dir = %dir.display(), groups = ?groups, "killed programs a crashed pose estimation left running");
            }
            killed += groups.len();
            let _ = std::fs::remove_dir(&registry);
        }
        removed += remove_leftovers(&dir);
    }
    (killed, removed)
}

/// Working folders of an estimation cut short (`.data.posing-*`); returns
/// how many were removed.
fn remove_leftovers(dir: &Path) -> usize {
    let mut removed = 0;
    let prefix = format!(".{DATA_DIR}.posing-");
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        if e.file_name().to_string_lossy().starts_with(&prefix) && std::fs::remove_dir_all(e.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// Why the scene of a pose-estimation job that ended without success
/// failed (`job` is `None` when the scene's job does not exist); `None`
/// while the job is active or when it succeeded. Shared by every store of
/// the queue, so a client reads the same reason from each.
pub(crate) fn settle_reason(job: Option<&Job>) -> Option<String> {
    match job {
        None => Some("the server stopped before the pose estimation was queued; upload the photos again".to_string()),
        Some(j) if j.status == Status::Canceled => Some("pose estimation was canceled".to_string()),
        Some(j) if j.status == Status::Failed => {
            Some(format!("pose estimation failed: {}", j.error.as_deref().unwrap_or("no reason recorded")))
        }
        Some(_) => None,
    }
}

/// Marks the scene of a pose-estimation job `failed` when the job ended
/// without success (`job` is `None` when the scene's job does not exist:
/// the server stopped between storing the scene and queueing its job).
/// Does nothing to scenes that are not posing by this job.
pub(crate) fn settle(storage: &DataDir, scene_id: &str, job: Option<&Job>) {
    let Some(reason) = settle_reason(job) else { return };
    let Ok(Some(mut scene)) = storage.load_scene(scene_id) else { return };
    let job_id = scene.poses.as_ref().map(|p| p.job_id.as_str());
    if scene.status != SceneStatus::Posing || (job.is_some() && job_id != job.map(|j| j.id.as_str())) {
        return;
    }
    scene.status = SceneStatus::Failed;
    scene.error = Some(reason);
    match write_json(&storage.scene_record(scene_id), &scene) {
        Ok(()) => {
            let dir = storage.scene_dir(scene_id);
            let _ = std::fs::remove_dir_all(dir.join(UPLOAD_DIR));
            let _ = std::fs::remove_dir_all(dir.join(RESUME_DIR));
        }
        Err(e) => tracing::error!(scene = %scene_id, error = %e, "cannot record the failed pose estimation"),
    }
}
