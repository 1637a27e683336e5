//! Where the service's state lives, behind the two interfaces the API goes
//! through (docs/design/scale-out.md, section 2):
//!
//! - [`JobStore`]: the job queue as clients see it (enqueue, read, cancel,
//!   delete) and the records of scenes, models and videos;
//! - [`ArtifactStore`]: their bytes (uploaded datasets, checkpoints,
//!   videos).
//!
//! `embedded` implements both over one data directory with the scheduler,
//! its redb job database and the files beside it: the default, one node.
//! `pg` is the PostgreSQL job queue, and `pg::PgJobStore` the [`JobStore`]
//! over it for many nodes (`serve --database-url`). `object` is the
//! [`ArtifactStore`] over an object store (an S3 bucket or a folder) with a
//! local cache, for many nodes too (`serve --object-store`).
//!
//! Both interfaces are async (the API is tokio) and dyn-compatible: every
//! method returns a boxed future ([`Fut`]), so the API holds them as
//! `Arc<dyn JobStore>` and `Arc<dyn ArtifactStore>` whatever backs them.
//! The job bodies, which run on std threads, see the service through the
//! synchronous `jobs::host::JobHost` instead.

use std::collections::HashMap;
use std::io;
use std::path::{Path, PathBuf};

use crate::datadir::{DiskUsage, Local, ScenePart};
use crate::jobs::{Counters, Job, JobSpec, SchedError, Status};
use crate::records::{CropBox, ModelInfo, SceneInfo, VideoInfo};

pub mod embedded;
pub mod object;
pub mod pg;

/// The future every store method returns: boxed, so the traits are
/// dyn-compatible without `async-trait`.
pub type Fut<'a, T> = futures_util::future::BoxFuture<'a, T>;

/// A job to enqueue: what the API hands a job store.
#[derive(Clone, Debug)]
pub struct NewJob {
    /// The job's id, chosen by the caller (from `datadir::new_id("job")`)
    /// when a record must name the job first; `None`: a fresh one.
    pub id: Option<String>,
    pub spec: JobSpec,
    /// Video: the model rendered (training jobs start without one).
    pub model_id: Option<String>,
    /// Estimated peak memory of the job, bytes.
    pub memory_estimate: u64,
}

/// Jobs per status and the queue's depth (/metrics).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct QueueStats {
    /// Jobs of each status; a status no job has may be missing.
    pub by_status: HashMap<Status, usize>,
    /// Jobs waiting to run.
    pub queued: usize,
}

/// The jobs and the records of what they use and make. The refusals are
/// [`SchedError`]s, the same whichever store answers, so clients see the
/// same codes (404, 409, 503 `queue_full`).
pub trait JobStore: Send + Sync + 'static {
    /// Registers a job and answers with its queued record once that is
    /// durable. A training job needs a ready scene, a pose estimation its
    /// scene, a video job its model ([`NewJob::model_id`]); a full queue
    /// refuses (`QueueFull`).
    fn enqueue(&self, job: NewJob) -> Fut<'_, Result<Job, SchedError>>;

    fn get_job<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<Job>>>;

    /// Jobs in enqueue order, optionally of one status.
    fn list_jobs(&self, status: Option<Status>) -> Fut<'_, io::Result<Vec<Job>>>;

    fn stats(&self) -> Fut<'_, io::Result<QueueStats>>;

    /// Cancels a queued job at once (answering it `canceled`), or asks a
    /// running one to stop (answering it still `running`: it checkpoints
    /// and becomes `canceled` within about a training step).
    fn cancel<'a>(&'a self, id: &'a str) -> Fut<'a, Result<Job, SchedError>>;

    /// Removes a finished job's record; what it made stays. A queued or
    /// running job is refused (`JobNotFinal`): cancel it first.
    fn delete_job<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>>;

    /// Resolves when job `id` may have changed, or after a while: a hint
    /// for those following a job (its events), who read it again and
    /// compare. Never pending for long, so a follower cannot hang on it.
    fn job_changed<'a>(&'a self, id: &'a str) -> Fut<'a, ()>;

    /// Stores a scene's record: the commit point of an upload, whose files
    /// must have been put ([`ArtifactStore::put_scene_files`]) and become
    /// visible with it. With `poses_job` (a photo-only upload; its spec
    /// names this scene), the job that estimates the poses is queued with
    /// it: both or neither.
    fn insert_scene(&self, scene: SceneInfo, poses_job: Option<NewJob>) -> Fut<'_, Result<Option<Job>, SchedError>>;

    fn get_scene<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<SceneInfo>>>;

    /// Scenes by creation time.
    fn list_scenes(&self) -> Fut<'_, io::Result<Vec<SceneInfo>>>;

    /// Removes a scene (its record, then its files) unless a queued or
    /// running job uses it (`SceneInUse`). Models trained on it stay.
    fn delete_scene<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>>;

    fn get_model<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<ModelInfo>>>;

    /// Models by creation time.
    fn list_models(&self) -> Fut<'_, io::Result<Vec<ModelInfo>>>;

    /// Removes a model (its record, then its checkpoint) unless a queued or
    /// running job writes or renders it (`ModelInUse`). Videos made from it
    /// stay.
    fn delete_model<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>>;

    /// Sets (`Some`) or removes (`None`) a model's crop volume, bumping its
    /// `updated_at`; the record as it now is. Refused like a deletion
    /// (`ModelInUse`) while a queued or running job writes or renders the
    /// model, whose record or views would otherwise disagree with it.
    fn set_crop<'a>(&'a self, id: &'a str, crop: Option<CropBox>) -> Fut<'a, Result<ModelInfo, SchedError>>;

    fn get_video<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<VideoInfo>>>;

    /// Videos by creation time.
    fn list_videos(&self) -> Fut<'_, io::Result<Vec<VideoInfo>>>;

    /// Removes a video (its record, then its file) unless its job has not
    /// ended (`VideoInUse`).
    fn delete_video<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>>;

    /// The training counters of the jobs this process runs; `None` on a
    /// node that runs none.
    fn counters(&self) -> Option<&Counters>;

    /// Whether the store can serve (/readyz); the error says what is wrong.
    fn ready(&self) -> Fut<'_, io::Result<()>>;

    /// Stops the jobs this process runs (they checkpoint, and resume at
    /// the next start) and lets go of the store.
    fn shutdown(&self) -> Fut<'_, ()>;
}

/// The bytes behind a record the [`JobStore`] deleted, for
/// [`ArtifactStore::remove`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Artifact<'a> {
    /// Every part of scene `id` (its dataset, its uploaded photos).
    Scene(&'a str),
    /// Every checkpoint of model `id`.
    Model(&'a str),
    /// Video `id`'s file.
    Video(&'a str),
}

/// The bytes of scenes, models and videos. Their records are the
/// [`JobStore`]'s: an artifact is visible once its record is.
pub trait ArtifactStore: Send + Sync + 'static {
    /// A local folder, not yet created, where an upload of scene `id` is
    /// written and checked before it is stored.
    fn staging_dir(&self, id: &str) -> PathBuf;

    /// Stores `files` (a local folder in `staging_dir(id)`) as `part` of
    /// scene `id`. Nothing is visible until [`JobStore::insert_scene`]
    /// stores the record.
    fn put_scene_files<'a>(&'a self, id: &'a str, part: ScenePart, files: &'a Path) -> Fut<'a, io::Result<()>>;

    /// A local folder laid out as the scene's folder, holding at least
    /// `part`: a ready scene's dataset is `<path>/<scene.root>`.
    fn scene_files<'a>(&'a self, scene: &'a SceneInfo, part: ScenePart) -> Fut<'a, io::Result<Local>>;

    /// A model's checkpoint as a local file.
    fn checkpoint<'a>(&'a self, model: &'a ModelInfo) -> Fut<'a, io::Result<Local>>;

    /// A video's bytes.
    fn video<'a>(&'a self, video: &'a VideoInfo) -> Fut<'a, io::Result<Vec<u8>>>;

    /// Bytes stored, by kind (/metrics).
    fn usage(&self) -> Fut<'_, io::Result<DiskUsage>>;

    /// Free space for new outputs, when the store is bounded by one (a
    /// job whose outputs would not fit is refused); `None` when it is not
    /// known.
    fn free_space(&self) -> Fut<'_, io::Result<Option<u64>>>;

    /// Whether the store can serve (/readyz); the error says what is wrong.
    fn ready(&self) -> Fut<'_, io::Result<()>>;

    /// Removes the bytes behind a record the [`JobStore`] has just deleted
    /// (record first: a delete it refuses, such as a scene a queued job
    /// uses, must leave the bytes). What is already gone is no error. The
    /// embedded job store deletes its files with their records, so the
    /// embedded artifact store has nothing left to do.
    fn remove<'a>(&'a self, what: Artifact<'a>) -> Fut<'a, io::Result<()>>;
}
