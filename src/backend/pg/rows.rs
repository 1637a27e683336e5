//! A `jobs` row as the [`Job`] clients see: its columns, `spec` (the
//! [`JobSpec`] as JSON, tagged by kind) and `progress` (the [`JobProgress`]
//! as JSON), so a job answered from PostgreSQL serialises exactly as one
//! from the embedded queue.

use serde::de::DeserializeOwned;
use tokio_postgres::Row;
use tokio_postgres::types::Json;

use super::error::PgError;
use crate::jobs::{Job, JobProgress, JobSpec, Status};

/// The columns [`job`] reads, for `SELECT` and `RETURNING` lists.
pub(super) const JOB_COLUMNS: &str = "id, seq, status, spec, created_at, started_at, finished_at, error, model_id, \
                                      video_id, progress, attempts, memory_estimate_bytes, crashes";

/// The job a row holds (it must have [`JOB_COLUMNS`]).
pub(super) fn job(row: &Row) -> Result<Job, PgError> {
    let id: String = row.try_get("id")?;
    let bad = |reason: String| PgError::BadRecord { id: id.clone(), reason };
    let status: String = row.try_get("status")?;
    let Json(spec) = json::<JobSpec>(row, "spec").map_err(&bad)?;
    let Json(progress) = json::<JobProgress>(row, "progress").map_err(&bad)?;
    Ok(Job {
        seq: unsigned(row, "seq").map_err(&bad)?,
        status: status.parse::<Status>().map_err(&bad)?,
        spec,
        created_at: unsigned(row, "created_at").map_err(&bad)?,
        started_at: unsigned_opt(row, "started_at").map_err(&bad)?,
        finished_at: unsigned_opt(row, "finished_at").map_err(&bad)?,
        error: row.try_get("error")?,
        model_id: row.try_get("model_id")?,
        video_id: row.try_get("video_id")?,
        progress,
        attempts: count(row, "attempts").map_err(&bad)?,
        memory_estimate_bytes: unsigned(row, "memory_estimate_bytes").map_err(&bad)?,
        crashes: count(row, "crashes").map_err(&bad)?,
        id,
    })
}

/// A JSON column read as `T`; the reason when it is not one.
fn json<T: DeserializeOwned>(row: &Row, col: &str) -> Result<Json<T>, String> {
    row.try_get::<_, Json<T>>(col).map_err(|e| format!("column {col}: {}", super::error::chain(&e)))
}

/// A non-negative `bigint` column as the record's `u64`.
fn unsigned(row: &Row, col: &str) -> Result<u64, String> {
    unsigned_opt(row, col)?.ok_or_else(|| format!("column {col} is null"))
}

fn unsigned_opt(row: &Row, col: &str) -> Result<Option<u64>, String> {
    let v: Option<i64> = row.try_get(col).map_err(|e| format!("column {col}: {}", super::error::chain(&e)))?;
    v.map(|v| u64::try_from(v).map_err(|_| format!("column {col} holds {v}, a negative count"))).transpose()
}

/// A non-negative `int` column as the record's `u32`.
fn count(row: &Row, col: &str) -> Result<u32, String> {
    let v: i32 = row.try_get(col).map_err(|e| format!("column {col}: {}", super::error::chain(&e)))?;
    u32::try_from(v).map_err(|_| format!("column {col} holds {v}, a negative count"))
}

/// A count of bytes as PostgreSQL's `bigint`.
pub(super) fn bigint(bytes: u64, what: &str) -> Result<i64, PgError> {
    i64::try_from(bytes).map_err(|_| PgError::Invalid(format!("{what} ({bytes}) is out of range")))
}
