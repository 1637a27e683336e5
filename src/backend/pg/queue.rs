//! The API's side of the queue: enqueue (in `seq` order, with the embedded
//! queue's checks and answers), store a scene together with its pose
//! estimation job, read and count jobs, cancel, delete a finished job.
//!
//! Each call is one transaction. Row locks take the place of the embedded
//! scheduler's lock: an enqueue holds `FOR SHARE` on the scene or model it
//! needs, so a deletion's `FOR UPDATE` waits for it, and enqueues run one
//! at a time under a transaction advisory lock so the `max_queued` count
//! stays exact.

use std::collections::HashMap;
use std::io;

use deadpool_postgres::{Pool, Transaction};
use tokio_postgres::types::Json;

use super::error::PgError;
use super::rows::{JOB_COLUMNS, bigint, job};
use crate::backend::NewJob;
use crate::datadir::{new_id, valid_id};
use crate::jobs::{Job, JobProgress, JobSpec, SchedError, Status, check_trainable, poses, reserved_model_id};
use crate::records::{ModelInfo, SceneInfo};

/// The transaction advisory lock enqueues take: "radiqueu" in ASCII.
pub const ENQUEUE_LOCK_KEY: i64 = 0x7261_6469_7175_6575;

/// Queue settings (API side).
#[derive(Clone, Debug)]
pub struct QueueConfig {
    /// Queued jobs beyond this are refused (`SchedError::QueueFull`).
    pub max_queued: usize,
}

impl Default for QueueConfig {
    /// The embedded scheduler's default limit.
    fn default() -> Self {
        Self { max_queued: crate::jobs::SchedulerConfig::default().max_queued }
    }
}

/// The job queue in PostgreSQL (see the module comments of `queue` and
/// `lease`). Cheap to clone: the pool is shared.
#[derive(Clone)]
pub struct PgQueue {
    pub(super) pool: Pool,
    config: QueueConfig,
}

impl PgQueue {
    /// The queue over a pool of a migrated database (`migrate::migrate`).
    pub fn new(pool: Pool, config: QueueConfig) -> Self {
        Self { pool, config }
    }

    /// The newest migration the database has applied (0 before any).
    pub async fn schema_version(&self) -> Result<i32, PgError> {
        let client = self.pool.get().await?;
        let row = client.query_one("SELECT coalesce(max(version), 0) FROM radiance_migrations", &[]).await?;
        Ok(row.try_get(0)?)
    }

    /// Closes the pool: every later call fails at once (`Unavailable`).
    pub fn close(&self) {
        self.pool.close();
    }

    /// Registers a job and answers with its queued record, as the embedded
    /// `Scheduler::enqueue_as` does: a training job needs a ready scene, a
    /// pose estimation its scene, a video its model (`model_id`); a full
    /// queue refuses. The job is claimable once this returns.
    pub async fn enqueue(&self, new: NewJob) -> Result<Job, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let job = enqueue_in(&tx, self.config.max_queued, new).await?;
        tx.commit().await?;
        Ok(job)
    }

    /// Stores a scene's record, and with it (one transaction: both or
    /// neither) the job that estimates its poses, when it was uploaded as
    /// photos only. The record is the commit point of an upload: its files
    /// must be stored before.
    pub async fn insert_scene(&self, scene: &SceneInfo, poses_job: Option<NewJob>) -> Result<Option<Job>, PgError> {
        if !valid_id(&scene.id) {
            return Err(PgError::Invalid(format!("'{}' is not a valid scene id", scene.id)));
        }
        if let Some(j) = &poses_job
            && (!matches!(j.spec, JobSpec::Poses(_)) || j.spec.scene_id() != Some(scene.id.as_str()))
        {
            return Err(PgError::Invalid(format!(
                "the job stored with scene '{}' is not its pose estimation",
                scene.id
            )));
        }
        let record = serde_json::to_value(scene).map_err(|e| PgError::Invalid(format!("scene record: {e}")))?;
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let inserted = tx
            .execute(
                "INSERT INTO scenes (id, status, created_at, record) VALUES ($1, $2, $3, $4) ON CONFLICT (id) DO NOTHING",
                &[&scene.id, &scene.status.name(), &bigint(scene.created_at, "created_at")?, &record],
            )
            .await?;
        if inserted == 0 {
            return Err(SchedError::Io(io::Error::other(format!("scene id '{}' is taken", scene.id))).into());
        }
        let job = match poses_job {
            Some(j) => Some(enqueue_in(&tx, self.config.max_queued, j).await?),
            None => None,
        };
        tx.commit().await?;
        Ok(job)
    }

    /// A scene's record.
    pub async fn scene(&self, id: &str) -> Result<Option<SceneInfo>, PgError> {
        let client = self.pool.get().await?;
        let row = client.query_opt("SELECT record FROM scenes WHERE id = $1", &[&id]).await?;
        row.map(|r| r.try_get::<_, Json<SceneInfo>>(0).map(|Json(s)| s)).transpose().map_err(PgError::from)
    }

    /// A job as clients see it.
    pub async fn get(&self, id: &str) -> Result<Option<Job>, PgError> {
        let client = self.pool.get().await?;
        let row = client.query_opt(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1"), &[&id]).await?;
        row.as_ref().map(job).transpose()
    }

    /// Jobs in enqueue order, optionally of one status.
    pub async fn list(&self, status: Option<Status>) -> Result<Vec<Job>, PgError> {
        let client = self.pool.get().await?;
        let rows = client
            .query(
                &format!("SELECT {JOB_COLUMNS} FROM jobs WHERE $1::text IS NULL OR status = $1 ORDER BY seq"),
                &[&status.map(Status::name)],
            )
            .await?;
        rows.iter().map(job).collect()
    }

    /// How many jobs have each status (a status no job has is missing).
    pub async fn count_by_status(&self) -> Result<HashMap<Status, usize>, PgError> {
        let client = self.pool.get().await?;
        let rows = client.query("SELECT status, count(*) FROM jobs GROUP BY status", &[]).await?;
        let mut counts = HashMap::new();
        for row in &rows {
            let (status, n): (String, i64) = (row.try_get(0)?, row.try_get(1)?);
            let status = status.parse::<Status>().map_err(PgError::Invalid)?;
            counts.insert(status, usize::try_from(n).unwrap_or(0));
        }
        Ok(counts)
    }

    /// Removes a finished job's record (and its runs' history); what it
    /// made stays. A queued or running job is refused (`JobNotFinal`): it
    /// must be canceled first.
    pub async fn delete_job(&self, id: &str) -> Result<(), PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let row = tx.query_opt("SELECT status FROM jobs WHERE id = $1 FOR UPDATE", &[&id]).await?;
        let Some(row) = row else { return Err(SchedError::JobNotFound(id.into()).into()) };
        let status = row.try_get::<_, String>(0)?.parse::<Status>().map_err(PgError::Invalid)?;
        if !status.is_final() {
            return Err(SchedError::JobNotFinal { id: id.into(), status: status.name() }.into());
        }
        tx.execute("DELETE FROM jobs WHERE id = $1", &[&id]).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Cancels a queued job at once (a pose estimation's scene becomes
    /// `failed` with it), or asks a running one to stop: `cancel_requested`
    /// is set, the `jobs` trigger announces `cancel:<id>` to the worker's
    /// listener, and its next heartbeat reads it too. Answers the job as it
    /// is then (still `running` in the second case), as the embedded queue.
    pub async fn cancel(&self, id: &str) -> Result<Job, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let row = tx.query_opt(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1 FOR UPDATE"), &[&id]).await?;
        let current = row.as_ref().map(job).transpose()?.ok_or_else(|| SchedError::JobNotFound(id.into()))?;
        let answer = match current.status {
            s if s.is_final() => return Err(SchedError::AlreadyFinal { id: id.into(), status: s.name() }.into()),
            Status::Running => {
                tx.execute("UPDATE jobs SET cancel_requested = true WHERE id = $1", &[&id]).await?;
                current
            }
            _ => {
                let row = tx
                    .query_one(
                        &format!(
                            "UPDATE jobs SET status = 'canceled', finished_at = radiance_now_ms() WHERE id = $1 \
                             RETURNING {JOB_COLUMNS}"
                        ),
                        &[&id],
                    )
                    .await?;
                let canceled = job(&row)?;
                settle_scene(&tx, &canceled).await?;
                canceled
            }
        };
        tx.commit().await?;
        Ok(answer)
    }
}

/// A model's record, read for a job that uses it (kept until the job is queued).
async fn pg_model(tx: &Transaction<'_>, id: &str) -> Result<Option<ModelInfo>, PgError> {
    let row = tx.query_opt("SELECT record FROM models WHERE id = $1 FOR SHARE", &[&id]).await?;
    Ok(row.map(|r| r.try_get::<_, Json<ModelInfo>>(0)).transpose()?.map(|j| j.0))
}

/// The enqueue of [`PgQueue::enqueue`], inside the caller's transaction.
async fn enqueue_in(tx: &Transaction<'_>, max_queued: usize, new: NewJob) -> Result<Job, PgError> {
    let id = match new.id {
        Some(id) if valid_id(&id) => id,
        Some(id) => return Err(PgError::Invalid(format!("'{id}' is not a valid job id"))),
        None => new_id("job"),
    };
    tx.execute("SELECT pg_advisory_xact_lock($1)", &[&ENQUEUE_LOCK_KEY]).await?;
    match &new.spec {
        JobSpec::Train(t) => {
            let row = tx.query_opt("SELECT record FROM scenes WHERE id = $1 FOR SHARE", &[&t.scene_id]).await?;
            let Json(scene) =
                row.ok_or_else(|| SchedError::SceneNotFound(t.scene_id.clone()))?.try_get::<_, Json<SceneInfo>>(0)?;
            check_trainable(&scene)?;
        }
        JobSpec::Poses(p) => {
            if tx.query_opt("SELECT 1 FROM scenes WHERE id = $1 FOR SHARE", &[&p.scene_id]).await?.is_none() {
                return Err(SchedError::SceneNotFound(p.scene_id.clone()).into());
            }
        }
        JobSpec::Bake(b) => crate::jobs::bake::check_source(&pg_model(tx, &b.source_model_id).await?, b)?,
        JobSpec::Video(_) => {
            let model = new.model_id.clone().unwrap_or_default();
            if tx.query_opt("SELECT 1 FROM models WHERE id = $1 FOR SHARE", &[&model]).await?.is_none() {
                return Err(SchedError::ModelNotFound(model).into());
            }
        }
    }
    let queued: i64 = tx.query_one("SELECT count(*) FROM jobs WHERE status = 'queued'", &[]).await?.get(0);
    if queued >= i64::try_from(max_queued).unwrap_or(i64::MAX) {
        return Err(SchedError::QueueFull(queued as usize).into());
    }
    // The model it writes (train) or reads (video): what a model's deletion checks.
    let target_model = match &new.spec {
        JobSpec::Train(_) => Some(reserved_model_id(&id)),
        JobSpec::Video(_) => new.model_id.clone(),
        JobSpec::Poses(_) => None,
        JobSpec::Bake(b) => Some(b.source_model_id.clone()),
    };
    let spec = serde_json::to_value(&new.spec).map_err(|e| PgError::Invalid(format!("job spec: {e}")))?;
    let row = tx
        .query_opt(
            &format!(
                "INSERT INTO jobs (id, kind, status, spec, scene_id, target_model_id, model_id, created_at, progress, \
                 memory_estimate_bytes) VALUES ($1, $2, 'queued', $3, $4, $5, $6, radiance_now_ms(), $7, $8) \
                 ON CONFLICT (id) DO NOTHING RETURNING {JOB_COLUMNS}"
            ),
            &[
                &id,
                &new.spec.name(),
                &spec,
                &new.spec.scene_id(),
                &target_model,
                &new.model_id,
                &Json(JobProgress::default()),
                &bigint(new.memory_estimate, "the memory estimate")?,
            ],
        )
        .await?;
    let Some(row) = row else {
        return Err(SchedError::Io(io::Error::other(format!("job id '{id}' is taken"))).into());
    };
    job(&row)
}

/// After a pose estimation ended without success (canceled, failed): its
/// scene, if still posing by this job, becomes `failed` with the reason the
/// embedded queue gives (`jobs::poses::settle`), in the caller's
/// transaction. Its photos are the artifact store's to remove.
pub(super) async fn settle_scene(tx: &Transaction<'_>, job: &Job) -> Result<(), PgError> {
    let JobSpec::Poses(p) = &job.spec else { return Ok(()) };
    let Some(reason) = poses::settle_reason(Some(job)) else { return Ok(()) };
    tx.execute(
        "UPDATE scenes SET status = 'failed', record = record || jsonb_build_object('status', 'failed', 'error', $3::text) \
         WHERE id = $1 AND status = 'posing' AND record->'poses'->>'job_id' = $2",
        &[&p.scene_id, &job.id, &reason],
    )
    .await?;
    Ok(())
}
