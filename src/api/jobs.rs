//! `/v1/jobs`: enqueue a training job (202), list, get, cancel.

use axum::Json;
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use serde::Deserialize;

use super::{ApiError, ApiResult, AppState, Code};
use crate::engine::nerf::NerfConfig;
use crate::engine::trainer::Budget;
use crate::jobs::train::{PRESETS, check_config, preset};
use crate::jobs::{Job, SchedError, Status, TrainSpec};

/// `POST /v1/jobs` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateJob {
    pub scene_id: String,
    /// Preset: `nerf` (default, the paper's model) or `nerf-tiny`.
    #[serde(default = "default_model")]
    pub model: String,
    pub budget: BudgetRequest,
    #[serde(default)]
    pub seed: u64,
    /// Rays per step (1024).
    pub batch_rays: Option<usize>,
    /// A full model configuration replacing the preset's.
    pub config: Option<NerfConfig>,
}

fn default_model() -> String {
    "nerf".into()
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BudgetRequest {
    pub seconds: Option<f64>,
    pub steps: Option<u64>,
    pub target_psnr: Option<f64>,
}

/// Longest accepted time budget: a week.
const MAX_SECONDS: f64 = 7.0 * 86400.0;

fn to_spec(r: CreateJob) -> ApiResult<TrainSpec> {
    let mut config = preset(&r.model).ok_or_else(|| {
        ApiError::bad_request(format!("unknown model '{}' (available: {})", r.model, PRESETS.join(", ")))
    })?;
    if let Some(c) = r.config {
        config = c;
    }
    check_config(&config).map_err(ApiError::bad_request)?;
    let b = r.budget;
    if b.target_psnr.is_some() {
        return Err(ApiError::bad_request("budget.target_psnr is not supported yet: give seconds or steps"));
    }
    if b.seconds.is_none() && b.steps.is_none() {
        return Err(ApiError::bad_request("budget needs seconds or steps"));
    }
    if let Some(s) = b.seconds
        && !(s.is_finite() && s > 0.0 && s <= MAX_SECONDS)
    {
        return Err(ApiError::bad_request(format!("budget.seconds must be in (0, {MAX_SECONDS}]")));
    }
    if let Some(n) = b.steps
        && !(1..=1_000_000_000).contains(&n)
    {
        return Err(ApiError::bad_request("budget.steps must be in 1..=1000000000"));
    }
    let batch_rays = r.batch_rays.unwrap_or(1024);
    if !(1..=65536).contains(&batch_rays) {
        return Err(ApiError::bad_request("batch_rays must be in 1..=65536"));
    }
    Ok(TrainSpec {
        scene_id: r.scene_id,
        model: r.model,
        config,
        budget: Budget { seconds: b.seconds, steps: b.steps },
        seed: r.seed,
        batch_rays,
    })
}

fn sched_error(e: SchedError) -> ApiError {
    match e {
        SchedError::SceneNotFound(_) | SchedError::JobNotFound(_) => ApiError::new(Code::NotFound, e.to_string()),
        SchedError::QueueFull(_) => ApiError::new(Code::QueueFull, e.to_string()),
        SchedError::SceneInUse { .. } | SchedError::AlreadyFinal { .. } => ApiError::conflict(e.to_string()),
        SchedError::Io(io) => ApiError::internal(io),
    }
}

pub async fn create(
    State(s): State<AppState>,
    body: Result<Json<CreateJob>, JsonRejection>,
) -> ApiResult<(StatusCode, Json<Job>)> {
    let Json(req) = body?;
    let spec = to_spec(req)?;
    let sched = s.scheduler.clone();
    let job = tokio::task::spawn_blocking(move || sched.enqueue(spec)).await?.map_err(sched_error)?;
    tracing::info!(job = %job.id, scene = %job.spec.scene_id, "job queued");
    Ok((StatusCode::ACCEPTED, Json(job)))
}

#[derive(Debug, Deserialize)]
pub struct ListQuery {
    pub status: Option<String>,
}

pub async fn list(State(s): State<AppState>, q: Result<Query<ListQuery>, QueryRejection>) -> ApiResult<Json<Vec<Job>>> {
    let Query(q) = q?;
    let status = q.status.map(|v| v.parse::<Status>()).transpose().map_err(ApiError::bad_request)?;
    Ok(Json(s.scheduler.list(status)))
}

pub async fn get_one(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<Json<Job>> {
    s.scheduler.get(&id).map(Json).ok_or_else(|| ApiError::not_found("job", &id))
}

/// Cancels a job: a queued one at once; a running one stops within about a
/// training step, keeping its last state as a usable model.
pub async fn cancel(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<(StatusCode, Json<Job>)> {
    let sched = s.scheduler.clone();
    let job = tokio::task::spawn_blocking(move || sched.cancel(&id)).await?.map_err(sched_error)?;
    Ok((StatusCode::ACCEPTED, Json(job)))
}
