//! The workers' side of the queue: claim a job under a lease, keep the
//! lease with heartbeats, record the end of the run, take back the jobs of
//! workers that stopped heartbeating, and publish a model under the lease.
//!
//! A claim hands out a lease: the worker's id, a fresh token, and an expiry
//! by the database clock. Every later write for the job names the token and
//! changes nothing once it no longer matches (the job was reclaimed, maybe
//! already claimed by another worker): that fencing, not the expiry, is
//! what keeps a job from being run by two workers at once. A lease that
//! expired but was not yet reclaimed can still be renewed or finished: no
//! one else holds the job.
//!
//! Every claim adds a `job_runs` row (job, attempt, worker), closed with the
//! run's outcome: `succeeded`, `failed`, `canceled`, `interrupted` (the
//! worker stopped; the job is queued again) or `lost` (reclaimed).

use std::time::{Duration, SystemTime};

use tokio_postgres::types::Json;
use uuid::Uuid;

use super::error::PgError;
use super::queue::{PgQueue, settle_scene};
use super::rows::{JOB_COLUMNS, bigint, job};
use crate::jobs::{Job, JobProgress, JobSpec, MAX_CRASHES, Status, crashes_after};
use crate::records::ModelInfo;

/// What a worker can take now: its limits, and what it runs already.
#[derive(Clone, Debug)]
pub struct Admission {
    /// Jobs it runs at once (`--max-concurrent-jobs`; at least one).
    pub max_concurrent: usize,
    /// The largest job it takes (`--max-job-memory-mb`): larger ones are
    /// left for a bigger worker.
    pub max_job_memory_bytes: u64,
    /// Estimated memory of all its running jobs together.
    pub memory_budget_bytes: u64,
    /// Jobs it runs now, and the sum of their estimates.
    pub running_jobs: usize,
    pub running_bytes: u64,
    /// Whether it has COLMAP: pose estimations go only to workers that do.
    pub colmap: bool,
}

impl Admission {
    /// How much memory a job claimed now may need: `None` while the worker
    /// runs all the jobs it may. Alone, a worker takes any job within
    /// `max_job_memory_bytes`, as the embedded scheduler does.
    pub fn free_bytes(&self) -> Option<u64> {
        if self.running_jobs >= self.max_concurrent.max(1) {
            None
        } else if self.running_jobs == 0 {
            Some(u64::MAX)
        } else {
            Some(self.memory_budget_bytes.saturating_sub(self.running_bytes))
        }
    }
}

/// A worker's hold on a job it runs.
#[derive(Clone, Debug, PartialEq)]
pub struct Lease {
    pub job_id: String,
    /// The worker that claimed it.
    pub worker: String,
    /// The fencing token every write for the job names.
    pub token: Uuid,
    /// The run: the job's `attempts` after the claim, its `job_runs` row.
    pub attempt: u32,
    /// How long each heartbeat extends it.
    pub duration: Duration,
    /// When it expires unless renewed (database clock, as of the claim).
    pub expires_at: SystemTime,
}

/// A job claimed, as it is now (`running`), and its lease.
#[derive(Clone, Debug)]
pub struct Claimed {
    pub job: Job,
    pub lease: Lease,
}

/// What a running job reports: heartbeats and its end write it.
#[derive(Clone, Debug, Default)]
pub struct RunState {
    pub progress: JobProgress,
    /// Training: once a checkpoint exists. Video: the model rendered.
    /// `None` leaves the job's value as it is.
    pub model_id: Option<String>,
    /// Video: once the video is stored. `None` leaves it as it is.
    pub video_id: Option<String>,
}

/// The answer to a heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Heartbeat {
    /// The lease runs for another `Lease::duration`; whether a client asked
    /// for the job to be canceled.
    Renewed { cancel_requested: bool },
    /// The lease is gone: stop the job and write nothing more for it.
    Lost,
}

/// How a run ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RunEnd {
    Succeeded,
    Failed(String),
    /// Stopped by its cancel flag: `canceled` if a client asked for it
    /// (`cancel_requested`), otherwise the worker is stopping and the job is
    /// queued again (`interrupted`; not a crash).
    Stopped,
}

/// A job taken back from a worker whose lease expired.
#[derive(Clone, Debug)]
pub struct Reclaimed {
    /// The job as it is now: queued again, or failed after
    /// [`MAX_CRASHES`], or canceled when a client had asked for that.
    pub job: Job,
    /// The worker that lost it, and its run.
    pub worker: String,
    pub attempt: u32,
}

/// The spec of the job `lease` holds, its row locked until the end of
/// `tx`: the fence every publish goes through. [`PgError::LeaseLost`] when
/// the token no longer holds a running job.
pub(super) async fn fenced_spec(tx: &tokio_postgres::Transaction<'_>, lease: &Lease) -> Result<JobSpec, PgError> {
    let row = tx
        .query_opt(
            "SELECT spec FROM jobs WHERE id = $1 AND lease_token = $2 AND status = 'running' FOR UPDATE",
            &[&lease.job_id, &lease.token],
        )
        .await?;
    let Some(row) = row else { return Err(PgError::LeaseLost(lease.job_id.clone())) };
    let Json(spec) = row.try_get::<_, Json<JobSpec>>(0)?;
    Ok(spec)
}

/// Expired leases taken back per [`PgQueue::reclaim`] call.
pub const RECLAIM_BATCH: i64 = 16;

impl PgQueue {
    /// Claims the oldest queued job this worker may run, if any: the
    /// oldest in `seq` order among those within its `max_job_memory_bytes`
    /// (and not pose estimations unless it has COLMAP). If that job does
    /// not fit the memory left by its running jobs, nothing is claimed: it
    /// waits at the head of this worker's line, as in the embedded
    /// scheduler. Rows other workers are claiming are skipped (`SKIP
    /// LOCKED`), so no job is claimed twice.
    pub async fn claim(
        &self,
        worker: &str,
        admission: &Admission,
        lease: Duration,
    ) -> Result<Option<Claimed>, PgError> {
        if worker.is_empty() {
            return Err(PgError::Invalid("a worker needs an id".into()));
        }
        let secs = lease_seconds(lease)?;
        let Some(free) = admission.free_bytes() else { return Ok(None) };
        let clamp = |b: u64| i64::try_from(b).unwrap_or(i64::MAX);
        let token = Uuid::now_v7();
        let client = self.pool.get().await?;
        let statement = client
            .prepare_cached(&format!(
                "WITH next AS (
                   SELECT id, memory_estimate_bytes FROM jobs
                   WHERE status = 'queued' AND memory_estimate_bytes <= $1 AND (kind <> 'poses' OR $2)
                   ORDER BY seq LIMIT 1
                   FOR UPDATE SKIP LOCKED),
                 claimed AS (
                   UPDATE jobs j SET status = 'running', attempts = j.attempts + 1, started_at = radiance_now_ms(),
                          error = NULL, cancel_requested = false, lease_owner = $4, lease_token = $5,
                          lease_expires_at = now() + make_interval(secs => $6)
                   FROM next WHERE j.id = next.id AND next.memory_estimate_bytes <= $3
                   RETURNING j.*),
                 run AS (INSERT INTO job_runs (job_id, attempt, worker_id) SELECT id, attempts, $4 FROM claimed)
                 SELECT {JOB_COLUMNS}, lease_expires_at FROM claimed"
            ))
            .await?;
        let row = client
            .query_opt(
                &statement,
                &[&clamp(admission.max_job_memory_bytes), &admission.colmap, &clamp(free), &worker, &token, &secs],
            )
            .await?;
        let Some(row) = row else { return Ok(None) };
        let job = job(&row)?;
        let lease = Lease {
            job_id: job.id.clone(),
            worker: worker.to_string(),
            token,
            attempt: job.attempts,
            duration: lease,
            expires_at: row.try_get("lease_expires_at")?,
        };
        Ok(Some(Claimed { job, lease }))
    }

    /// Renews the lease by its duration from now (database clock), writes
    /// the job's progress (and its model or video once known), and reads
    /// whether a client asked to cancel it. [`Heartbeat::Lost`] when the
    /// token no longer holds the job.
    pub async fn heartbeat(&self, lease: &Lease, state: &RunState) -> Result<Heartbeat, PgError> {
        let client = self.pool.get().await?;
        let statement = client
            .prepare_cached(
                "UPDATE jobs SET progress = $3, model_id = coalesce($4, model_id), video_id = coalesce($5, video_id),
                        lease_expires_at = now() + make_interval(secs => $6)
                 WHERE id = $1 AND lease_token = $2 AND status = 'running'
                 RETURNING cancel_requested",
            )
            .await?;
        let row = client
            .query_opt(
                &statement,
                &[
                    &lease.job_id,
                    &lease.token,
                    &Json(&state.progress),
                    &state.model_id,
                    &state.video_id,
                    &lease_seconds(lease.duration)?,
                ],
            )
            .await?;
        Ok(match row {
            Some(r) => Heartbeat::Renewed { cancel_requested: r.try_get(0)? },
            None => Heartbeat::Lost,
        })
    }

    /// Records the end of a run under its lease (see [`RunEnd`]), closes its
    /// `job_runs` row, and settles the scene of a pose estimation that did
    /// not succeed, in one transaction. Returns the job as recorded;
    /// [`PgError::LeaseLost`] (and nothing written) when the token no longer
    /// holds the job.
    pub async fn finish(&self, lease: &Lease, end: RunEnd, state: &RunState) -> Result<Job, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let Some(row) = tx
            .query_opt(
                "SELECT cancel_requested FROM jobs WHERE id = $1 AND lease_token = $2 AND status = 'running' FOR UPDATE",
                &[&lease.job_id, &lease.token],
            )
            .await?
        else {
            return Err(PgError::LeaseLost(lease.job_id.clone()));
        };
        let cancel_requested: bool = row.try_get(0)?;
        let (status, outcome, error) = match end {
            RunEnd::Succeeded => (Status::Succeeded, "succeeded", None),
            RunEnd::Failed(e) => (Status::Failed, "failed", Some(e)),
            RunEnd::Stopped if cancel_requested => (Status::Canceled, "canceled", None),
            RunEnd::Stopped => (Status::Queued, "interrupted", None),
        };
        let statement = tx
            .prepare_cached(&format!(
                "UPDATE jobs SET status = $2, finished_at = CASE WHEN $3 THEN radiance_now_ms() END, error = $4,
                        progress = $5, model_id = coalesce($6, model_id), video_id = coalesce($7, video_id),
                        cancel_requested = false, lease_owner = NULL, lease_token = NULL, lease_expires_at = NULL
                 WHERE id = $1 RETURNING {JOB_COLUMNS}"
            ))
            .await?;
        let row = tx
            .query_one(
                &statement,
                &[
                    &lease.job_id,
                    &status.name(),
                    &status.is_final(),
                    &error,
                    &Json(&state.progress),
                    &state.model_id,
                    &state.video_id,
                ],
            )
            .await?;
        let ended = job(&row)?;
        close_run(&tx, &lease.job_id, lease.attempt, outcome).await?;
        settle_scene(&tx, &ended).await?;
        tx.commit().await?;
        Ok(ended)
    }

    /// Takes back up to [`RECLAIM_BATCH`] jobs whose lease expired (their
    /// worker died, hung, or lost the database), oldest first, counting a
    /// crash for each as the embedded scheduler does at start-up: a
    /// training job that saved a checkpoint during the lost run starts
    /// again at one crash, any other adds one, and at [`MAX_CRASHES`] the
    /// job fails instead of running again. A job a client had asked to
    /// cancel is canceled. The rest are queued again at their place
    /// (`seq`), and the `jobs` trigger wakes idle workers. Run by every
    /// worker; `SKIP LOCKED` keeps two from taking back the same job, and
    /// keeps a reclaim from interleaving with a fenced publish.
    pub async fn reclaim(&self) -> Result<Vec<Reclaimed>, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let expired = tx
            .query(
                "SELECT j.id, j.crashes, j.attempts, j.lease_owner, j.cancel_requested,
                        j.kind = 'train' AND EXISTS (SELECT 1 FROM models m
                          WHERE m.id = j.target_model_id AND m.saved_at > r.claimed_at) AS saved
                 FROM jobs j JOIN job_runs r ON r.job_id = j.id AND r.attempt = j.attempts
                 WHERE j.status = 'running' AND j.lease_expires_at < now()
                 ORDER BY j.seq
                 LIMIT $1
                 FOR UPDATE OF j SKIP LOCKED",
                &[&RECLAIM_BATCH],
            )
            .await?;
        let mut reclaimed = Vec::with_capacity(expired.len());
        for row in &expired {
            let id: String = row.try_get("id")?;
            let attempts: i32 = row.try_get("attempts")?;
            let worker: String = row.try_get("lease_owner")?;
            let crashes = crashes_after(row.try_get::<_, i32>("crashes")?.max(0) as u32, row.try_get("saved")?);
            let (status, error) = if row.try_get("cancel_requested")? {
                (Status::Canceled, None)
            } else if crashes >= MAX_CRASHES {
                tracing::error!(job = %id, crashes, "job failed: the workers running it died repeatedly");
                (Status::Failed, Some(crash_error(crashes)))
            } else {
                (Status::Queued, None)
            };
            let row = tx
                .query_one(
                    &format!(
                        "UPDATE jobs SET status = $2, crashes = $3, error = $4,
                                finished_at = CASE WHEN $5 THEN radiance_now_ms() END, cancel_requested = false,
                                lease_owner = NULL, lease_token = NULL, lease_expires_at = NULL
                         WHERE id = $1 RETURNING {JOB_COLUMNS}"
                    ),
                    &[&id, &status.name(), &(crashes as i32), &error, &status.is_final()],
                )
                .await?;
            let job = job(&row)?;
            let attempt = attempts.max(0) as u32;
            close_run(&tx, &id, attempt, "lost").await?;
            settle_scene(&tx, &job).await?;
            tracing::warn!(job = %id, worker = %worker, attempt, status = job.status.name(), "reclaimed a job whose lease expired");
            reclaimed.push(Reclaimed { job, worker, attempt });
        }
        tx.commit().await?;
        Ok(reclaimed)
    }

    /// Records a checkpoint of the training job `lease` holds: the model's
    /// record, its checkpoint object's sha256 and `saved_at` (database
    /// clock; crash counting reads it), and the job's `model_id`, in one
    /// transaction fenced by the lease. Returns the sha256 it replaces (the
    /// object to delete once this returns), if any and different.
    /// [`PgError::LeaseLost`] and nothing written when the token no longer
    /// holds the job: the session must stop.
    pub async fn publish_model(
        &self,
        lease: &Lease,
        info: &ModelInfo,
        checkpoint_sha256: &str,
    ) -> Result<Option<String>, PgError> {
        if checkpoint_sha256.len() != 64
            || !checkpoint_sha256.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        {
            return Err(PgError::Invalid(format!("'{checkpoint_sha256}' is not a lower-case hex sha256")));
        }
        let record = serde_json::to_value(info).map_err(|e| PgError::Invalid(format!("model record: {e}")))?;
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let spec = fenced_spec(&tx, lease).await?;
        if !matches!(spec, JobSpec::Train(_) | JobSpec::Bake(_)) || info.job_id != lease.job_id {
            return Err(PgError::Invalid(format!("job '{}' does not train model '{}'", lease.job_id, info.id)));
        }
        let previous: Option<String> = tx
            .query_opt("SELECT checkpoint_sha256 FROM models WHERE id = $1 FOR UPDATE", &[&info.id])
            .await?
            .map(|r| r.try_get(0))
            .transpose()?;
        tx.execute(
            "INSERT INTO models (id, scene_id, job_id, created_at, updated_at, checkpoint_sha256, saved_at, record)
             VALUES ($1, $2, $3, $4, $5, $6, now(), $7)
             ON CONFLICT (id) DO UPDATE SET scene_id = EXCLUDED.scene_id, job_id = EXCLUDED.job_id,
               updated_at = EXCLUDED.updated_at, checkpoint_sha256 = EXCLUDED.checkpoint_sha256,
               saved_at = now(), record = EXCLUDED.record",
            &[
                &info.id,
                &info.scene_id,
                &info.job_id,
                &bigint(info.created_at, "created_at")?,
                &bigint(info.updated_at, "updated_at")?,
                &checkpoint_sha256,
                &record,
            ],
        )
        .await?;
        tx.execute("UPDATE jobs SET model_id = $2 WHERE id = $1", &[&lease.job_id, &info.id]).await?;
        tx.commit().await?;
        Ok(previous.filter(|p| p != checkpoint_sha256))
    }
}

fn crash_error(crashes: u32) -> String {
    format!(
        "the worker running this job died {crashes} times in a row without the job saving progress in between \
         (killed, out of memory, or cut off from the database?); it is not run again"
    )
}

/// Closes a run's `job_runs` row with its outcome.
async fn close_run(
    tx: &deadpool_postgres::Transaction<'_>,
    job_id: &str,
    attempt: u32,
    outcome: &str,
) -> Result<(), PgError> {
    tx.execute(
        "UPDATE job_runs SET ended_at = now(), outcome = $3 WHERE job_id = $1 AND attempt = $2",
        &[&job_id, &(attempt as i32), &outcome],
    )
    .await?;
    Ok(())
}

/// A lease's length in seconds, as `make_interval` takes it.
fn lease_seconds(lease: Duration) -> Result<f64, PgError> {
    if lease.is_zero() || lease > Duration::from_secs(24 * 3600) {
        return Err(PgError::Invalid(format!("a lease of {lease:?}: expected more than zero and at most a day")));
    }
    Ok(lease.as_secs_f64())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn admission(running_jobs: usize, running_bytes: u64) -> Admission {
        Admission {
            max_concurrent: 2,
            max_job_memory_bytes: 800,
            memory_budget_bytes: 1000,
            running_jobs,
            running_bytes,
            colmap: false,
        }
    }

    #[test]
    fn free_memory_follows_the_embedded_schedulers_rules() {
        assert_eq!(admission(0, 0).free_bytes(), Some(u64::MAX), "alone, any job within the per-job limit");
        assert_eq!(admission(1, 300).free_bytes(), Some(700));
        assert_eq!(admission(1, 1200).free_bytes(), Some(0), "over budget: nothing fits");
        assert_eq!(admission(2, 300).free_bytes(), None, "at max_concurrent");
        let single = Admission { max_concurrent: 0, ..admission(0, 0) };
        assert_eq!(single.free_bytes(), Some(u64::MAX), "max_concurrent 0 runs one, as the scheduler");
        assert_eq!(Admission { max_concurrent: 0, ..admission(1, 0) }.free_bytes(), None);
    }

    #[test]
    fn crashes_count_up_unless_the_run_saved() {
        assert_eq!(crashes_after(0, false), 1);
        assert_eq!(crashes_after(1, false), 2);
        assert_eq!(crashes_after(1, true), 1);
        assert_eq!(crashes_after(5, true), 1);
        assert_eq!(crashes_after(u32::MAX, false), u32::MAX);
        assert!(crashes_after(crashes_after(0, false), false) >= MAX_CRASHES, "two lost runs in a row fail a job");
    }

    #[test]
    fn leases_must_be_positive_and_bounded() {
        assert!(lease_seconds(Duration::ZERO).is_err());
        assert!(lease_seconds(Duration::from_secs(2 * 24 * 3600)).is_err());
        assert_eq!(lease_seconds(Duration::from_millis(2500)).unwrap(), 2.5);
    }
}
