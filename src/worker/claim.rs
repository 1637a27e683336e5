//! The claim loop: one task per worker that takes expired leases back,
//! claims the jobs this worker may run, starts each on a thread, and then
//! sleeps until something may have changed.
//!
//! Each pass, in order:
//!
//! 1. reclaim expired leases (at most once every [`RECLAIM_EVERY`]; every
//!    worker does it, `SKIP LOCKED` keeps them apart);
//! 2. claim jobs while this worker's admission allows (its concurrency and
//!    memory budget, as the embedded scheduler's), starting each;
//! 3. wait for the first of: a `queued` notice (LISTEN), a job of this
//!    worker ending, the [`POLL`] fallback, or the stop signal. A `cancel`
//!    notice for a job running here sets its stop flag at once (the
//!    heartbeat would see it within its interval); other notices are
//!    ignored. A listener whose connection ended is started again at the
//!    next pass; until then the poll alone wakes the loop.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use tokio::sync::watch;

use super::Ctx;
use crate::backend::pg::{Database, Listener, Notice};

/// The longest a worker sleeps without looking at the queue.
pub const POLL: Duration = Duration::from_secs(1);

/// How often a worker takes back expired leases.
pub const RECLAIM_EVERY: Duration = Duration::from_secs(1);

/// The claim loop (see the module comment); returns when `stop` is set.
pub async fn claim_loop(ctx: Arc<Ctx>, db: Database, mut stop: watch::Receiver<bool>) {
    let mut listener: Option<Listener> = None;
    let mut last_reclaim: Option<Instant> = None;
    let mut last_listen: Option<Instant> = None;
    while !*stop.borrow() {
        if listener.is_none() && last_listen.is_none_or(|t| t.elapsed() >= POLL) {
            last_listen = Some(Instant::now());
            match Listener::start(&db).await {
                Ok(l) => listener = Some(l),
                Err(e) => tracing::warn!(worker = %ctx.node, error = %e, "cannot listen for queued jobs; polling"),
            }
        }
        if last_reclaim.is_none_or(|t| t.elapsed() >= RECLAIM_EVERY) {
            last_reclaim = Some(Instant::now());
            reclaim(&ctx).await;
        }
        claim_all(&ctx).await;
        let deadline = tokio::time::sleep(POLL);
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                _ = &mut deadline => break,
                _ = stop.changed() => break,
                _ = ctx.ended.notified() => break,
                notice = next_notice(&mut listener) => match notice {
                    Some(Notice::Queued(_)) => break,
                    Some(Notice::Cancel(id)) => cancel_here(&ctx, &id),
                    Some(Notice::Changed(_)) => {}
                    None => {
                        tracing::warn!(worker = %ctx.node, "the listener's connection ended; listening again");
                        listener = None;
                    }
                },
            }
        }
    }
}

/// The next notice; pending for ever without a listener.
async fn next_notice(listener: &mut Option<Listener>) -> Option<Notice> {
    match listener {
        Some(l) => l.recv().await,
        None => std::future::pending().await,
    }
}

/// Sets the stop flag of job `id` if it runs here.
fn cancel_here(ctx: &Ctx, id: &str) {
    if let Some(run) = ctx.running().get(id) {
        run.cancel.store(true, Ordering::SeqCst);
        tracing::info!(job = id, worker = %ctx.node, "cancel requested: stopping");
    }
}

async fn reclaim(ctx: &Ctx) {
    match ctx.queue.reclaim().await {
        Ok(taken) => {
            ctx.stats.reclaimed.fetch_add(taken.len() as u64, Ordering::Relaxed);
            for r in taken {
                tracing::warn!(job = %r.job.id, worker = %ctx.node, lost_by = %r.worker, attempt = r.attempt,
                    status = r.job.status.name(), "took back a job whose worker stopped renewing its lease");
            }
        }
        Err(e) => tracing::warn!(worker = %ctx.node, error = %e, "cannot take back expired leases"),
    }
}

/// Claims and starts jobs while this worker may take more.
async fn claim_all(ctx: &Arc<Ctx>) {
    while !ctx.stopping.load(Ordering::SeqCst) {
        let admission = ctx.admission();
        match ctx.queue.claim(&ctx.node, &admission, ctx.lease).await {
            Ok(Some(claimed)) => ctx.start(claimed),
            Ok(None) => return,
            Err(e) => {
                tracing::warn!(worker = %ctx.node, error = %e, "cannot claim jobs");
                return;
            }
        }
    }
}
