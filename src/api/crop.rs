//! A model's crop volume: `GET`, `PUT` and `DELETE /v1/models/{id}/crop`.
//!
//! The crop is an oriented box in world units (`centre`, unit orthogonal
//! `axes` as rows, `half` extents) stored on the model's record. A splats
//! model's views, videos and exports then keep only the Gaussians inside
//! it (`crop=false` on a render or an export shows them all); a field
//! model's views are not cropped, but its crop carries over to its bake.
//! `PUT` takes a box, or `{"auto": true}` for the box the engine finds
//! around what the training cameras all look at (`engine::front::auto_crop`,
//! a splats model of a capture walked around).

use axum::Json;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use serde_json::json;

use super::error::Code;
use super::{ApiError, ApiResult, AppState, models};
use crate::datadir::ScenePart;
use crate::engine::front::{CropBox, CropError, Dataset, MaskUse, auto_crop_for, crop_model, splats_of};
use crate::jobs::scoring::load_dataset;
use crate::records::ModelInfo;

/// The body of `PUT /v1/models/{id}/crop`.
enum CropRequest {
    Auto,
    Box(CropBox),
}

/// `body` as a request: `{"auto": true}`, or a box whose every field is
/// there with its shape; otherwise 422 naming the field.
fn parse(body: serde_json::Value) -> ApiResult<CropRequest> {
    let serde_json::Value::Object(fields) = body else {
        return Err(invalid_field("crop", "must be a JSON object: a box or {\"auto\": true}".into()));
    };
    if let Some(auto) = fields.get("auto") {
        if let Some(other) = fields.keys().find(|k| *k != "auto") {
            return Err(invalid_field(other, "is not taken beside auto".into()));
        }
        return match auto {
            serde_json::Value::Bool(true) => Ok(CropRequest::Auto),
            v => Err(invalid_field("auto", format!("{v}: must be true (DELETE removes the crop)"))),
        };
    }
    if let Some(other) = fields.keys().find(|k| !["centre", "axes", "half"].contains(&k.as_str())) {
        return Err(invalid_field(other, "is not a field of a crop box (centre, axes, half)".into()));
    }
    let field = |name: &str, shape: &str| -> ApiResult<serde_json::Value> {
        fields.get(name).cloned().ok_or_else(|| invalid_field(name, format!("is missing: {shape}")))
    };
    let triple = |name: &str| -> ApiResult<[f32; 3]> {
        serde_json::from_value(field(name, "three numbers")?)
            .map_err(|_| invalid_field(name, "must be three numbers".into()))
    };
    let axes: [[f32; 3]; 3] = serde_json::from_value(field("axes", "three rows of three numbers")?)
        .map_err(|_| invalid_field("axes", "must be three rows of three numbers".into()))?;
    Ok(CropRequest::Box(CropBox { centre: triple("centre")?, axes, half: triple("half")? }))
}

/// `GET`: the model's crop, or 404 when it has none.
pub async fn get(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<Json<CropBox>> {
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    let crop = info.crop.ok_or_else(|| {
        ApiError::new(Code::NotFound, format!("model '{id}' has no crop (PUT /v1/models/{id}/crop sets one)"))
            .with_details(json!({ "kind": "crop", "id": id }))
    })?;
    Ok(Json(crop))
}

/// `PUT`: stores the box given (checked: 422 naming the field; a box that
/// keeps none of a splats model's Gaussians is refused too) or the one found
/// automatically, and answers with it.
pub async fn put(
    State(s): State<AppState>,
    Path(id): Path<String>,
    body: Result<Json<serde_json::Value>, JsonRejection>,
) -> ApiResult<Json<CropBox>> {
    let Json(body) = body?;
    let request = parse(body)?;
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    let model = models::model_of(&s, &info).await?;
    let b = match request {
        CropRequest::Auto => {
            if splats_of(&*model).is_none() {
                return Err(ApiError::conflict(format!(
                    "model '{id}' is a '{}' model: the automatic crop is found from splats; bake it first, or PUT a box",
                    model.kind()
                )));
            }
            let ds = training_set(&s, &info, "find the crop").await?;
            let model = model.clone();
            let found = tokio::task::spawn_blocking(move || -> ApiResult<Option<CropBox>> {
                auto_crop_for(splats_of(&*model).expect("checked above"), &ds).map_err(invalid)
            })
            .await??;
            found.ok_or_else(|| {
                invalid_field(
                    "auto",
                    "the capture was not walked around (forward-facing, or no rig): PUT a box instead".into(),
                )
            })?
        }
        CropRequest::Box(b) => b,
    };
    let check = model.clone();
    tokio::task::spawn_blocking(move || crop_model(&*check, &b).map(|_| ())).await?.map_err(invalid)?;
    let info = s.jobs.set_crop(&id, Some(b)).await?;
    tracing::info!(model = %id, "crop set");
    Ok(Json(info.crop.expect("just set")))
}

/// The model's scene as it trained on it (no masks), loaded on the blocking
/// threads, to find an automatic crop from its training cameras; `purpose`
/// completes "needed to ..." and "loading the scene to ..." in the errors.
pub(super) async fn training_set(s: &AppState, info: &ModelInfo, purpose: &str) -> ApiResult<Dataset> {
    let scene = s.jobs.get_scene(&info.scene_id).await?.ok_or_else(|| {
        ApiError::conflict(format!(
            "model '{}''s scene '{}' is gone: its training cameras are needed to {purpose}",
            info.id, info.scene_id
        ))
    })?;
    let files = s.artifacts.scene_files(&scene, ScenePart::Data).await?;
    let loaded = tokio::task::spawn_blocking(move || load_dataset(&files.path, &scene, MaskUse::Off)).await?;
    loaded.map_err(|e| ApiError::internal(format!("loading the scene to {purpose}: {e}")))
}

/// `DELETE`: removes the crop (204; 404 when there was none).
pub async fn delete(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    if info.crop.is_none() {
        return Err(ApiError::new(Code::NotFound, format!("model '{id}' has no crop"))
            .with_details(json!({ "kind": "crop", "id": id })));
    }
    s.jobs.set_crop(&id, None).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// A crop that cannot be used: 422 naming the field.
fn invalid(e: CropError) -> ApiError {
    match e {
        CropError::Field(field, why) => invalid_field(field, why),
        CropError::Empty(n) => invalid_field("crop", format!("keeps none of the model's {n} Gaussians")),
        CropError::Unseen => invalid_field("auto", e.to_string()),
        CropError::Model(e) => ApiError::internal(e),
    }
}

pub(super) fn invalid_field(field: &str, why: String) -> ApiError {
    let message = if field == "crop" { format!("the crop {why}") } else { format!("crop {field}: {why}") };
    ApiError::new(Code::InvalidCrop, message).with_details(json!({ "field": field }))
}
