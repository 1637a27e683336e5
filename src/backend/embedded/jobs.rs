//! The embedded job store: the scheduler (its queue in memory, its records
//! in redb) and the records of scenes, models and videos as JSON files in
//! the data directory.

use std::io;
use std::time::Duration;

use super::{blocking, invalid};
use crate::backend::{Fut, JobStore, NewJob, QueueStats};
use crate::datadir::{DataDir, valid_id, write_json};
use crate::jobs::{Counters, Job, JobSpec, SchedError, Scheduler, Status};
use crate::records::{CropBox, ModelInfo, SceneInfo, VideoInfo};

/// How often a job's followers look at it again: the scheduler's progress
/// lives in memory, so a look costs a lock.
const CHANGE_POLL: Duration = Duration::from_millis(50);

/// The scheduler and the data directory's records.
pub struct EmbeddedJobs {
    scheduler: Scheduler,
    storage: DataDir,
}

impl EmbeddedJobs {
    pub fn new(scheduler: Scheduler, storage: DataDir) -> Self {
        Self { scheduler, storage }
    }
}

/// Enqueues with the scheduler, under the id the job names (checked: it
/// becomes a path component of the model and video it makes) or a fresh one.
fn enqueue(scheduler: &Scheduler, new: NewJob) -> Result<Job, SchedError> {
    match new.id {
        None => scheduler.enqueue(new.spec, new.model_id, new.memory_estimate),
        Some(id) if valid_id(&id) => scheduler.enqueue_as(id, new.spec, new.model_id, new.memory_estimate),
        Some(id) => Err(invalid(format!("'{id}' is not a valid job id")).into()),
    }
}

/// Writes the record of a scene staged in `tmp/ID/` and renames the folder
/// to `scenes/ID/`: the scene appears whole, files and record, or not at
/// all. A photo-only scene's record names its job before the job exists,
/// so the job never meets a record without it; a crash before the job is
/// queued leaves a posing scene without its job, which the next start
/// marks failed. If the job cannot be queued, the scene is removed again.
fn insert_scene(
    scheduler: &Scheduler,
    storage: &DataDir,
    scene: &SceneInfo,
    poses_job: Option<NewJob>,
) -> Result<Option<Job>, SchedError> {
    if !valid_id(&scene.id) {
        return Err(invalid(format!("'{}' is not a valid scene id", scene.id)).into());
    }
    if let Some(j) = &poses_job
        && (!matches!(j.spec, JobSpec::Poses(_)) || j.spec.scene_id() != Some(scene.id.as_str()))
    {
        return Err(invalid(format!("the job stored with scene '{}' is not its pose estimation", scene.id)).into());
    }
    let staging = storage.staging_dir(&scene.id);
    write_json(&staging.join("scene.json"), scene)?;
    let dir = storage.scene_dir(&scene.id);
    std::fs::rename(&staging, &dir)?;
    let Some(new) = poses_job else { return Ok(None) };
    match enqueue(scheduler, new) {
        Ok(job) => Ok(Some(job)),
        Err(e) => {
            let trash = storage.scene_trash(&scene.id);
            if std::fs::rename(&dir, &trash).is_ok() {
                let _ = std::fs::remove_dir_all(trash);
            }
            Err(e)
        }
    }
}

/// Removes a scene unless a queued or running job uses it: one rename
/// (checked under the scheduler's lock) makes it disappear, then its files
/// go.
fn delete_scene(scheduler: &Scheduler, storage: &DataDir, id: &str) -> Result<(), SchedError> {
    if storage.load_scene(id)?.is_none() {
        return Err(SchedError::SceneNotFound(id.into()));
    }
    let trash = storage.scene_trash(id);
    scheduler.delete_scene(id, || std::fs::rename(storage.scene_dir(id), &trash)).map_err(|e| match e {
        // Deleted meanwhile.
        SchedError::Io(io) if io.kind() == io::ErrorKind::NotFound => SchedError::SceneNotFound(id.into()),
        e => e,
    })?;
    Ok(std::fs::remove_dir_all(trash)?)
}

impl JobStore for EmbeddedJobs {
    fn enqueue(&self, job: NewJob) -> Fut<'_, Result<Job, SchedError>> {
        let scheduler = self.scheduler.clone();
        Box::pin(async move { blocking(move || enqueue(&scheduler, job)).await? })
    }

    /// From memory, where the scheduler keeps progress.
    fn get_job<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<Job>>> {
        Box::pin(std::future::ready(Ok(self.scheduler.get(id))))
    }

    fn list_jobs(&self, status: Option<Status>) -> Fut<'_, io::Result<Vec<Job>>> {
        Box::pin(std::future::ready(Ok(self.scheduler.list(status))))
    }

    fn stats(&self) -> Fut<'_, io::Result<QueueStats>> {
        let (by_status, queued) = self.scheduler.stats();
        Box::pin(std::future::ready(Ok(QueueStats { by_status, queued })))
    }

    fn cancel<'a>(&'a self, id: &'a str) -> Fut<'a, Result<Job, SchedError>> {
        let (scheduler, id) = (self.scheduler.clone(), id.to_string());
        Box::pin(async move { blocking(move || scheduler.cancel(&id)).await? })
    }

    fn delete_job<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        let (scheduler, id) = (self.scheduler.clone(), id.to_string());
        Box::pin(async move { blocking(move || scheduler.delete_job(&id)).await? })
    }

    /// Progress changes in memory with no announcement: look again shortly.
    fn job_changed<'a>(&'a self, _id: &'a str) -> Fut<'a, ()> {
        Box::pin(tokio::time::sleep(CHANGE_POLL))
    }

    fn insert_scene(&self, scene: SceneInfo, poses_job: Option<NewJob>) -> Fut<'_, Result<Option<Job>, SchedError>> {
        let (scheduler, storage) = (self.scheduler.clone(), self.storage.clone());
        Box::pin(async move { blocking(move || insert_scene(&scheduler, &storage, &scene, poses_job)).await? })
    }

    fn get_scene<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<SceneInfo>>> {
        let (storage, id) = (self.storage.clone(), id.to_string());
        Box::pin(async move { blocking(move || storage.load_scene(&id)).await? })
    }

    fn list_scenes(&self) -> Fut<'_, io::Result<Vec<SceneInfo>>> {
        let storage = self.storage.clone();
        Box::pin(async move { blocking(move || storage.list_scenes()).await? })
    }

    fn delete_scene<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        let (scheduler, storage, id) = (self.scheduler.clone(), self.storage.clone(), id.to_string());
        Box::pin(async move { blocking(move || delete_scene(&scheduler, &storage, &id)).await? })
    }

    fn get_model<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<ModelInfo>>> {
        let (storage, id) = (self.storage.clone(), id.to_string());
        Box::pin(async move { blocking(move || storage.load_model(&id)).await? })
    }

    fn list_models(&self) -> Fut<'_, io::Result<Vec<ModelInfo>>> {
        let storage = self.storage.clone();
        Box::pin(async move { blocking(move || storage.list_models()).await? })
    }

    /// Under the scheduler's lock (see `jobs::lifecycle`).
    fn delete_model<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        let (scheduler, id) = (self.scheduler.clone(), id.to_string());
        Box::pin(async move { blocking(move || scheduler.delete_model(&id)).await? })
    }

    /// Under the scheduler's lock, as a deletion.
    fn set_crop<'a>(&'a self, id: &'a str, crop: Option<CropBox>) -> Fut<'a, Result<ModelInfo, SchedError>> {
        let (scheduler, id) = (self.scheduler.clone(), id.to_string());
        Box::pin(async move { blocking(move || scheduler.set_crop(&id, crop)).await? })
    }

    fn get_video<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<VideoInfo>>> {
        let (storage, id) = (self.storage.clone(), id.to_string());
        Box::pin(async move { blocking(move || storage.load_video(&id)).await? })
    }

    fn list_videos(&self) -> Fut<'_, io::Result<Vec<VideoInfo>>> {
        let storage = self.storage.clone();
        Box::pin(async move { blocking(move || storage.list_videos()).await? })
    }

    /// Under the scheduler's lock (see `jobs::lifecycle`).
    fn delete_video<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        let (scheduler, id) = (self.scheduler.clone(), id.to_string());
        Box::pin(async move { blocking(move || scheduler.delete_video(&id)).await? })
    }

    fn counters(&self) -> Option<&Counters> {
        Some(self.scheduler.counters())
    }

    /// The job database answers a read (it is open, and its file is
    /// readable).
    fn ready(&self) -> Fut<'_, io::Result<()>> {
        let scheduler = self.scheduler.clone();
        Box::pin(async move { blocking(move || scheduler.check_database()).await? })
    }

    /// Running jobs checkpoint and stay queued on disk; the job database is
    /// closed once every job thread has written its last record.
    fn shutdown(&self) -> Fut<'_, ()> {
        let scheduler = self.scheduler.clone();
        Box::pin(async move {
            if let Err(e) = blocking(move || scheduler.shutdown()).await {
                tracing::error!(error = %e, "stopping the scheduler");
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::embedded;
    use crate::jobs::{PosesSpec, SchedulerConfig};
    use crate::records::{SceneStatus, sample_scene};

    #[tokio::test]
    async fn a_photo_upload_whose_job_is_refused_leaves_nothing_on_disk() {
        let dir = tempfile::tempdir().unwrap();
        let config = SchedulerConfig { max_queued: 0, run_jobs: false, ..Default::default() };
        let (jobs, _artifacts) = embedded::open(dir.path(), config).unwrap();
        let storage = DataDir { root: dir.path().to_path_buf() };
        let upload = storage.staging_dir("scn_a").join("upload");
        std::fs::create_dir_all(&upload).unwrap();
        std::fs::write(upload.join("a.jpg"), b"jpeg").unwrap();
        let scene = SceneInfo { status: SceneStatus::Posing, ..sample_scene("scn_a") };
        let job = NewJob {
            id: Some("job_a".into()),
            spec: JobSpec::Poses(PosesSpec { scene_id: "scn_a".into() }),
            model_id: None,
            memory_estimate: 0,
        };
        let refused = jobs.insert_scene(scene, Some(job)).await;
        assert!(matches!(refused, Err(SchedError::QueueFull(0))), "{refused:?}");
        for d in [storage.scenes_dir(), storage.tmp_dir()] {
            let left: Vec<_> = std::fs::read_dir(&d).unwrap().collect();
            assert!(left.is_empty(), "{} holds {left:?}", d.display());
        }
        jobs.shutdown().await;
    }

    #[tokio::test]
    async fn a_scene_appears_as_staged_in_one_rename() {
        let dir = tempfile::tempdir().unwrap();
        let config = SchedulerConfig { run_jobs: false, ..Default::default() };
        let (jobs, _artifacts) = embedded::open(dir.path(), config).unwrap();
        let storage = DataDir { root: dir.path().to_path_buf() };
        let data = storage.staging_dir("scn_a").join("data");
        std::fs::create_dir_all(&data).unwrap();
        std::fs::write(data.join("transforms_train.json"), b"{}").unwrap();
        assert!(jobs.insert_scene(sample_scene("scn_a"), None).await.unwrap().is_none());
        assert!(!storage.staging_dir("scn_a").exists());
        assert_eq!(std::fs::read(storage.scene_dir("scn_a").join("data/transforms_train.json")).unwrap(), b"{}");
        assert_eq!(storage.load_scene("scn_a").unwrap().map(|s| s.id), Some("scn_a".to_string()));
        // Deleted: gone from `scenes/`, and nothing left in `tmp/`.
        jobs.delete_scene("scn_a").await.unwrap();
        assert!(!storage.scene_dir("scn_a").exists());
        assert_eq!(std::fs::read_dir(storage.tmp_dir()).unwrap().count(), 0);
        jobs.shutdown().await;
    }
}
