//! What a crash or a finished job leaves on disk, and its removal:
//!
//! - at start-up, [`remove_orphans`] removes checkpoints and video files
//!   that have no record and that no queued or running job will write (what
//!   a crash mid-delete, or mid-save of a job that then ended, leaves);
//! - from the scheduler thread, at start-up, once a minute and when a job
//!   ends, [`sweep`] drops the optimiser state from the checkpoints of
//!   models whose training ended at least `keep_training_state_hours` ago
//!   (they still render the same; only resuming training needs it).

use std::collections::BTreeMap;
use std::io;
use std::path::Path;
use std::time::{Duration, Instant};

use super::lifecycle::writes_model;
use super::{Job, JobSpec, Shared};
use crate::datadir::{DataDir, now_ms, remove_file_if_exists, valid_id, write_json};
use crate::engine::front::strip_training_state;
use crate::records::ModelInfo;

/// Longest pause between two sweeps.
pub(crate) const SWEEP_EVERY: Duration = Duration::from_secs(60);

/// Whether a sweep is due: never swept yet, a job ended since, or a minute.
pub(crate) fn sweep_due(shared: &Shared, last: Option<Instant>) -> bool {
    let requested = shared.sweep_requested.swap(false, std::sync::atomic::Ordering::SeqCst);
    requested || last.is_none_or(|t| t.elapsed() >= SWEEP_EVERY)
}

/// Removes `models/ID.ckpt` files without a record that no queued or
/// running training job will write (a running job writes its checkpoint
/// before its record, and resumes from it after a crash), and
/// `videos/ID.bin` files without a record that no queued or running video
/// job reserves. Returns the paths removed.
pub(crate) fn remove_orphans(storage: &DataDir, jobs: &BTreeMap<String, Job>) -> io::Result<Vec<String>> {
    let active: Vec<&Job> = jobs.values().filter(|j| !j.status.is_final()).collect();
    let mut removed = Vec::new();
    for id in ids_with_extension(&storage.models_dir(), "ckpt")? {
        let written = active.iter().any(|j| writes_model(j, &id));
        if !written && !storage.model_record(&id).exists() {
            remove_file_if_exists(&storage.checkpoint(&id))?;
            removed.push(format!("models/{id}.ckpt"));
        }
    }
    // Frames saved by video jobs that are no longer running (`video.rs`).
    for e in std::fs::read_dir(storage.videos_dir())? {
        let name = e?.file_name().to_string_lossy().into_owned();
        if let Some(job) = name.strip_prefix(crate::datadir::VIDEO_FRAMES_PREFIX)
            && !active.iter().any(|j| j.id == job)
        {
            let _ = std::fs::remove_dir_all(storage.videos_dir().join(&name));
            removed.push(format!("videos/{name}"));
        }
    }
    for id in ids_with_extension(&storage.videos_dir(), "bin")? {
        let written = active.iter().any(|j| matches!(j.spec, JobSpec::Video(_)) && j.reserved_video_id() == id);
        if !written && !storage.video_record(&id).exists() {
            remove_file_if_exists(&storage.video_file(&id))?;
            removed.push(format!("videos/{id}.bin"));
        }
    }
    Ok(removed)
}

/// The ids of `dir/ID.EXT` files (temporary files, whose names start with
/// a dot, are not ids).
fn ids_with_extension(dir: &Path, ext: &str) -> io::Result<Vec<String>> {
    let mut ids = Vec::new();
    for e in std::fs::read_dir(dir)? {
        let name = e?.file_name().to_string_lossy().into_owned();
        if let Some(id) = name.strip_suffix(ext).and_then(|s| s.strip_suffix('.'))
            && valid_id(id)
        {
            ids.push(id.to_string());
        }
    }
    Ok(ids)
}

/// The models whose optimiser state can go: still there, training ended
/// (no queued or running job writes them) at least `keep` ago.
pub(crate) fn strip_candidates(
    models: &[ModelInfo],
    jobs: &BTreeMap<String, Job>,
    now: u64,
    keep: Duration,
) -> Vec<String> {
    let keep_ms = u64::try_from(keep.as_millis()).unwrap_or(u64::MAX);
    models
        .iter()
        .filter(|m| m.training_state && now.saturating_sub(m.updated_at) >= keep_ms)
        .filter(|m| !jobs.values().any(|j| !j.status.is_final() && writes_model(j, &m.id)))
        .map(|m| m.id.clone())
        .collect()
}

/// Drops the optimiser state of every candidate (see [`strip_candidates`]).
/// Runs on the scheduler thread without its lock; errors are logged.
pub(crate) fn sweep(shared: &Shared) {
    let models = match shared.storage.list_models() {
        Ok(m) => m,
        Err(e) => {
            tracing::warn!(error = %e, "retention: cannot list the models");
            return;
        }
    };
    let candidates = strip_candidates(&models, &shared.lock().jobs, now_ms(), shared.config.keep_training_state);
    for id in candidates {
        match strip_model(shared, &id) {
            Ok(Some(size)) => tracing::info!(model = %id, size_bytes = size, "dropped the optimiser state"),
            Ok(None) => {}
            Err(e) => tracing::warn!(model = %id, error = %e, "retention: cannot drop the optimiser state"),
        }
    }
}

/// Rewrites one checkpoint without its optimiser state, then its record
/// (new size, `training_state: false`); the new size, or `None` if the
/// model was deleted or stripped meanwhile. Under `model_files`, so a
/// deletion cannot interleave and leave a checkpoint or record behind.
fn strip_model(shared: &Shared, id: &str) -> Result<Option<u64>, String> {
    let _files = shared.model_files.lock().unwrap_or_else(|e| e.into_inner());
    let storage = &shared.storage;
    let Some(mut info) = storage.load_model(id).map_err(|e| e.to_string())? else { return Ok(None) };
    if !info.training_state {
        return Ok(None);
    }
    let path = storage.checkpoint(id);
    // A crash after this rewrite but before the record's leaves the record
    // claiming the state: the next sweep finds the file stripped and fixes it.
    strip_training_state(&path).map_err(|e| e.to_string())?;
    info.size_bytes = std::fs::metadata(&path).map_err(|e| e.to_string())?.len();
    info.training_state = false;
    info.updated_at = now_ms();
    write_json(&storage.model_record(id), &info).map_err(|e| e.to_string())?;
    Ok(Some(info.size_bytes))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::{JobProgress, Status, VideoSpec};
    use crate::media::video::VideoFormat;
    use crate::records::ViewDefaults;

    fn job(id: &str, status: Status, train: bool, model_id: Option<&str>) -> Job {
        let spec = if train {
            crate::jobs::journal::tests::train_spec()
        } else {
            let format = VideoFormat::Gif;
            JobSpec::Video(VideoSpec {
                frames: 1,
                fps: 1,
                width: 16,
                height: 16,
                elevation: 0.0,
                radius: 1.0,
                fov: 40.0,
                format,
                path: None,
                appearance: Default::default(),
            })
        };
        Job {
            id: id.into(),
            seq: 0,
            status,
            spec,
            created_at: 0,
            started_at: None,
            finished_at: None,
            error: None,
            model_id: model_id.map(Into::into),
            video_id: None,
            progress: JobProgress::default(),
            attempts: 0,
            memory_estimate_bytes: 0,
            crashes: 0,
        }
    }

    fn jobs(v: Vec<Job>) -> BTreeMap<String, Job> {
        v.into_iter().map(|j| (j.id.clone(), j)).collect()
    }

    fn model(id: &str, updated_at: u64, training_state: bool) -> ModelInfo {
        let view = ViewDefaults { width: 1, height: 1, ..crate::records::sample_view() };
        ModelInfo {
            id: id.into(),
            scene_id: "scn_a".into(),
            job_id: "job_x".into(),
            model: "nerf-tiny".into(),
            model_reason: None,
            config: serde_json::Value::Null,
            steps: 1,
            training_seconds: 1.0,
            test_psnr: None,
            test_views: 0,
            size_bytes: 1,
            created_at: 0,
            updated_at,
            complete: true,
            training_state,
            view,
            poses: None,
            gaussians: None,
            transients: None,
            crop: None,
        }
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> =
            std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        v.sort();
        v
    }

    #[test]
    fn orphans_go_and_what_a_job_will_write_stays() {
        let dir = tempfile::tempdir().unwrap();
        let s = DataDir::open(dir.path()).unwrap();
        let touch = |p: std::path::PathBuf| std::fs::write(p, b"x").unwrap();
        // A running training job's checkpoint before its first record, and
        // one of a queued job that already checkpointed (model_id set).
        let running = job("job_run", Status::Running, true, None);
        touch(s.checkpoint(&running.reserved_model_id()));
        touch(s.checkpoint("mdl_resumed"));
        let queued = job("job_resume", Status::Queued, true, Some("mdl_resumed"));
        // A finished job's checkpoint without a record (a crash mid-delete).
        let ended = job("job_end", Status::Succeeded, true, None);
        touch(s.checkpoint(&ended.reserved_model_id()));
        // A recorded model; a record alone; someone's temporary file.
        touch(s.checkpoint("mdl_kept"));
        touch(s.model_record("mdl_kept"));
        touch(s.model_record("mdl_record_only"));
        touch(s.models_dir().join(".mdl_x.ckpt.tmp1.0"));
        // Videos: a queued video job's reserved file, a finished one's without
        // a record, a recorded one.
        let vqueued = job("job_vq", Status::Queued, false, Some("mdl_kept"));
        touch(s.video_file(&vqueued.reserved_video_id()));
        let vdone = job("job_vd", Status::Failed, false, Some("mdl_kept"));
        touch(s.video_file(&vdone.reserved_video_id()));
        touch(s.video_file("vid_kept"));
        touch(s.video_record("vid_kept"));

        let all = jobs(vec![running, queued, ended, vqueued, vdone]);
        let mut removed = remove_orphans(&s, &all).unwrap();
        removed.sort();
        assert_eq!(removed, ["models/mdl_end.ckpt", "videos/vid_vd.bin"]);
        assert_eq!(
            names(&s.models_dir()),
            [
                ".mdl_x.ckpt.tmp1.0",
                "mdl_kept.ckpt",
                "mdl_kept.json",
                "mdl_record_only.json",
                "mdl_resumed.ckpt",
                "mdl_run.ckpt"
            ]
        );
        assert_eq!(names(&s.videos_dir()), ["vid_kept.bin", "vid_kept.json", "vid_vq.bin"]);
        assert!(remove_orphans(&s, &all).unwrap().is_empty(), "a second pass finds nothing");
    }

    #[test]
    fn only_models_whose_training_ended_long_enough_ago_are_stripped() {
        let hour = 3_600_000;
        let now = 10 * hour;
        let models = [
            model("mdl_old", now - 2 * hour, true),
            model("mdl_young", now - hour / 2, true),
            model("mdl_stripped", now - 5 * hour, false),
            // Interrupted by a shutdown: `complete`, but its job resumes.
            model("mdl_paused", now - 5 * hour, true),
            // A queued video job only reads it: stripping keeps it renderable.
            model("mdl_video", now - 5 * hour, true),
        ];
        let all = jobs(vec![
            job("job_paused", Status::Running, true, Some("mdl_paused")),
            job("job_v", Status::Queued, false, Some("mdl_video")),
            job("job_old", Status::Succeeded, true, Some("mdl_old")),
        ]);
        let keep = Duration::from_secs(3600);
        assert_eq!(strip_candidates(&models, &all, now, keep), ["mdl_old", "mdl_video"]);
        assert_eq!(strip_candidates(&models, &all, now, Duration::ZERO), ["mdl_old", "mdl_young", "mdl_video"]);
        // A queued job that will write it (its reserved id) protects it too.
        let reserved = jobs(vec![job("job_old", Status::Queued, true, None)]);
        assert_eq!(strip_candidates(&models[..1], &reserved, now, Duration::ZERO), Vec::<String>::new());
    }
}
