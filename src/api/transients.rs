//! `GET /v1/models/{id}/transients/{photo}`: the transient mask of one of
//! a model's training photos, for a model trained with `drop_transients`
//! (its record's `transients` lists the photos and their shares).

use axum::extract::{Path, State};
use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;

use super::{ApiError, ApiResult, AppState, models};
use crate::media::png::encode_gray;

/// The mask of training photo `photo` (its name, the image file's stem) as
/// an 8-bit PNG of the photo's size: 255 where training used the pixel, 0
/// where it was dropped as transient (the layout of a dataset's `masks/`).
/// The maps come with the model from the API's model cache, so the masks of
/// one model read its checkpoint once.
pub async fn get(State(s): State<AppState>, Path((id, photo)): Path<(String, String)>) -> ApiResult<impl IntoResponse> {
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    if info.transients.is_none() {
        return Err(ApiError::conflict(format!(
            "model '{id}' has no transient masks: it did not drop transients (a model other than capture, or drop_transients false) or is still training"
        )));
    }
    let maps = models::loaded(&s, &info).await?.transients;
    let name = photo.clone();
    let png = tokio::task::spawn_blocking(move || -> ApiResult<Option<Vec<u8>>> {
        let Some((w, h, gray)) = maps.and_then(|m| m.mask_image(m.index_of(&name)?)) else { return Ok(None) };
        encode_gray(w, h, &gray).map(Some).map_err(ApiError::internal)
    })
    .await??;
    let png = png.ok_or_else(|| ApiError::not_found("training photo", &photo))?;
    Ok(([(CONTENT_TYPE, "image/png")], png))
}
