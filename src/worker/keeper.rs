//! A running job's hold on its lease: what the job's thread, its heartbeat
//! task and the claim loop share ([`Run`]), and the heartbeat itself
//! ([`keep`]).
//!
//! The heartbeat renews the lease every [`heartbeat_every`] (a fifth of the
//! lease, at most a second), writing the job's progress as clients see it,
//! and reads whether a client asked to cancel it. A worker that cannot be
//! sure it still holds the job stops it and writes nothing more for it
//! ([`Run::fence`]): when a heartbeat is refused (the lease was reclaimed),
//! and when no heartbeat succeeded for [`FENCE_AFTER`] of the lease (by
//! this machine's monotonic clock, so before the database lets another
//! worker take the job; a worker that was frozen sees it as soon as it
//! runs again).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use crate::backend::pg::{Heartbeat, Lease, PgQueue, RunState};
use crate::jobs::Job;

/// The part of the lease after which a worker whose heartbeats all failed
/// stops its job: the rest is its margin against the database's clock.
pub const FENCE_AFTER: f64 = 0.8;

/// How often a lease of `lease` is renewed: a fifth of it (so four
/// heartbeats can fail before the self-fence), at most once a second.
pub fn heartbeat_every(lease: Duration) -> Duration {
    (lease / 5).min(Duration::from_secs(1))
}

/// A job this worker runs.
pub struct Run {
    pub lease: Lease,
    /// The job as clients see it: its progress, model and video, which the
    /// job's thread updates and each heartbeat writes.
    job: Mutex<Job>,
    /// The engine's stop flag: set for a cancel, a lost lease, a shutdown.
    pub cancel: AtomicBool,
    /// Set once the lease may be lost: nothing more is written for the job.
    fenced: AtomicBool,
    /// When the lease was last renewed (or claimed).
    renewed: Mutex<Instant>,
}

impl Run {
    pub fn new(job: Job, lease: Lease) -> Self {
        Self {
            lease,
            job: Mutex::new(job),
            cancel: AtomicBool::new(false),
            fenced: AtomicBool::new(false),
            renewed: Mutex::new(Instant::now()),
        }
    }

    pub fn job(&self) -> MutexGuard<'_, Job> {
        self.job.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// What a heartbeat or the run's end writes.
    pub fn state(&self) -> RunState {
        let j = self.job();
        RunState { progress: j.progress.clone(), model_id: j.model_id.clone(), video_id: j.video_id.clone() }
    }

    /// Whether this worker may still write for the job: not fenced, and
    /// renewed within [`FENCE_AFTER`] of the lease.
    pub fn holds(&self) -> bool {
        let renewed = *self.renewed.lock().unwrap_or_else(|e| e.into_inner());
        !self.fenced.load(Ordering::SeqCst) && renewed.elapsed().as_secs_f64() < FENCE_AFTER * self.lease_secs()
    }

    /// Stops the job and writes nothing more for it.
    pub fn fence(&self, why: &str) {
        if !self.fenced.swap(true, Ordering::SeqCst) {
            tracing::warn!(job = %self.lease.job_id, worker = %self.lease.worker, reason = why,
                "stopping the job and writing nothing more for it: another worker may run it");
        }
        self.cancel.store(true, Ordering::SeqCst);
    }

    fn lease_secs(&self) -> f64 {
        self.lease.duration.as_secs_f64()
    }

    fn renewed_now(&self) {
        *self.renewed.lock().unwrap_or_else(|e| e.into_inner()) = Instant::now();
    }
}

/// Renews `run`'s lease until `stop` fires or the lease may be lost (see
/// the module comment). A cancel request sets the job's stop flag; the
/// job's thread then stops within a training step and records the end.
pub async fn keep(queue: PgQueue, run: Arc<Run>, mut stop: oneshot::Receiver<()>) {
    let every = heartbeat_every(run.lease.duration);
    loop {
        tokio::select! {
            _ = &mut stop => return,
            _ = tokio::time::sleep(every) => {}
        }
        if !run.holds() {
            run.fence("the lease could not be renewed in time");
            return;
        }
        // One attempt at a time, each bounded by the interval.
        match tokio::time::timeout(every, queue.heartbeat(&run.lease, &run.state())).await {
            Ok(Ok(Heartbeat::Renewed { cancel_requested })) => {
                run.renewed_now();
                if cancel_requested && !run.cancel.swap(true, Ordering::SeqCst) {
                    tracing::info!(job = %run.lease.job_id, worker = %run.lease.worker, "cancel requested: stopping");
                }
            }
            Ok(Ok(Heartbeat::Lost)) => {
                run.fence("the heartbeat was refused: the lease is lost");
                return;
            }
            Ok(Err(e)) => tracing::warn!(job = %run.lease.job_id, error = %e, "heartbeat failed; retrying"),
            Err(_) => tracing::warn!(job = %run.lease.job_id, "heartbeat timed out; retrying"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::SystemTime;

    fn run(lease: Duration) -> Run {
        let job = Job {
            id: "job_a".into(),
            seq: 1,
            status: crate::jobs::Status::Running,
            spec: crate::jobs::JobSpec::Poses(crate::jobs::PosesSpec { scene_id: "scn_a".into() }),
            created_at: 1,
            started_at: None,
            finished_at: None,
            error: None,
            model_id: None,
            video_id: None,
            progress: Default::default(),
            attempts: 1,
            memory_estimate_bytes: 0,
            crashes: 0,
        };
        let lease = Lease {
            job_id: "job_a".into(),
            worker: "w1".into(),
            token: uuid::Uuid::now_v7(),
            attempt: 1,
            duration: lease,
            expires_at: SystemTime::now(),
        };
        Run::new(job, lease)
    }

    #[test]
    fn heartbeats_come_five_times_a_lease_and_at_least_every_second() {
        assert_eq!(heartbeat_every(Duration::from_secs(3)), Duration::from_millis(600));
        assert_eq!(heartbeat_every(Duration::from_secs(10)), Duration::from_secs(1));
        assert_eq!(heartbeat_every(Duration::from_secs(600)), Duration::from_secs(1));
    }

    #[test]
    fn a_run_holds_its_lease_until_fenced_or_too_long_unrenewed() {
        // A long lease, and the last renewal set back in time rather than
        // waited for: no stall of this thread can pass 0.8 of it.
        let r = run(Duration::from_secs(100));
        let renewed_ago = |secs: u64| {
            let at = Instant::now().checked_sub(Duration::from_secs(secs)).expect("the monotonic clock is past 90 s");
            *r.renewed.lock().unwrap() = at;
        };
        assert!(r.holds() && !r.cancel.load(Ordering::SeqCst));
        renewed_ago(70);
        assert!(r.holds(), "renewed 0.7 of the lease ago");
        renewed_ago(90); // past 0.8 of the lease
        assert!(!r.holds(), "not renewed for 0.8 of the lease");
        r.renewed_now();
        assert!(r.holds());
        r.fence("test");
        assert!(
            !r.holds() && r.fenced.load(Ordering::SeqCst) && r.cancel.load(Ordering::SeqCst),
            "fencing stops the job for good"
        );
        r.renewed_now();
        assert!(!r.holds(), "a fenced run never holds again");
    }
}
