//! One claimed job on a thread of its own: its heartbeat started, its body
//! run (`jobs::run_body`) over a [`RemoteHost`], its end
//! recorded under the lease, its scratch folder removed.
//!
//! The end is recorded only while the lease holds: a worker that lost its
//! job (reclaimed after its lease expired, maybe already run by another
//! worker) writes nothing. A stop that is neither a client's cancel nor a
//! lost lease is this worker shutting down: the job is queued again
//! (`interrupted`) and resumes on any worker from its last checkpoint.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use super::Ctx;
use super::host::RemoteHost;
use super::keeper::{self, Run};
use crate::backend::pg::{Claimed, RunEnd};
use crate::jobs::{Outcome, run_body};

/// Attempts at recording a run's end while the database does not answer.
const FINISH_ATTEMPTS: u32 = 5;

/// Runs `claimed` to its end (called on the job's own thread).
pub fn run_claimed(ctx: Arc<Ctx>, claimed: Claimed, run: Arc<Run>) {
    let job = claimed.job;
    let span = tracing::info_span!("job", job = %job.id, kind = job.spec.name(), attempt = job.attempts,
        worker = %ctx.node);
    let _entered = span.enter();
    tracing::info!(resumes = job.progress.step > 0, "job started");
    let (stop_heartbeat, stopped) = tokio::sync::oneshot::channel();
    let heartbeat = ctx.rt.spawn(keeper::keep(ctx.queue.clone(), run.clone(), stopped));
    let host = RemoteHost { ctx: ctx.clone(), run: run.clone() };
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run_body(&host, &job, &run.cancel)))
        .unwrap_or_else(|_| Outcome::Failed("the job panicked (see the worker's log)".into()));
    let _ = stop_heartbeat.send(());
    let _ = ctx.rt.block_on(heartbeat);
    record_end(&ctx, &run, outcome);
    if let Err(e) = std::fs::remove_dir_all(host.scratch())
        && e.kind() != std::io::ErrorKind::NotFound
    {
        tracing::warn!(error = %e, "cannot remove the job's scratch folder");
    }
}

/// Records the end under the lease, retrying while the database does not
/// answer and the lease holds; nothing once it may be lost.
fn record_end(ctx: &Ctx, run: &Run, outcome: Outcome) {
    let end = match outcome {
        Outcome::Succeeded => RunEnd::Succeeded,
        Outcome::Failed(e) => RunEnd::Failed(e),
        Outcome::Stopped => RunEnd::Stopped,
    };
    for attempt in 1..=FINISH_ATTEMPTS {
        if !run.holds() {
            run.fence("the run ended without the lease");
            ctx.stats.leases_lost.fetch_add(1, Ordering::Relaxed);
            tracing::warn!("the job's end is not recorded: its lease is lost");
            return;
        }
        match ctx.rt.block_on(ctx.queue.finish(&run.lease, end.clone(), &run.state())) {
            Ok(job) => {
                let error = job.error.as_deref().unwrap_or("");
                tracing::info!(status = job.status.name(), step = job.progress.step, error, "job ended");
                return;
            }
            Err(crate::backend::pg::PgError::LeaseLost(_)) => {
                run.fence("recording the end was refused: the lease is lost");
                ctx.stats.leases_lost.fetch_add(1, Ordering::Relaxed);
                return;
            }
            Err(e) => {
                tracing::warn!(error = %e, attempt, "cannot record the job's end; retrying");
                std::thread::sleep(Duration::from_millis(500));
            }
        }
    }
    tracing::error!("the job's end could not be recorded: its lease will expire and it will run again");
}
