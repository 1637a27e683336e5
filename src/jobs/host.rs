//! What a job body (`train`, `video`, `poses`) needs from the place it
//! runs in: settings, progress reporting, the records it reads, the files
//! it works on, and where its results go. The bodies run on std threads,
//! so the interface is synchronous; they reach the records and files only
//! through it.
//!
//! The embedded scheduler's [`Shared`] implements it over the data
//! directory. A worker of a distributed deployment implements it over the
//! shared backends (`worker::host::RemoteHost`: PostgreSQL and the object
//! store), fetching what a job reads into a local cache and fencing what it
//! publishes with its lease.

use std::io;
use std::path::{Path, PathBuf};

use super::{Counters, Job, JobSpec, SchedulerConfig, Shared};
use crate::datadir::{Local, ScenePart, write_json};
use crate::engine::front::write_atomic;
use crate::records::{ModelInfo, SceneInfo, VideoInfo};

/// A job body's view of the service (see the module comment).
pub(crate) trait JobHost: Send + Sync {
    fn config(&self) -> &SchedulerConfig;

    /// The training counters of /metrics.
    fn counters(&self) -> &Counters;

    /// Updates the job's progress as clients see it (not persisted).
    fn set_progress(&self, job_id: &str, f: &mut dyn FnMut(&mut Job));

    fn scene(&self, id: &str) -> io::Result<Option<SceneInfo>>;

    fn model(&self, id: &str) -> io::Result<Option<ModelInfo>>;

    /// A folder laid out as the scene's folder holding at least `part`: a
    /// ready scene's dataset is `<path>/<scene.root>`.
    fn scene_dir(&self, scene: &SceneInfo, part: ScenePart) -> io::Result<Local>;

    /// The checkpoint a training job's session reads (when it resumes) and
    /// saves to.
    fn job_checkpoint(&self, job: &Job, model_id: &str) -> io::Result<PathBuf>;

    /// Publishes the record of the checkpoint the session just saved at
    /// `ckpt`; the model's record never points at a checkpoint not saved.
    fn publish_model(&self, job: &Job, info: &ModelInfo, ckpt: &Path) -> io::Result<()>;

    /// A model's checkpoint, to load (video jobs).
    fn model_checkpoint(&self, info: &ModelInfo) -> io::Result<Local>;

    /// Publishes a video: its bytes, then its record, so a record always
    /// names a whole video.
    fn publish_video(&self, job: &Job, info: &VideoInfo, bytes: &[u8]) -> io::Result<()>;

    /// Where a video job keeps the frames it rendered, so that a restart
    /// after a crash renders only the rest (`None`: not kept). Removed when
    /// the job ends.
    fn video_frames_dir(&self, _job: &Job) -> Option<PathBuf> {
        None
    }

    /// The folder a pose estimation works in: the scene's folder, holding
    /// the photos in `upload/`; the dataset is written to `data/` beside them.
    fn posing_workdir(&self, job: &Job, scene: &SceneInfo) -> io::Result<PathBuf>;

    /// Publishes a posed scene: its `ready` record (for the dataset in
    /// `workdir/data/`), after which the uploaded photos go.
    fn publish_posed_scene(&self, job: &Job, ready: &SceneInfo, workdir: &Path) -> io::Result<()>;

    /// Enqueues a job under the id `id` (a training job's bake); a job of
    /// that id already queued or run (this job enqueued it in a run before)
    /// is not enqueued again.
    fn enqueue(&self, id: String, spec: JobSpec, memory_estimate: u64) -> Result<(), String>;
}

/// The embedded scheduler's host: the data directory, in place.
impl JobHost for Shared {
    fn config(&self) -> &SchedulerConfig {
        &self.config
    }

    fn counters(&self) -> &Counters {
        &self.counters
    }

    fn set_progress(&self, job_id: &str, f: &mut dyn FnMut(&mut Job)) {
        if let Some(j) = self.lock().jobs.get_mut(job_id) {
            f(j);
        }
    }

    fn scene(&self, id: &str) -> io::Result<Option<SceneInfo>> {
        self.storage.load_scene(id)
    }

    fn model(&self, id: &str) -> io::Result<Option<ModelInfo>> {
        self.storage.load_model(id)
    }

    fn scene_dir(&self, scene: &SceneInfo, _part: ScenePart) -> io::Result<Local> {
        Ok(Local::at(self.storage.scene_dir(&scene.id)))
    }

    /// `models/ID.ckpt`: the session saves it in place, atomically.
    fn job_checkpoint(&self, _job: &Job, model_id: &str) -> io::Result<PathBuf> {
        Ok(self.storage.checkpoint(model_id))
    }

    /// The checkpoint is already in place: writes `models/ID.json`.
    fn publish_model(&self, _job: &Job, info: &ModelInfo, _ckpt: &Path) -> io::Result<()> {
        write_json(&self.storage.model_record(&info.id), info).map_err(|e| context(e, "saving the model record"))
    }

    fn model_checkpoint(&self, info: &ModelInfo) -> io::Result<Local> {
        Ok(Local::at(self.storage.checkpoint(&info.id)))
    }

    /// `videos/ID.bin`, then `videos/ID.json`, each atomically.
    fn publish_video(&self, _job: &Job, info: &VideoInfo, bytes: &[u8]) -> io::Result<()> {
        write_atomic(&self.storage.video_file(&info.id), bytes).map_err(|e| context(e, "saving the video"))?;
        write_json(&self.storage.video_record(&info.id), info).map_err(|e| context(e, "saving the video record"))
    }

    fn posing_workdir(&self, _job: &Job, scene: &SceneInfo) -> io::Result<PathBuf> {
        Ok(self.storage.scene_dir(&scene.id))
    }

    /// `videos/.frames-JOB/`.
    fn video_frames_dir(&self, job: &Job) -> Option<PathBuf> {
        Some(self.storage.video_frames_dir(&job.id))
    }

    /// Rewrites `scenes/ID/scene.json` (the dataset is already in place in
    /// the scene's folder), then removes the photos as uploaded: they are in
    /// `data/images` now, downscaled as trained on.
    fn publish_posed_scene(&self, _job: &Job, ready: &SceneInfo, workdir: &Path) -> io::Result<()> {
        write_json(&self.storage.scene_record(&ready.id), ready)?;
        let _ = std::fs::remove_dir_all(workdir.join(ScenePart::Upload.dir_name()));
        Ok(())
    }

    fn enqueue(&self, id: String, spec: JobSpec, memory_estimate: u64) -> Result<(), String> {
        if self.lock().jobs.contains_key(&id) {
            return Ok(());
        }
        self.enqueue_as(id, spec, None, memory_estimate).map(|_| ()).map_err(|e| e.to_string())
    }
}

/// `e` with what was being done, keeping its kind.
fn context(e: io::Error, doing: &str) -> io::Error {
    io::Error::new(e.kind(), format!("{doing}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::datadir::{DataDir, now_ms};
    use crate::jobs::{JobProgress, JobSpec, PosesSpec, Scheduler, Status, VideoSpec};
    use crate::media::video::VideoFormat;
    use crate::records::{SceneStatus, sample_scene};

    /// A scheduler that starts no jobs, over a fresh data directory.
    fn scheduler(dir: &Path) -> Scheduler {
        let storage = DataDir::open(dir).unwrap();
        Scheduler::open(storage, SchedulerConfig { run_jobs: false, ..Default::default() }).unwrap()
    }

    fn job(spec: JobSpec) -> Job {
        Job {
            id: "job_a".into(),
            seq: 0,
            status: Status::Running,
            spec,
            created_at: now_ms(),
            started_at: None,
            finished_at: None,
            error: None,
            model_id: None,
            video_id: None,
            progress: JobProgress::default(),
            attempts: 1,
            memory_estimate_bytes: 0,
            crashes: 0,
        }
    }

    fn video_job() -> Job {
        let spec = VideoSpec {
            frames: 1,
            fps: 1,
            width: 16,
            height: 16,
            elevation: 0.0,
            radius: 1.0,
            fov: 40.0,
            format: VideoFormat::Gif,
            path: None,
            appearance: Default::default(),
        };
        Job { model_id: Some("mdl_a".into()), ..job(JobSpec::Video(spec)) }
    }

    #[test]
    fn a_video_is_published_file_first_and_never_as_a_record_alone() {
        let dir = tempfile::tempdir().unwrap();
        let sched = scheduler(dir.path());
        let host: &dyn JobHost = &*sched.shared;
        let (job, storage) = (video_job(), DataDir { root: dir.path().to_path_buf() });
        let info = VideoInfo {
            id: job.reserved_video_id(),
            model_id: "mdl_a".into(),
            job_id: job.id.clone(),
            format: VideoFormat::Gif,
            frames: 1,
            fps: 1,
            width: 16,
            height: 16,
            size_bytes: 3,
            created_at: now_ms(),
        };
        host.publish_video(&job, &info, b"GIF").unwrap();
        assert_eq!(std::fs::read(storage.video_file(&info.id)).unwrap(), b"GIF");
        assert_eq!(storage.load_video(&info.id).unwrap().map(|v| v.size_bytes), Some(3));

        // The file cannot be written (its folder is gone): no record, and
        // the error says what failed.
        std::fs::remove_dir_all(storage.videos_dir()).unwrap();
        let e = host.publish_video(&job, &info, b"GIF").unwrap_err();
        assert!(e.to_string().starts_with("saving the video: "), "{e}");
        std::fs::create_dir_all(storage.videos_dir()).unwrap();
        assert!(storage.load_video(&info.id).unwrap().is_none());
        sched.shutdown();
    }

    #[test]
    fn a_posed_scene_is_published_in_place_and_its_photos_go() {
        let dir = tempfile::tempdir().unwrap();
        let sched = scheduler(dir.path());
        let host: &dyn JobHost = &*sched.shared;
        let storage = DataDir { root: dir.path().to_path_buf() };
        let posing = SceneInfo { status: SceneStatus::Posing, ..sample_scene("scn_a") };
        let upload = storage.scene_dir("scn_a").join(ScenePart::Upload.dir_name());
        std::fs::create_dir_all(&upload).unwrap();
        std::fs::write(upload.join("a.jpg"), b"jpeg").unwrap();
        write_json(&storage.scene_record("scn_a"), &posing).unwrap();

        let job = job(JobSpec::Poses(PosesSpec { scene_id: "scn_a".into() }));
        let workdir = host.posing_workdir(&job, &posing).unwrap();
        assert_eq!(workdir, storage.scene_dir("scn_a"));
        let ready = sample_scene("scn_a");
        host.publish_posed_scene(&job, &ready, &workdir).unwrap();
        assert_eq!(host.scene("scn_a").unwrap().map(|s| s.status), Some(SceneStatus::Ready));
        assert!(!upload.exists());
        // The dataset of a ready scene is read where its record says.
        let data = host.scene_dir(&ready, ScenePart::Data).unwrap();
        assert_eq!(data.path.join(&ready.root), storage.scene_dir("scn_a").join("data"));
        sched.shutdown();
    }
}
