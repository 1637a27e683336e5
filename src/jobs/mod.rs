//! Jobs: their records and states (`job`), their journal in the job database (`journal`),
//! and the scheduler that runs at most `max_concurrent` of them at once.
//! The job bodies (`train`, `video`, `poses`, `bake`) reach the service only
//! through [`host::JobHost`], which the scheduler's shared state implements.
//!
//! Only the enqueued, started, interrupted (written back as queued by a
//! clean shutdown) and final states are written to disk (the job database,
//! one committed transaction each, written outside the scheduler's lock:
//! see `journal`): progress lives in memory. On start-up a
//! job found `queued` or `running` is queued again in its original order; a
//! training job whose checkpoint exists resumes from it. One found `running`
//! was cut short by the process dying: see [`MAX_CRASHES`].

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::io;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::datadir::{DataDir, new_id, now_ms};
use crate::poses::PoseError;
use crate::records::{SceneInfo, SceneStatus};
pub use error::JobError;
use host::JobHost;
pub use job::{
    BakeAfter, BakeSpec, Job, JobBudget, JobProgress, JobSpec, PosesSpec, Status, TrainSpec, VideoSpec,
    reserved_model_id,
};
use journal::{Journal, Record};
pub(crate) use run::{Outcome, run_body};
use run::{scheduler_loop, settle_scene};

pub mod bake;
mod error;
pub(crate) mod host;
mod job;
mod journal;
mod lifecycle;
pub mod poses;
mod retention;
mod run;
pub mod scoring;
pub mod train;
pub mod video;

/// Scheduler settings.
#[derive(Clone, Debug)]
pub struct SchedulerConfig {
    pub max_concurrent: usize,
    /// Queued jobs beyond this are refused (503).
    pub max_queued: usize,
    /// Seconds of training between checkpoints.
    pub checkpoint_every: f64,
    /// Held-out views rendered to measure a finished model.
    pub eval_views: usize,
    /// Seconds of training between estimates of the held-out PSNR (spaced
    /// out further when an estimate would cost over a fifth of the time).
    pub heldout_every: f64,
    /// Whether to start jobs at all (tests enqueue with it off, then restart).
    pub run_jobs: bool,
    /// How long a model keeps its optimiser state after its training ended
    /// (then its checkpoint is rewritten without it; zero: at once).
    pub keep_training_state: Duration,
    /// Estimated peak memory one job may have (larger ones are refused).
    pub max_job_memory_bytes: u64,
    /// Estimated peak memory of all running jobs together: a job waits
    /// while starting it would pass this.
    pub memory_budget_bytes: u64,
    /// COLMAP (and ffmpeg) for photo-only uploads; `None` when missing, and
    /// such uploads are refused.
    pub poses: Option<poses::PosesSetup>,
}

impl Default for SchedulerConfig {
    fn default() -> Self {
        Self {
            max_concurrent: 1,
            max_queued: 100,
            checkpoint_every: 30.0,
            eval_views: 4,
            heldout_every: 10.0,
            run_jobs: true,
            keep_training_state: Duration::from_secs(24 * 3600),
            max_job_memory_bytes: default_memory_budget(),
            memory_budget_bytes: default_memory_budget(),
            poses: None,
        }
    }
}

/// The default memory budget for jobs: 80 % of the machine's memory (4 GiB
/// where it cannot be read), leaving room for the server, renders and the
/// page cache.
pub fn default_memory_budget() -> u64 {
    crate::system::total_memory().map_or(4 << 30, |t| t / 5 * 4)
}

/// Why a job could not be enqueued or a scene deleted.
#[derive(Debug, thiserror::Error)]
pub enum SchedError {
    #[error("scene '{0}' not found")]
    SceneNotFound(String),
    #[error("scene '{scene}' is {status}{}: only a ready scene can be trained on", reason.as_deref().map(|r| format!(" ({r})")).unwrap_or_default())]
    SceneNotReady { scene: String, status: &'static str, reason: Option<String> },
    #[error("the queue is full ({0} jobs waiting)")]
    QueueFull(usize),
    #[error("scene '{scene}' is used by job '{job}' ({status})")]
    SceneInUse { scene: String, job: String, status: &'static str },
    #[error("model '{0}' not found")]
    ModelNotFound(String),
    #[error("job '{0}' not found")]
    JobNotFound(String),
    #[error("job '{id}' is already {status}")]
    AlreadyFinal { id: String, status: &'static str },
    #[error("job '{id}' is {status}: cancel it first")]
    JobNotFinal { id: String, status: &'static str },
    #[error("model '{model}' is used by job '{job}' ({status})")]
    ModelInUse { model: String, job: String, status: &'static str },
    #[error("video '{0}' not found")]
    VideoNotFound(String),
    #[error("video '{video}' belongs to job '{job}', which is {status}")]
    VideoInUse { video: String, job: String, status: &'static str },
    #[error("{0}")]
    Io(#[from] io::Error),
}

/// A training job needs a ready scene: a posing or failed one is refused,
/// saying why (the same answer whichever store holds the queue).
pub(crate) fn check_trainable(scene: &SceneInfo) -> Result<(), SchedError> {
    if scene.status == SceneStatus::Ready {
        return Ok(());
    }
    let reason = match scene.status {
        SceneStatus::Posing => Some("its poses are being estimated".to_string()),
        _ => scene.error.clone(),
    };
    Err(SchedError::SceneNotReady { scene: scene.id.clone(), status: scene.status.name(), reason })
}

/// Counters for /metrics.
#[derive(Default)]
pub struct Counters {
    pub train_steps: AtomicU64,
    pub train_rays: AtomicU64,
    /// Training time in microseconds.
    pub train_micros: AtomicU64,
}

struct Running {
    cancel: Arc<AtomicBool>,
    /// The client asked to cancel (as opposed to a shutdown).
    user_cancel: bool,
}

#[derive(Default)]
struct State {
    jobs: BTreeMap<String, Job>,
    /// Jobs being enqueued whose record is not yet committed: not listed nor
    /// run, but counted by the queue limit and by the checks of deletions.
    enqueuing: BTreeMap<String, Job>,
    queue: VecDeque<String>,
    running: HashMap<String, Running>,
    threads: Vec<JoinHandle<()>>,
    next_seq: u64,
    /// The revision of the last record handed out (see `journal`).
    rev: u64,
    shutting_down: bool,
}

impl State {
    /// A record of `job` as it is now, to write once the lock is released.
    fn record(&mut self, job: Job) -> Record {
        self.rev += 1;
        Record { rev: self.rev, job }
    }

    /// Queued, running and enqueuing jobs.
    fn active(&self) -> impl Iterator<Item = &Job> {
        self.jobs.values().filter(|j| !j.status.is_final()).chain(self.enqueuing.values())
    }
}

pub(crate) struct Shared {
    state: Mutex<State>,
    wake: Condvar,
    storage: DataDir,
    /// The job database, written outside `state`'s lock.
    journal: Journal,
    config: SchedulerConfig,
    pub counters: Counters,
    /// Held while a model's files change outside its training job (deleted,
    /// or stripped of its optimiser state); taken before `state`.
    model_files: Mutex<()>,
    /// A job ended: the retention sweep runs at the next tick.
    sweep_requested: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Writes a record where a failure cannot be answered to a client:
    /// logged, and the job goes on (as before a restart would show).
    fn persist_logged(&self, record: &Record, what: &str) {
        if let Err(e) = self.journal.put(record) {
            tracing::error!(job = %record.job.id, error = %e, "cannot persist the job's {what}");
        }
    }
}

/// The job queue and its scheduler thread.
#[derive(Clone)]
pub struct Scheduler {
    shared: Arc<Shared>,
    thread: Arc<Mutex<Option<JoinHandle<()>>>>,
}

impl Scheduler {
    /// Loads the job records, removes checkpoints and videos that have no
    /// record and no job to write them (`retention`), and starts the
    /// scheduler thread.
    pub fn open(storage: DataDir, config: SchedulerConfig) -> io::Result<Self> {
        let mut st = State::default();
        let (killed, removed) = poses::clean_up_after_crash(&storage);
        if killed + removed > 0 {
            tracing::info!(processes = killed, folders = removed, "cleaned up after a pose estimation cut short");
        }
        let (journal, mut jobs) = Journal::open(&storage)?;
        jobs.sort_by_key(|j| j.seq);
        for mut j in jobs {
            st.next_seq = st.next_seq.max(j.seq + 1);
            if j.status == Status::Running {
                count_crash(&storage, &mut j);
                journal.put(&st.record(j.clone()))?;
            }
            if !j.status.is_final() {
                // It was waiting or interrupted: run it again, in order.
                j.status = Status::Queued;
                st.queue.push_back(j.id.clone());
            }
            st.jobs.insert(j.id.clone(), j);
        }
        for path in retention::remove_orphans(&storage, &st.jobs)? {
            tracing::info!(path = %path, "removed a file without a record");
        }
        // Scenes still posing whose job ended (or never was queued).
        for scene in storage.list_scenes()?.into_iter().filter(|s| s.status == SceneStatus::Posing) {
            let job = scene.poses.as_ref().and_then(|p| st.jobs.get(&p.job_id));
            if job.is_none_or(|j| j.status.is_final()) {
                poses::settle(&storage, &scene.id, job);
            }
        }
        let shared = Arc::new(Shared {
            state: Mutex::new(st),
            wake: Condvar::new(),
            storage,
            journal,
            config,
            counters: Counters::default(),
            model_files: Mutex::new(()),
            sweep_requested: AtomicBool::new(false),
        });
        let s2 = shared.clone();
        let handle = std::thread::Builder::new().name("scheduler".into()).spawn(move || scheduler_loop(&s2))?;
        Ok(Self { shared, thread: Arc::new(Mutex::new(Some(handle))) })
    }

    pub fn counters(&self) -> &Counters {
        &self.shared.counters
    }

    /// Registers a job and answers with its queued record, once that is
    /// committed. A training job needs its scene; a video job needs a model
    /// (`model_id`).
    pub fn enqueue(&self, spec: JobSpec, model_id: Option<String>, memory_estimate: u64) -> Result<Job, SchedError> {
        self.enqueue_as(new_id("job"), spec, model_id, memory_estimate)
    }

    /// [`Self::enqueue`] with the job's id chosen by the caller (from
    /// `datadir::new_id("job")`), for records that must name the job before
    /// it can start.
    pub fn enqueue_as(
        &self,
        id: String,
        spec: JobSpec,
        model_id: Option<String>,
        memory_estimate: u64,
    ) -> Result<Job, SchedError> {
        self.shared.enqueue_as(id, spec, model_id, memory_estimate)
    }
}

/// The enqueueing of [`Scheduler::enqueue_as`], on the shared state: job
/// bodies enqueue too (a training job its bake: `JobHost::enqueue`).
impl Shared {
    pub(crate) fn enqueue_as(
        &self,
        id: String,
        spec: JobSpec,
        model_id: Option<String>,
        memory_estimate: u64,
    ) -> Result<Job, SchedError> {
        let record = self.reserve(id, spec, model_id, memory_estimate)?;
        // Outside the lock; the job is `enqueuing` meanwhile, so deleting its
        // scene or model is refused as when it is queued.
        let written = self.journal.put(&record);
        let mut st = self.lock();
        let job = st.enqueuing.remove(&record.job.id).unwrap_or(record.job);
        written?;
        // In enqueue order, should a later enqueue have committed first.
        let at =
            st.queue.iter().position(|q| st.jobs.get(q).is_some_and(|j| j.seq > job.seq)).unwrap_or(st.queue.len());
        st.queue.insert(at, job.id.clone());
        st.jobs.insert(job.id.clone(), job.clone());
        drop(st);
        self.wake.notify_all();
        Ok(job)
    }

    /// Checks an enqueue under the lock and holds the new job as
    /// `enqueuing`; its record is to be written.
    fn reserve(
        &self,
        id: String,
        spec: JobSpec,
        model_id: Option<String>,
        memory_estimate: u64,
    ) -> Result<Record, SchedError> {
        let mut st = self.lock();
        let storage = &self.storage;
        match &spec {
            JobSpec::Train(t) => {
                let scene =
                    storage.load_scene(&t.scene_id)?.ok_or_else(|| SchedError::SceneNotFound(t.scene_id.clone()))?;
                check_trainable(&scene)?;
            }
            JobSpec::Poses(p) => {
                if storage.load_scene(&p.scene_id)?.is_none() {
                    return Err(SchedError::SceneNotFound(p.scene_id.clone()));
                }
            }
            JobSpec::Video(_) => {
                let id = model_id.clone().unwrap_or_default();
                if storage.load_model(&id)?.is_none() {
                    return Err(SchedError::ModelNotFound(id));
                }
            }
            JobSpec::Bake(b) => bake::check_source(&storage.load_model(&b.source_model_id)?, b)?,
        }
        let waiting = st.queue.len() + st.enqueuing.len();
        if waiting >= self.config.max_queued {
            return Err(SchedError::QueueFull(waiting));
        }
        if st.jobs.contains_key(&id) || st.enqueuing.contains_key(&id) {
            return Err(SchedError::Io(io::Error::other(format!("job id '{id}' is taken"))));
        }
        let job = Job {
            id,
            seq: st.next_seq,
            status: Status::Queued,
            spec,
            created_at: now_ms(),
            started_at: None,
            finished_at: None,
            error: None,
            model_id,
            video_id: None,
            progress: JobProgress::default(),
            attempts: 0,
            memory_estimate_bytes: memory_estimate,
            crashes: 0,
        };
        st.next_seq += 1;
        st.enqueuing.insert(job.id.clone(), job.clone());
        Ok(st.record(job))
    }
}

impl Scheduler {
    pub fn get(&self, id: &str) -> Option<Job> {
        self.shared.lock().jobs.get(id).cloned()
    }

    /// Jobs in enqueue order, optionally of one status.
    pub fn list(&self, status: Option<Status>) -> Vec<Job> {
        let st = self.shared.lock();
        let mut v: Vec<Job> = st.jobs.values().filter(|j| status.is_none_or(|s| j.status == s)).cloned().collect();
        v.sort_by_key(|j| j.seq);
        v
    }

    /// Jobs per status and the queue depth.
    pub fn stats(&self) -> (HashMap<Status, usize>, usize) {
        let st = self.shared.lock();
        let mut m = HashMap::new();
        for j in st.jobs.values() {
            *m.entry(j.status).or_insert(0) += 1;
        }
        (m, st.queue.len())
    }

    /// Cancels a queued job at once, or asks a running one to stop (it
    /// checkpoints and becomes `canceled` within about a step).
    pub fn cancel(&self, id: &str) -> Result<Job, SchedError> {
        let record = {
            let mut st = self.shared.lock();
            let Some(status) = st.jobs.get(id).map(|j| j.status) else {
                return Err(SchedError::JobNotFound(id.into()));
            };
            match status {
                s if s.is_final() => return Err(SchedError::AlreadyFinal { id: id.into(), status: s.name() }),
                Status::Running => {
                    if let Some(r) = st.running.get_mut(id) {
                        r.user_cancel = true;
                        r.cancel.store(true, Ordering::SeqCst);
                    }
                    return Ok(st.jobs[id].clone());
                }
                _ => {
                    st.queue.retain(|q| q != id);
                    let job = st.jobs.get_mut(id).expect("checked above");
                    job.status = Status::Canceled;
                    job.finished_at = Some(now_ms());
                    let job = job.clone();
                    st.record(job)
                }
            }
        };
        self.shared.journal.put(&record)?;
        settle_scene(&self.shared, &record.job);
        Ok(record.job)
    }

    /// Runs `delete` (which removes the scene) unless a queued or running
    /// job uses the scene; holding the lock so no job can be enqueued on it
    /// meanwhile.
    pub fn delete_scene(&self, scene_id: &str, delete: impl FnOnce() -> io::Result<()>) -> Result<(), SchedError> {
        let st = self.shared.lock();
        if let Some(j) = st.active().find(|j| j.spec.scene_id() == Some(scene_id)) {
            return Err(SchedError::SceneInUse { scene: scene_id.into(), job: j.id.clone(), status: j.status.name() });
        }
        delete()?;
        Ok(())
    }

    /// Whether the job database is open and answers a read (for readiness
    /// probes): an error once it is closed at shutdown, or when redb cannot
    /// start a read.
    pub fn check_database(&self) -> io::Result<()> {
        self.shared.journal.check()
    }

    /// Stops the scheduler: running jobs checkpoint and stay `running` on
    /// disk (they resume at the next start). Blocks until they have.
    pub fn shutdown(&self) {
        {
            let mut st = self.shared.lock();
            st.shutting_down = true;
            for r in st.running.values() {
                r.cancel.store(true, Ordering::SeqCst);
            }
        }
        self.shared.wake.notify_all();
        if let Some(h) = self.thread.lock().unwrap_or_else(|e| e.into_inner()).take() {
            let _ = h.join();
        }
        let threads = std::mem::take(&mut self.shared.lock().threads);
        for t in threads {
            let _ = t.join();
        }
        // Every job thread has written its last record.
        self.shared.journal.close();
    }
}

/// Runs in a row that end with the process dying, without the job saving
/// anything new in between, before the job is failed rather than run again.
pub const MAX_CRASHES: u32 = 2;

/// A job found `running` at start-up: the process died while running it (a
/// clean shutdown writes it back as `queued`). Counts the crash, unless
/// the job saved a checkpoint since it started, which shows it was making
/// progress (a restart then resumes it); fails it at [`MAX_CRASHES`], so a
/// job that takes the process down (out of memory) cannot do so at every
/// start.
fn count_crash(storage: &DataDir, j: &mut Job) {
    let saved_since_start = match &j.spec {
        JobSpec::Train(_) | JobSpec::Bake(_) => storage
            .load_model(&j.reserved_model_id())
            .ok()
            .flatten()
            .is_some_and(|m| j.started_at.is_some_and(|s| m.updated_at > s)),
        JobSpec::Poses(p) => poses::saved_progress_since(storage, &p.scene_id, j.started_at),
        JobSpec::Video(_) => video::saved_frames_since(storage, &j.id, j.started_at),
    };
    j.crashes = crashes_after(j.crashes, saved_since_start);
    if j.crashes >= MAX_CRASHES {
        j.status = Status::Failed;
        j.finished_at = Some(now_ms());
        j.error = Some(format!(
            "the server process died {} times in a row while running this job, without the job saving progress \
             in between (killed, or out of memory?); it is not run again",
            j.crashes
        ));
        tracing::error!(job = %j.id, crashes = j.crashes, "job failed: it crashed the server repeatedly");
    }
}

/// The crash count after a run cut short by its process dying: back to one
/// if the run saved progress (a checkpoint), else one more. The rule of
/// every store of the queue.
pub(crate) fn crashes_after(crashes: u32, saved_during_run: bool) -> u32 {
    if saved_during_run { 1 } else { crashes.saturating_add(1) }
}
