//! Workers of a distributed deployment (docs/design/scale-out.md, section
//! 2.3): a node with `--role worker` (or `all` over a database) takes jobs
//! from the PostgreSQL queue and runs them with the same job bodies the
//! embedded scheduler runs, over the shared stores.
//!
//! - `claim`: the claim loop (reclaim expired leases, claim, wait on
//!   LISTEN/NOTIFY with a polling fallback);
//! - `run`: one claimed job on its own thread, its end recorded under the
//!   lease;
//! - `keeper`: the job's heartbeat and the self-fence of a worker that may
//!   have lost its lease;
//! - `host`: [`RemoteHost`](host::RemoteHost), the job bodies' `JobHost`
//!   over PostgreSQL and the object store.
//!
//! [`Worker::shutdown`] (SIGTERM) stops claiming, sets every running job's
//! stop flag (each checkpoints, publishes its model and is queued again,
//! `interrupted`), and waits for their threads.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use tokio::sync::{Notify, watch};

use crate::backend::object::ObjectArtifacts;
use crate::backend::pg::{Admission, Claimed, Database, PgQueue};
use crate::jobs::SchedulerConfig;

mod claim;
mod host;
mod keeper;
mod run;
mod stats;

pub use keeper::{FENCE_AFTER, heartbeat_every};
pub use stats::WorkerStats;

/// What a worker needs to run.
pub struct WorkerConfig {
    /// Its id in leases and `job_runs` (`--node-id`).
    pub node: String,
    /// How long a lease lasts without a heartbeat (`--lease-seconds`).
    pub lease: Duration,
    /// Its limits (concurrency, memory), checkpoint interval and the like,
    /// as the embedded scheduler's.
    pub scheduler: SchedulerConfig,
    /// Where jobs keep their scratch files (`DATA/cache/jobs`), emptied at
    /// start.
    pub scratch: PathBuf,
}

/// What the claim loop and the job threads share.
pub(crate) struct Ctx {
    node: String,
    queue: PgQueue,
    artifacts: Arc<ObjectArtifacts>,
    config: SchedulerConfig,
    lease: Duration,
    stats: Arc<WorkerStats>,
    rt: tokio::runtime::Handle,
    scratch: PathBuf,
    /// Jobs running here, by id.
    running: Mutex<HashMap<String, Arc<keeper::Run>>>,
    threads: Mutex<Vec<JoinHandle<()>>>,
    /// A job here ended: the claim loop may claim again.
    ended: Notify,
    /// Set by shutdown: claim nothing more.
    stopping: AtomicBool,
}

impl Ctx {
    fn running(&self) -> MutexGuard<'_, HashMap<String, Arc<keeper::Run>>> {
        self.running.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// What this worker may claim now.
    fn admission(&self) -> Admission {
        let running = self.running();
        Admission {
            max_concurrent: self.config.max_concurrent,
            max_job_memory_bytes: self.config.max_job_memory_bytes,
            memory_budget_bytes: self.config.memory_budget_bytes,
            running_jobs: running.len(),
            running_bytes: running.values().map(|r| r.job().memory_estimate_bytes).sum(),
            // Pose estimations are not run by workers yet (`host`).
            colmap: false,
        }
    }

    /// Starts a claimed job on its own thread.
    fn start(self: &Arc<Self>, claimed: Claimed) {
        let id = claimed.job.id.clone();
        let run = Arc::new(keeper::Run::new(claimed.job.clone(), claimed.lease.clone()));
        self.running().insert(id.clone(), run.clone());
        self.stats.claims.fetch_add(1, Ordering::Relaxed);
        self.stats.running.fetch_add(1, Ordering::Relaxed);
        let (ctx, failed_id) = (self.clone(), id.clone());
        let spawned = std::thread::Builder::new().name(format!("job-{id}")).spawn(move || {
            run::run_claimed(ctx.clone(), claimed, run);
            ctx.running().remove(&id);
            ctx.stats.running.fetch_sub(1, Ordering::Relaxed);
            ctx.ended.notify_one();
        });
        match spawned {
            Ok(t) => {
                let mut threads = self.threads.lock().unwrap_or_else(|e| e.into_inner());
                threads.retain(|t| !t.is_finished());
                threads.push(t);
            }
            Err(e) => {
                // Not run here: its lease expires and a reclaim (here or on
                // another worker) queues it again.
                self.running().remove(&failed_id);
                self.stats.running.fetch_sub(1, Ordering::Relaxed);
                tracing::error!(worker = %self.node, job = %failed_id, error = %e, "cannot start a job's thread");
            }
        }
    }
}

/// A running worker.
pub struct Worker {
    ctx: Arc<Ctx>,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
}

impl Worker {
    /// Starts the claim loop on the current runtime. `db` is the database
    /// the queue's pool is over (the loop LISTENs on a connection of its
    /// own).
    pub fn start(
        config: WorkerConfig,
        db: Database,
        queue: PgQueue,
        artifacts: Arc<ObjectArtifacts>,
    ) -> std::io::Result<Worker> {
        if config.scratch.exists() {
            std::fs::remove_dir_all(&config.scratch)?;
        }
        std::fs::create_dir_all(&config.scratch)?;
        let ctx = Arc::new(Ctx {
            node: config.node,
            queue,
            artifacts,
            config: config.scheduler,
            lease: config.lease,
            stats: Arc::new(WorkerStats::default()),
            rt: tokio::runtime::Handle::current(),
            scratch: config.scratch,
            running: Mutex::default(),
            threads: Mutex::default(),
            ended: Notify::new(),
            stopping: AtomicBool::new(false),
        });
        tracing::info!(worker = %ctx.node, lease_seconds = ctx.lease.as_secs_f64(),
            heartbeat_seconds = heartbeat_every(ctx.lease).as_secs_f64(), "worker started");
        let (stop, stopped) = watch::channel(false);
        let task = tokio::spawn(claim::claim_loop(ctx.clone(), db, stopped));
        Ok(Worker { ctx, stop, task })
    }

    /// What this worker counts (/metrics).
    pub fn stats(&self) -> Arc<WorkerStats> {
        self.ctx.stats.clone()
    }

    /// Stops claiming, stops the running jobs (each checkpoints and is
    /// queued again) and waits for them.
    pub async fn shutdown(self) {
        self.ctx.stopping.store(true, Ordering::SeqCst);
        let _ = self.stop.send(true);
        let _ = self.task.await;
        for run in self.ctx.running().values() {
            run.cancel.store(true, Ordering::SeqCst);
        }
        let threads = std::mem::take(&mut *self.ctx.threads.lock().unwrap_or_else(|e| e.into_inner()));
        let joined = tokio::task::spawn_blocking(move || {
            for t in threads {
                let _ = t.join();
            }
        });
        let _ = joined.await;
        tracing::info!(worker = %self.ctx.node, "worker stopped");
    }
}
