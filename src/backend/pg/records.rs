//! The records of scenes, models and videos in PostgreSQL: read, list (by
//! creation time, as the embedded store lists its files) and delete with
//! the embedded store's refusals.
//!
//! A deletion locks the record's row (`FOR UPDATE`) before it looks for
//! queued or running jobs that need it. An enqueue holds `FOR SHARE` on the
//! scene or model it checks (`queue::enqueue_in`), so the two wait for each
//! other: a job is either seen by the deletion (which refuses) or finds the
//! record gone (and is refused). That row lock is what the embedded
//! scheduler's lock does for the same checks.
//!
//! Only records are deleted here: the files (a scene's dataset, a model's
//! checkpoint, a video) are the artifact store's, which this store cannot
//! reach: the API's delete handlers remove them once the record is gone
//! (`ArtifactStore::remove`).

use deadpool_postgres::Transaction;
use serde::de::DeserializeOwned;
use tokio_postgres::Row;
use tokio_postgres::types::Json;

use super::error::PgError;
use super::queue::PgQueue;
use crate::jobs::{SchedError, Status};
use crate::records::{CropBox, ModelInfo, SceneInfo, VideoInfo};
use crate::system::now_ms;

/// The job statuses a record's user can have to keep it from being deleted.
const ACTIVE: &str = "status IN ('queued', 'running')";

impl PgQueue {
    /// Scenes by creation time (then id).
    pub async fn list_scenes(&self) -> Result<Vec<SceneInfo>, PgError> {
        self.records("SELECT id, record FROM scenes ORDER BY created_at, id", &[]).await
    }

    /// Removes a scene's record unless a queued or running job (training
    /// or pose estimation) uses it: `SceneInUse` naming the oldest such
    /// job. Models trained on it stay.
    pub async fn delete_scene(&self, id: &str) -> Result<(), PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        if tx.query_opt("SELECT 1 FROM scenes WHERE id = $1 FOR UPDATE", &[&id]).await?.is_none() {
            return Err(SchedError::SceneNotFound(id.into()).into());
        }
        let user = first_user(&tx, &format!("scene_id = $1 AND {ACTIVE}"), id).await?;
        if let Some((job, status)) = user {
            return Err(SchedError::SceneInUse { scene: id.into(), job, status }.into());
        }
        tx.execute("DELETE FROM scenes WHERE id = $1", &[&id]).await?;
        tx.commit().await?;
        Ok(())
    }

    /// A model's record.
    pub async fn model(&self, id: &str) -> Result<Option<ModelInfo>, PgError> {
        Ok(self.records("SELECT id, record FROM models WHERE id = $1", &[&id]).await?.pop())
    }

    /// Models by creation time (then id).
    pub async fn list_models(&self) -> Result<Vec<ModelInfo>, PgError> {
        self.records("SELECT id, record FROM models ORDER BY created_at, id", &[]).await
    }

    /// Removes a model's record unless a queued or running job writes it (a
    /// training job, whose model id is reserved before its first
    /// checkpoint) or renders it (a video job): `ModelInUse`. Videos made
    /// from it stay.
    pub async fn delete_model(&self, id: &str) -> Result<(), PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        if tx.query_opt("SELECT 1 FROM models WHERE id = $1 FOR UPDATE", &[&id]).await?.is_none() {
            return Err(SchedError::ModelNotFound(id.into()).into());
        }
        let user = first_user(&tx, &format!("(target_model_id = $1 OR model_id = $1) AND {ACTIVE}"), id).await?;
        if let Some((job, status)) = user {
            return Err(SchedError::ModelInUse { model: id.into(), job, status }.into());
        }
        tx.execute("DELETE FROM models WHERE id = $1", &[&id]).await?;
        tx.commit().await?;
        Ok(())
    }

    /// Sets or removes a model's crop volume unless a queued or running job
    /// writes or renders the model (`ModelInUse`), with the row locked as a
    /// deletion locks it; the record as it now is.
    pub async fn set_crop(&self, id: &str, crop: Option<CropBox>) -> Result<ModelInfo, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let Some(row) = tx.query_opt("SELECT id, record FROM models WHERE id = $1 FOR UPDATE", &[&id]).await? else {
            return Err(SchedError::ModelNotFound(id.into()).into());
        };
        let mut info: ModelInfo = record(&row)?;
        let user = first_user(&tx, &format!("(target_model_id = $1 OR model_id = $1) AND {ACTIVE}"), id).await?;
        if let Some((job, status)) = user {
            return Err(SchedError::ModelInUse { model: id.into(), job, status }.into());
        }
        info.crop = crop;
        // Strictly later, so that a cache keyed on it sees the change.
        info.updated_at = now_ms().max(info.updated_at + 1);
        let updated = i64::try_from(info.updated_at).unwrap_or(i64::MAX);
        tx.execute("UPDATE models SET record = $2, updated_at = $3 WHERE id = $1", &[&id, &Json(&info), &updated])
            .await?;
        tx.commit().await?;
        Ok(info)
    }

    /// A video's record.
    pub async fn video(&self, id: &str) -> Result<Option<VideoInfo>, PgError> {
        Ok(self.records("SELECT id, record FROM videos WHERE id = $1", &[&id]).await?.pop())
    }

    /// Videos by creation time (then id).
    pub async fn list_videos(&self) -> Result<Vec<VideoInfo>, PgError> {
        self.records("SELECT id, record FROM videos ORDER BY created_at, id", &[]).await
    }

    /// Removes a video's record unless the job that makes it has not ended
    /// (`VideoInUse`).
    pub async fn delete_video(&self, id: &str) -> Result<(), PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let Some(row) = tx.query_opt("SELECT job_id FROM videos WHERE id = $1 FOR UPDATE", &[&id]).await? else {
            return Err(SchedError::VideoNotFound(id.into()).into());
        };
        let job_id: String = row.try_get(0)?;
        let maker = first_user(&tx, &format!("id = $1 AND {ACTIVE}"), &job_id).await?;
        if let Some((job, status)) = maker {
            return Err(SchedError::VideoInUse { video: id.into(), job, status }.into());
        }
        tx.execute("DELETE FROM videos WHERE id = $1", &[&id]).await?;
        tx.commit().await?;
        Ok(())
    }

    /// The `record` column of each row `sql` selects (with `id` first), as
    /// `T`.
    async fn records<T: DeserializeOwned>(
        &self,
        sql: &str,
        params: &[&(dyn tokio_postgres::types::ToSql + Sync)],
    ) -> Result<Vec<T>, PgError> {
        let client = self.pool.get().await?;
        let rows = client.query(sql, params).await?;
        rows.iter().map(record).collect()
    }
}

/// A row's `record` column as `T`; an error naming the row when it is not one.
fn record<T: DeserializeOwned>(row: &Row) -> Result<T, PgError> {
    let id: String = row.try_get("id")?;
    row.try_get::<_, Json<T>>("record")
        .map(|Json(r)| r)
        .map_err(|e| PgError::BadRecord { id, reason: format!("column record: {}", super::error::chain(&e)) })
}

/// The oldest job matching `filter` (whose one parameter is `value`): its
/// id and status, for an in-use refusal.
async fn first_user(
    tx: &Transaction<'_>,
    filter: &str,
    value: &str,
) -> Result<Option<(String, &'static str)>, PgError> {
    let row =
        tx.query_opt(&format!("SELECT id, status FROM jobs WHERE {filter} ORDER BY seq LIMIT 1"), &[&value]).await?;
    let Some(row) = row else { return Ok(None) };
    let (id, status): (String, String) = (row.try_get(0)?, row.try_get(1)?);
    let status = status.parse::<Status>().map_err(|reason| PgError::BadRecord { id: id.clone(), reason })?;
    Ok(Some((id, status.name())))
}
