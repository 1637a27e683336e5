//! What a worker reads and writes beside its lease: the checkpoint a
//! training job resumes from, and the fenced publish of a video's record.
//!
//! A video's bytes are stored first (the artifact store); its record here
//! names them, so a record never names a video that is not whole. The
//! record is written only while the lease holds, as the model's is
//! (`lease::publish_model`): a worker that lost its job writes nothing.

use super::error::PgError;
use super::lease::{Lease, fenced_spec};
use super::queue::PgQueue;
use super::rows::bigint;
use crate::jobs::JobSpec;
use crate::records::VideoInfo;

impl PgQueue {
    /// The sha256 of model `id`'s published checkpoint (the object
    /// `models/<id>/<sha256>.ckpt`), if the model has a record.
    pub async fn checkpoint_sha256(&self, id: &str) -> Result<Option<String>, PgError> {
        let client = self.pool.get().await?;
        let row = client.query_opt("SELECT checkpoint_sha256 FROM models WHERE id = $1", &[&id]).await?;
        Ok(row.map(|r| r.try_get(0)).transpose()?)
    }

    /// Records the video the job `lease` holds has made (its bytes already
    /// stored) and sets the job's `video_id`, in one transaction fenced by
    /// the lease. [`PgError::LeaseLost`] and nothing written when the token
    /// no longer holds the job.
    pub async fn publish_video(&self, lease: &Lease, info: &VideoInfo) -> Result<(), PgError> {
        let record = serde_json::to_value(info).map_err(|e| PgError::Invalid(format!("video record: {e}")))?;
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let spec = fenced_spec(&tx, lease).await?;
        if !matches!(spec, JobSpec::Video(_)) || info.job_id != lease.job_id {
            return Err(PgError::Invalid(format!("job '{}' does not make video '{}'", lease.job_id, info.id)));
        }
        tx.execute(
            "INSERT INTO videos (id, model_id, job_id, created_at, record) VALUES ($1, $2, $3, $4, $5)
             ON CONFLICT (id) DO UPDATE SET model_id = EXCLUDED.model_id, job_id = EXCLUDED.job_id,
               created_at = EXCLUDED.created_at, record = EXCLUDED.record",
            &[&info.id, &info.model_id, &info.job_id, &bigint(info.created_at, "created_at")?, &record],
        )
        .await?;
        tx.execute("UPDATE jobs SET video_id = $2 WHERE id = $1", &[&lease.job_id, &info.id]).await?;
        tx.commit().await?;
        Ok(())
    }
}
