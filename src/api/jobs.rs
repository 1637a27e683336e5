//! `/v1/jobs`: enqueue a training or bake job (202), list, get, cancel, and follow
//! a job's progress as Server-Sent Events.

use std::convert::Infallible;

use axum::Json;
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::Stream;
use serde::Deserialize;

use super::{ApiError, ApiResult, AppState, limits};
use crate::backend::NewJob;
use crate::datadir::{ScenePart, new_id};
use crate::engine::front::{
    AUTO, CAPTURE_KIND, ConfigError, DEFAULT_BATCH_RAYS, MaskUse, ModelChoice, ModelConfig, SplatsConfig, choose_model,
    estimate_training, trainable_presets,
};
use crate::jobs::scoring::load_dataset;
use crate::jobs::{BakeAfter, BakeSpec, Job, JobBudget, JobSpec, SchedError, Status, TrainSpec, bake, check_trainable};

/// `POST /v1/jobs` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateJob {
    pub scene_id: String,
    /// `auto` (default: the scene decides, see `engine::models::auto`) or a
    /// preset: `instant` (the fast model), `instant-tiny`, `nerf` (the
    /// paper's model), `nerf-tiny`, `capture` (real photographs) or
    /// `capture-tiny`.
    #[serde(default = "default_model")]
    pub model: String,
    pub budget: JobBudget,
    #[serde(default)]
    pub seed: u64,
    /// Rays per step for `nerf` (1024); the fast model adapts its own.
    pub batch_rays: Option<usize>,
    /// A full model configuration replacing the preset's (same kind).
    pub config: Option<ModelConfig>,
    /// What the scene's per-image masks do: `auto` (default), `score`,
    /// `ignore`, `composite` or `off`. Read as any JSON value, so that a
    /// wrong one is refused naming the field.
    pub masks: Option<serde_json::Value>,
    /// `train` (the default here; `bake` bodies are [`CreateBake`]).
    pub kind: Option<String>,
    /// Bake the model into splats when training succeeds.
    pub bake: Option<BakeBudget>,
    /// Find transient occluders (a passer-by in a few photos) from the
    /// training errors and stop training on them: `capture` models do
    /// unless this is `false`; other models refuse `true`.
    #[serde(default)]
    pub drop_transients: Option<bool>,
}

/// A bake's budget: seconds (60 when neither is given) or optimisation steps.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BakeBudget {
    pub seconds: Option<f64>,
    pub steps: Option<u64>,
}

/// `POST /v1/jobs` body of a bake job: a trained model becomes splats.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateBake {
    pub kind: String,
    /// The trained model (instant, nerf or capture) to bake.
    pub model_id: String,
    pub seconds: Option<f64>,
    pub steps: Option<u64>,
    /// Spherical-harmonic degree of the colours, 0-3 (1).
    pub sh_degree: Option<u32>,
    /// The most Gaussians (300000).
    pub max_gaussians: Option<usize>,
    #[serde(default)]
    pub seed: u64,
}

/// A bake budget checked: seconds in (0, an hour], steps in 1..=10^9; a
/// minute when neither is given.
fn bake_budget(b: &BakeBudget, prefix: &str) -> ApiResult<(Option<f64>, Option<u64>)> {
    if let Some(t) = b.seconds
        && !(t.is_finite() && t > 0.0 && t <= bake::MAX_SECONDS)
    {
        let allowed = format!("(0, {}]", bake::MAX_SECONDS);
        let field = format!("{prefix}seconds");
        return Err(ApiError::bad_field(format!("{field} must be in {allowed}"), &field, t, &allowed));
    }
    if let Some(n) = b.steps
        && !(1..=1_000_000_000).contains(&n)
    {
        let field = format!("{prefix}steps");
        return Err(ApiError::bad_field(format!("{field} must be in 1..=1000000000"), &field, n, "1..=1000000000"));
    }
    let seconds = match (b.seconds, b.steps) {
        (None, None) => Some(bake::DEFAULT_SECONDS),
        (s, _) => s,
    };
    Ok((seconds, b.steps))
}

fn default_model() -> String {
    AUTO.into()
}

/// Longest accepted time budget: a week.
const MAX_SECONDS: f64 = 7.0 * 86400.0;

/// The job's spec from its body. `choice` is what `auto` chose for the
/// scene ([`auto_choice`]); it is used when `model` is `auto` and no
/// `config` is given (a `config` decides the model itself).
fn to_spec(r: CreateJob, choice: Option<ModelChoice>) -> ApiResult<TrainSpec> {
    let (model, model_reason) = match (r.model.as_str(), &r.config, choice) {
        (AUTO, Some(c), _) => (c.kind().to_string(), None),
        (AUTO, None, Some(choice)) => (choice.preset, Some(choice.reason)),
        (AUTO, None, None) => return Err(ApiError::internal("the model for 'auto' was not chosen")),
        (name, _, _) => (name.to_string(), None),
    };
    let allowed = || format!("{AUTO}, {}", trainable_presets().join(", "));
    let mut config = ModelConfig::preset(&model).filter(|c| c.spec().trains_on_rays()).ok_or_else(|| {
        let message = format!("unknown model '{}' (available: {})", r.model, allowed());
        ApiError::bad_field(message, "model", &r.model, &allowed())
    })?;
    if let Some(c) = r.config {
        if c.kind() != config.kind() {
            let message =
                format!("config.kind is '{}' but model '{}' is a '{}' model", c.kind(), r.model, config.kind());
            return Err(ApiError::bad_field(message, "config.kind", c.kind(), config.kind()));
        }
        config = c;
    }
    if !config.spec().trains_on_rays() {
        let message = format!("a '{}' model is baked from a trained model, not trained", config.kind());
        return Err(ApiError::bad_field(message, "config.kind", config.kind(), &allowed()));
    }
    config.check().map_err(config_error)?;
    let b = r.budget;
    if b.seconds.is_none() && b.steps.is_none() && b.target_psnr.is_none() {
        let allowed = "at least one of seconds, steps, target_psnr";
        return Err(ApiError::bad_field("budget needs seconds, steps or target_psnr", "budget", b, allowed));
    }
    if let Some(s) = b.seconds
        && !(s.is_finite() && s > 0.0 && s <= MAX_SECONDS)
    {
        let allowed = format!("(0, {MAX_SECONDS}]");
        return Err(ApiError::bad_field(format!("budget.seconds must be in {allowed}"), "budget.seconds", s, &allowed));
    }
    if let Some(n) = b.steps
        && !(1..=1_000_000_000).contains(&n)
    {
        return Err(ApiError::bad_field("budget.steps must be in 1..=1000000000", "budget.steps", n, "1..=1000000000"));
    }
    if let Some(p) = b.target_psnr
        && !(p.is_finite() && p > 0.0 && p <= 100.0)
    {
        let message = "budget.target_psnr must be in (0, 100] dB";
        return Err(ApiError::bad_field(message, "budget.target_psnr", p, "(0, 100]"));
    }
    let batch_rays = r.batch_rays.unwrap_or(DEFAULT_BATCH_RAYS);
    if !(1..=65536).contains(&batch_rays) {
        return Err(ApiError::bad_field("batch_rays must be in 1..=65536", "batch_rays", batch_rays, "1..=65536"));
    }
    let masks = mask_use(r.masks)?;
    let capture = config.kind() == CAPTURE_KIND;
    if r.drop_transients == Some(true) && !capture {
        let message = format!("drop_transients needs a capture model (this one is '{}')", config.kind());
        return Err(ApiError::bad_field(message, "drop_transients", true, CAPTURE_KIND));
    }
    if let Some(k) = r.kind.as_deref().filter(|k| *k != "train") {
        return Err(ApiError::bad_field(format!("unknown job kind '{k}'"), "kind", k, KINDS));
    }
    let bake = match &r.bake {
        Some(b) => {
            let (seconds, steps) = bake_budget(b, "bake.")?;
            Some(BakeAfter { job_id: String::new(), seconds, steps })
        }
        None => None,
    };
    Ok(TrainSpec {
        scene_id: r.scene_id,
        model,
        model_reason,
        config,
        budget: b,
        seed: r.seed,
        batch_rays,
        masks,
        bake,
        drop_transients: r.drop_transients.unwrap_or(capture),
    })
}

/// What `auto` chooses for the scene `scene_id` trained with `masks`: from
/// the kind its record keeps, or, for records from before it was kept, by
/// loading its dataset (on the blocking threads). A scene that is unknown
/// or not ready is refused as `enqueue` would refuse it.
async fn auto_choice(s: &AppState, scene_id: &str, masks: MaskUse) -> ApiResult<ModelChoice> {
    let scene = s.jobs.get_scene(scene_id).await?.ok_or_else(|| SchedError::SceneNotFound(scene_id.into()))?;
    check_trainable(&scene)?;
    if let Some(kind) = &scene.kind {
        return Ok(kind.clone().with_masks(scene.mask_folder.as_deref(), masks).choose());
    }
    let files = s.artifacts.scene_files(&scene, ScenePart::Data).await?;
    let loaded = tokio::task::spawn_blocking(move || load_dataset(&files.path, &scene, masks)).await?;
    let ds = loaded.map_err(|e| ApiError::internal(format!("loading scene '{scene_id}' to choose its model: {e}")))?;
    Ok(choose_model(&ds))
}

/// The job's `masks`: one of the names of [`MaskUse`], `auto` when absent.
fn mask_use(v: Option<serde_json::Value>) -> ApiResult<MaskUse> {
    const ALLOWED: &str = "auto, score, ignore, composite or off";
    match v {
        None => Ok(MaskUse::Auto),
        Some(serde_json::Value::String(s)) => {
            s.parse().map_err(|m: String| ApiError::bad_field(format!("masks: {m}"), "masks", &s, ALLOWED))
        }
        Some(other) => Err(ApiError::bad_field(format!("masks must be one of {ALLOWED}"), "masks", &other, ALLOWED)),
    }
}

/// A refused model configuration: the message names every failing field;
/// `details.fields` lists them as `{field, value, allowed}` for programs.
fn config_error(e: ConfigError) -> ApiError {
    let details = serde_json::json!({ "fields": e.fields });
    ApiError::bad_request(e.to_string()).with_details(details)
}

/// The job kinds `POST /v1/jobs` takes.
const KINDS: &str = "train or bake";

/// `POST /v1/jobs`: a training job (`kind` absent or `train`) or a bake
/// job (`kind: bake`).
pub async fn create(
    State(s): State<AppState>,
    body: Result<Json<serde_json::Value>, JsonRejection>,
) -> ApiResult<(StatusCode, Json<Job>)> {
    let Json(body) = body?;
    let parse_error = |e: serde_json::Error| {
        ApiError::bad_request(format!("Failed to deserialize the JSON body into the target type: {e}"))
    };
    if body.get("kind").and_then(|k| k.as_str()) == Some("bake") {
        let req: CreateBake = serde_json::from_value(body).map_err(parse_error)?;
        return create_bake(&s, req).await;
    }
    let req: CreateJob = serde_json::from_value(body).map_err(parse_error)?;
    let choice = match req.model == AUTO && req.config.is_none() {
        true => Some(auto_choice(&s, &req.scene_id, mask_use(req.masks.clone())?).await?),
        false => None,
    };
    let mut spec = to_spec(req, choice)?;
    if let Some(reason) = &spec.model_reason {
        tracing::info!(scene = %spec.scene_id, model = %spec.model, reason = %reason, "model chosen automatically");
    }
    // An unknown scene has no estimate: enqueue answers 404 for it.
    let memory = match s.jobs.get_scene(&spec.scene_id).await? {
        Some(scene) => {
            let threads = rayon::current_num_threads();
            let data = limits::scene_data(&scene, spec.masks);
            let e = estimate_training(&spec.config, data, threads);
            limits::check(&e, &s.config, s.artifacts.free_space().await?)?;
            if let Some(after) = &spec.bake {
                // The bake it asks for must fit as well.
                let bake = bake::spec_after_training(after, "", &spec.scene_id, spec.seed);
                limits::check(&bake::memory_estimate(&spec.config, &bake, data), &s.config, None)?;
            }
            e.memory_bytes
        }
        None => 0,
    };
    let id = new_id("job");
    if let Some(after) = &mut spec.bake {
        after.job_id = new_id("job");
    }
    let new = NewJob { id: Some(id), spec: JobSpec::Train(Box::new(spec)), model_id: None, memory_estimate: memory };
    let job = s.jobs.enqueue(new).await?;
    tracing::info!(job = %job.id, kind = "train", "job queued");
    Ok((StatusCode::ACCEPTED, Json(job)))
}

/// A bake job: the model must be a trained (complete) instant, nerf or
/// capture model whose scene is still there; the bake must fit the job
/// memory limit.
async fn create_bake(s: &AppState, r: CreateBake) -> ApiResult<(StatusCode, Json<Job>)> {
    let (seconds, steps) = bake_budget(&BakeBudget { seconds: r.seconds, steps: r.steps }, "")?;
    let defaults = SplatsConfig::default();
    let splats = SplatsConfig {
        sh_degree: r.sh_degree.unwrap_or(defaults.sh_degree),
        max_gaussians: r.max_gaussians.unwrap_or(defaults.max_gaussians),
    };
    ModelConfig::Splats(splats.clone()).check().map_err(config_error)?;
    let id = &r.model_id;
    let source = s.jobs.get_model(id).await?.ok_or_else(|| ApiError::not_found("model", id))?;
    let kind = ModelConfig::preset(&source.model).map(|c| c.kind()).unwrap_or(source.model.as_str());
    let config = ModelConfig::parse(kind, source.config.clone())
        .map_err(|e| ApiError::internal(format!("model '{id}' has an unreadable configuration: {e}")))?;
    if !config.spec().trains_on_rays() {
        let message = format!(
            "model '{id}' is a '{}' model already: bake a trained instant, nerf or capture model",
            config.kind()
        );
        return Err(ApiError::conflict(message));
    }
    if !source.complete {
        return Err(ApiError::conflict(format!("model '{id}' is still training: bake it once its training has ended")));
    }
    let scene = s.jobs.get_scene(&source.scene_id).await?.ok_or_else(|| {
        ApiError::conflict(format!(
            "the scene of model '{id}' ('{}') was deleted: its photos are what baking needs",
            source.scene_id
        ))
    })?;
    let spec = BakeSpec {
        source_model_id: id.clone(),
        scene_id: scene.id.clone(),
        seconds,
        steps,
        sh_degree: splats.sh_degree,
        max_gaussians: splats.max_gaussians,
        seed: r.seed,
    };
    let e = bake::memory_estimate(&config, &spec, limits::scene_data(&scene, MaskUse::Auto));
    limits::check(&e, &s.config, s.artifacts.free_space().await?)?;
    let new = NewJob { id: None, spec: JobSpec::Bake(spec), model_id: None, memory_estimate: e.memory_bytes };
    let job = s.jobs.enqueue(new).await?;
    tracing::info!(job = %job.id, kind = "bake", model = %id, "job queued");
    Ok((StatusCode::ACCEPTED, Json(job)))
}

#[derive(Debug, Deserialize)]
pub struct ListQuery {
    pub status: Option<String>,
}

pub async fn list(State(s): State<AppState>, q: Result<Query<ListQuery>, QueryRejection>) -> ApiResult<Json<Vec<Job>>> {
    let Query(q) = q?;
    let status = match q.status {
        Some(v) => Some(v.parse::<Status>().map_err(|m| ApiError::bad_field(m, "status", &v, STATUSES))?),
        None => None,
    };
    Ok(Json(s.jobs.list_jobs(status).await?))
}

/// What `?status=` takes.
const STATUSES: &str = "queued, running, succeeded, failed or canceled";

pub async fn get_one(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<Json<Job>> {
    s.jobs.get_job(&id).await?.map(Json).ok_or_else(|| ApiError::not_found("job", &id))
}

/// Cancels a job: a queued one at once; a running one stops within about a
/// training step, keeping its last state as a usable model.
pub async fn cancel(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<(StatusCode, Json<Job>)> {
    let job = s.jobs.cancel(&id).await?;
    Ok((StatusCode::ACCEPTED, Json(job)))
}

/// Deletes a finished job's record (204); what it made stays. A queued or
/// running job is a conflict (409): cancel it first.
pub async fn delete(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    s.jobs.delete_job(&id).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// `GET /v1/jobs/{id}/events`: Server-Sent Events. A `progress` event with
/// the job record whenever it changes (looked at again whenever the job
/// store says it may have: twenty times a second for the embedded store),
/// then an `end` event with the final record, and the stream closes.
/// Comment lines keep idle connections alive.
pub async fn events(
    State(s): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Sse<impl Stream<Item = Result<Event, Infallible>>>> {
    if s.jobs.get_job(&id).await?.is_none() {
        return Err(ApiError::not_found("job", &id));
    }
    let jobs = s.jobs.clone();
    let stream = futures_util::stream::unfold((None::<String>, false), move |(last, ended)| {
        let jobs = jobs.clone();
        let id = id.clone();
        async move {
            if ended {
                return None;
            }
            loop {
                let job = jobs.get_job(&id).await.ok()??;
                let json = serde_json::to_string(&job).ok()?;
                if last.as_deref() != Some(json.as_str()) {
                    let end = job.status.is_final();
                    let event = Event::default().event(if end { "end" } else { "progress" }).data(json.clone());
                    return Some((Ok(event), (Some(json), end)));
                }
                jobs.job_changed(&id).await;
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

#[cfg(test)]
mod tests {
    use serde_json::{Value, json};

    use super::*;

    /// The details of the error `to_spec` gives for a job body.
    fn details(body: Value) -> Value {
        let mut b = json!({ "scene_id": "scn_x", "budget": { "steps": 10 } });
        for (k, v) in body.as_object().unwrap() {
            b[k] = v.clone();
        }
        let r: CreateJob = serde_json::from_value(b).unwrap();
        let e = to_spec(r, Some(photos())).expect_err("a bad body");
        assert_eq!(e.code.info().0, "bad_request");
        e.details
    }

    /// What `auto` chooses for opaque photographs.
    fn photos() -> ModelChoice {
        ModelChoice { preset: "capture".into(), reason: "opaque photographs: the capture model".into() }
    }

    /// The spec of a job body (scene and budget filled in) with `choice`.
    fn spec(body: Value, choice: Option<ModelChoice>) -> ApiResult<TrainSpec> {
        let mut b = json!({ "scene_id": "scn_x", "budget": { "steps": 10 } });
        for (k, v) in body.as_object().unwrap() {
            b[k] = v.clone();
        }
        to_spec(serde_json::from_value(b).unwrap(), choice)
    }

    #[test]
    fn auto_is_the_default_and_takes_the_choice_with_its_reason() {
        let s = spec(json!({}), Some(photos())).unwrap();
        assert_eq!((s.model.as_str(), s.model_reason.as_deref()), ("capture", Some(photos().reason.as_str())));
        assert_eq!(s.config, ModelConfig::preset("capture").unwrap());
        // A named preset or a full config overrides the choice.
        let s = spec(json!({ "model": "nerf-tiny" }), Some(photos())).unwrap();
        assert_eq!((s.model.as_str(), s.model_reason), ("nerf-tiny", None));
        let instant = ModelConfig::preset("instant-tiny").unwrap();
        let s = spec(json!({ "model": "auto", "config": instant }), None).unwrap();
        assert_eq!((s.model.as_str(), s.model_reason, s.config), ("instant", None, instant));
        // `auto` without a choice is the handler's bug, not the client's.
        let e = spec(json!({}), None).unwrap_err();
        assert_eq!(e.code.info().0, "internal");
        // The records keep the reason, and records without one still load.
        let v = serde_json::to_value(spec(json!({}), Some(photos())).unwrap()).unwrap();
        assert_eq!(v["model_reason"], json!(photos().reason));
        let mut old = serde_json::to_value(spec(json!({ "model": "capture" }), None).unwrap()).unwrap();
        assert!(old.get("model_reason").is_none(), "{old}");
        old.as_object_mut().unwrap().remove("masks");
        assert_eq!(serde_json::from_value::<TrainSpec>(old).unwrap().model_reason, None);
    }

    #[test]
    fn bad_job_fields_are_named_with_their_value_and_range() {
        let d = details(json!({ "model": "fast" }));
        assert_eq!((&d["field"], &d["value"]), (&json!("model"), &json!("fast")));
        assert!(d["allowed"].as_str().unwrap().starts_with("auto, instant, instant-tiny"), "{d}");
        let d = details(json!({ "budget": { "seconds": -1.0 } }));
        assert_eq!(d, json!({ "field": "budget.seconds", "value": -1.0, "allowed": "(0, 604800]" }));
        let d = details(json!({ "budget": { "steps": 0 } }));
        assert_eq!(d, json!({ "field": "budget.steps", "value": 0, "allowed": "1..=1000000000" }));
        let d = details(json!({ "budget": { "target_psnr": 150.0 } }));
        assert_eq!(d, json!({ "field": "budget.target_psnr", "value": 150.0, "allowed": "(0, 100]" }));
        let d = details(json!({ "budget": {} }));
        assert_eq!(d["field"], "budget");
        let d = details(json!({ "batch_rays": 0 }));
        assert_eq!(d, json!({ "field": "batch_rays", "value": 0, "allowed": "1..=65536" }));
        let allowed = "auto, score, ignore, composite or off";
        let d = details(json!({ "masks": "sometimes" }));
        assert_eq!(d, json!({ "field": "masks", "value": "sometimes", "allowed": allowed }));
        let d = details(json!({ "masks": 3 }));
        assert_eq!(d, json!({ "field": "masks", "value": 3, "allowed": allowed }));
        let d = details(json!({ "model": "nerf", "config": ModelConfig::preset("instant").unwrap() }));
        assert_eq!(d, json!({ "field": "config.kind", "value": "instant", "allowed": "nerf" }));
        // Out-of-range model settings list every field.
        let mut c = serde_json::to_value(ModelConfig::preset("instant").unwrap()).unwrap();
        c["hidden"] = json!(0);
        c["grid"]["log2_table"] = json!(40);
        let d = details(json!({ "config": c }));
        assert_eq!(d["fields"].as_array().map(Vec::len), Some(2), "{d}");
    }
}
