//! The PostgreSQL [`JobStore`]: the API's view of a queue many nodes share.
//! Every call is one statement or one transaction of [`PgQueue`] (see
//! `queue` and `records`), so any API node answers the same; jobs run on
//! workers, which take them through `PgQueue`'s claim and leases.
//!
//! Where it differs from the embedded store, and why:
//!
//! - Deleting a scene, model or video removes its record only. The files
//!   belong to the artifact store, which this store cannot reach: the API's
//!   delete handlers remove them once the record is gone
//!   (`ArtifactStore::remove`).
//! - Canceling a running job sets `cancel_requested` and answers the job
//!   still `running`; its worker sees the request at its next heartbeat (or
//!   at once from the NOTIFY), stops, and records it `canceled`.
//! - Progress is what the worker's last heartbeat wrote (about once a
//!   second), not the step the job is at this instant.
//! - No jobs run in this process: [`JobStore::counters`] is `None`.

use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use tokio::sync::broadcast::error::RecvError;

use super::changes::Changes;
use super::connect::Database;
use super::error::PgError;
use super::migrate;
use super::queue::{PgQueue, QueueConfig};
use crate::backend::{Fut, JobStore, NewJob, QueueStats};
use crate::jobs::{Counters, Job, SchedError, Status};
use crate::records::{CropBox, ModelInfo, SceneInfo, VideoInfo};

/// How long a follower of a job waits for a notice of its change before it
/// reads the job again anyway (notices can be lost; see `changes`); the
/// default of [`PgJobStore::with_change_fallback`].
pub const CHANGE_FALLBACK: Duration = Duration::from_secs(1);

/// How long the readiness probe waits for the database's answer.
pub const READY_WITHIN: Duration = Duration::from_secs(1);

/// Settings of a PostgreSQL job store.
#[derive(Clone, Debug)]
pub struct PgStoreConfig {
    /// Connections in the pool (`--db-pool-size`).
    pub pool_size: usize,
    /// The queue's limits.
    pub queue: QueueConfig,
}

impl Default for PgStoreConfig {
    /// 8 connections (the design's default) and the embedded queue's limit.
    fn default() -> Self {
        Self { pool_size: 8, queue: QueueConfig::default() }
    }
}

/// The job store over a PostgreSQL database: the queue and the change feed.
pub struct PgJobStore {
    queue: PgQueue,
    changes: Changes,
    /// How long `job_changed` waits for a notice ([`CHANGE_FALLBACK`]).
    change_fallback: Duration,
    /// Set by `shutdown`: the store answers nothing more.
    closed: AtomicBool,
}

impl PgJobStore {
    /// Brings the database's schema to this binary's (`migrate`), opens the
    /// pool and starts listening for job changes. An unreachable server,
    /// refused credentials or a schema this binary cannot use are an error
    /// here, at start-up.
    pub async fn open(db: &Database, config: PgStoreConfig) -> Result<PgJobStore, PgError> {
        migrate::migrate(db).await?;
        let pool = db.pool(config.pool_size).await?;
        let changes = Changes::start(db).await?;
        Ok(PgJobStore {
            queue: PgQueue::new(pool, config.queue),
            changes,
            change_fallback: CHANGE_FALLBACK,
            closed: AtomicBool::new(false),
        })
    }

    /// The store with followers' fallback wait set to `fallback` instead of
    /// [`CHANGE_FALLBACK`] (tests set it long, to tell a notice from it).
    pub fn with_change_fallback(mut self, fallback: Duration) -> Self {
        self.change_fallback = fallback;
        self
    }

    /// The queue itself, for a worker in this process (claims, leases).
    pub fn queue(&self) -> &PgQueue {
        &self.queue
    }

    /// Whether the database answers within [`READY_WITHIN`] and holds every
    /// migration this binary knows (a newer schema is fine: migrations are
    /// additive).
    async fn check_ready(&self) -> io::Result<()> {
        if self.closed.load(Ordering::SeqCst) {
            return Err(io::Error::other("the PostgreSQL job store was shut down"));
        }
        let version = tokio::time::timeout(READY_WITHIN, self.queue.schema_version())
            .await
            .map_err(|_| {
                io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!("PostgreSQL did not answer within {} s", READY_WITHIN.as_secs_f64()),
                )
            })?
            .map_err(to_io)?;
        let needed = migrate::newest_version();
        if version < needed {
            return Err(io::Error::other(format!(
                "the database schema is at migration {version}; this binary needs migration {needed}"
            )));
        }
        Ok(())
    }
}

/// A store error as the API's refusal: the embedded store's own when it is
/// one (not found, in use, full...), an invalid argument, or an I/O error
/// saying what failed (answered 500, details logged).
fn to_sched(e: PgError) -> SchedError {
    match e {
        PgError::Refused(e) => e,
        e => SchedError::Io(to_io(e)),
    }
}

/// A store error as an I/O error: `InvalidInput` for a bad argument.
fn to_io(e: PgError) -> io::Error {
    match e {
        PgError::Invalid(m) => io::Error::new(io::ErrorKind::InvalidInput, m),
        PgError::Refused(SchedError::Io(e)) => e,
        e => io::Error::other(e.to_string()),
    }
}

impl JobStore for PgJobStore {
    fn enqueue(&self, job: NewJob) -> Fut<'_, Result<Job, SchedError>> {
        Box::pin(async move { self.queue.enqueue(job).await.map_err(to_sched) })
    }

    fn get_job<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<Job>>> {
        Box::pin(async move { self.queue.get(id).await.map_err(to_io) })
    }

    fn list_jobs(&self, status: Option<Status>) -> Fut<'_, io::Result<Vec<Job>>> {
        Box::pin(async move { self.queue.list(status).await.map_err(to_io) })
    }

    fn stats(&self) -> Fut<'_, io::Result<QueueStats>> {
        Box::pin(async move {
            let by_status = self.queue.count_by_status().await.map_err(to_io)?;
            let queued = by_status.get(&Status::Queued).copied().unwrap_or(0);
            Ok(QueueStats { by_status, queued })
        })
    }

    /// A running job is answered `running` with `cancel_requested` set in
    /// the database; see the module comment.
    fn cancel<'a>(&'a self, id: &'a str) -> Fut<'a, Result<Job, SchedError>> {
        Box::pin(async move { self.queue.cancel(id).await.map_err(to_sched) })
    }

    fn delete_job<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        Box::pin(async move { self.queue.delete_job(id).await.map_err(to_sched) })
    }

    /// Resolves at the first notice of a change of job `id` after this
    /// call, when notices were missed (a lagging follower), or after the
    /// fallback wait ([`CHANGE_FALLBACK`] unless set otherwise), whichever
    /// comes first.
    fn job_changed<'a>(&'a self, id: &'a str) -> Fut<'a, ()> {
        // Subscribed now, not at the first poll: a change made between this
        // call and the first poll is not missed.
        let mut ids = self.changes.subscribe();
        let fallback = self.change_fallback;
        Box::pin(async move {
            let notice = async {
                loop {
                    match ids.recv().await {
                        Ok(changed) if changed == id => return,
                        Ok(_) => {}
                        Err(RecvError::Lagged(_)) => return,
                        // The feed stopped (shut down): only the fallback is left.
                        Err(RecvError::Closed) => std::future::pending::<()>().await,
                    }
                }
            };
            let _ = tokio::time::timeout(fallback, notice).await;
        })
    }

    fn insert_scene(&self, scene: SceneInfo, poses_job: Option<NewJob>) -> Fut<'_, Result<Option<Job>, SchedError>> {
        Box::pin(async move { self.queue.insert_scene(&scene, poses_job).await.map_err(to_sched) })
    }

    fn get_scene<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<SceneInfo>>> {
        Box::pin(async move { self.queue.scene(id).await.map_err(to_io) })
    }

    fn list_scenes(&self) -> Fut<'_, io::Result<Vec<SceneInfo>>> {
        Box::pin(async move { self.queue.list_scenes().await.map_err(to_io) })
    }

    /// The record only: see the module comment.
    fn delete_scene<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        Box::pin(async move { self.queue.delete_scene(id).await.map_err(to_sched) })
    }

    fn get_model<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<ModelInfo>>> {
        Box::pin(async move { self.queue.model(id).await.map_err(to_io) })
    }

    fn list_models(&self) -> Fut<'_, io::Result<Vec<ModelInfo>>> {
        Box::pin(async move { self.queue.list_models().await.map_err(to_io) })
    }

    /// The record only: see the module comment.
    fn delete_model<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        Box::pin(async move { self.queue.delete_model(id).await.map_err(to_sched) })
    }

    fn set_crop<'a>(&'a self, id: &'a str, crop: Option<CropBox>) -> Fut<'a, Result<ModelInfo, SchedError>> {
        Box::pin(async move { self.queue.set_crop(id, crop).await.map_err(to_sched) })
    }

    fn get_video<'a>(&'a self, id: &'a str) -> Fut<'a, io::Result<Option<VideoInfo>>> {
        Box::pin(async move { self.queue.video(id).await.map_err(to_io) })
    }

    fn list_videos(&self) -> Fut<'_, io::Result<Vec<VideoInfo>>> {
        Box::pin(async move { self.queue.list_videos().await.map_err(to_io) })
    }

    /// The record only: see the module comment.
    fn delete_video<'a>(&'a self, id: &'a str) -> Fut<'a, Result<(), SchedError>> {
        Box::pin(async move { self.queue.delete_video(id).await.map_err(to_sched) })
    }

    /// No jobs run in this process.
    fn counters(&self) -> Option<&Counters> {
        None
    }

    fn ready(&self) -> Fut<'_, io::Result<()>> {
        Box::pin(self.check_ready())
    }

    /// Stops the change feed and closes the pool: later calls fail. Jobs
    /// run on workers, which stop on their own.
    fn shutdown(&self) -> Fut<'_, ()> {
        Box::pin(async move {
            self.closed.store(true, Ordering::SeqCst);
            self.changes.stop();
            self.queue.close();
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_pass_through_and_other_errors_say_what_failed() {
        let e = to_sched(PgError::Refused(SchedError::QueueFull(3)));
        assert!(matches!(e, SchedError::QueueFull(3)), "{e:?}");
        let e = to_sched(PgError::Invalid("'x' is not a valid job id".into()));
        match e {
            SchedError::Io(io) => {
                assert_eq!(io.kind(), io::ErrorKind::InvalidInput);
                assert_eq!(io.to_string(), "'x' is not a valid job id");
            }
            e => panic!("{e:?}"),
        }
        let e = to_io(PgError::Unavailable("pool timed out".into()));
        assert_eq!(
            (e.kind(), e.to_string()),
            (io::ErrorKind::Other, "the database is unavailable: pool timed out".into())
        );
        let taken = PgError::Refused(SchedError::Io(io::Error::other("job id 'job_1' is taken")));
        assert_eq!(to_io(taken).to_string(), "job id 'job_1' is taken");
    }
}
