//! `/v1/scenes`: upload a dataset as an archive, list, get, delete.
//!
//! An upload is extracted into `tmp/ID/data`, loaded and validated by the
//! engine's loader, its record written to `tmp/ID/scene.json`, and only then
//! renamed into `scenes/ID`: a scene either exists whole or not at all, and a
//! failed upload leaves nothing behind.

use std::path::Path;

use axum::Json;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path as UrlPath, State};
use axum::http::{HeaderMap, StatusCode, header::CONTENT_TYPE};

use super::archive::{self, ArchiveError, ArchiveKind, Limits};
use super::{ApiError, ApiResult, AppState, Code};
use crate::engine::dataset::{Dataset, LoadOptions};
use crate::engine::math::Vec3;
use crate::jobs::SchedError;
use crate::storage::{SceneInfo, SplitCounts, Storage, ViewDefaults, new_id, now_ms, write_json};

pub async fn create(
    State(s): State<AppState>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(StatusCode, Json<SceneInfo>)> {
    let ct = headers.get(CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    let kind = ArchiveKind::from_content_type(ct).ok_or_else(|| {
        ApiError::new(
            Code::UnsupportedMediaType,
            format!(
                "Content-Type '{ct}' is not an accepted archive (application/zip, application/x-tar, application/gzip)"
            ),
        )
    })?;
    let body = body.map_err(|e| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            ApiError::new(Code::PayloadTooLarge, format!("upload is larger than {} bytes", s.config.max_upload_bytes))
        } else {
            ApiError::bad_request(format!("reading the upload: {}", e.body_text()))
        }
    })?;
    if body.is_empty() {
        return Err(ApiError::bad_request("empty upload: send the archive as the request body"));
    }
    let limits = Limits { max_unpacked_bytes: s.config.max_unpacked_bytes, max_entries: s.config.max_archive_entries };
    let storage = s.storage.clone();
    let info = tokio::task::spawn_blocking(move || ingest(&storage, kind, &body, limits)).await??;
    tracing::info!(scene = %info.id, format = %info.format, train = info.images.train, "scene stored");
    Ok((StatusCode::CREATED, Json(info)))
}

/// Extracts, validates and stores an archive; removes everything on failure.
fn ingest(storage: &Storage, kind: ArchiveKind, bytes: &[u8], limits: Limits) -> ApiResult<SceneInfo> {
    let id = new_id("scn");
    let staging = storage.tmp_dir().join(&id);
    let result = (|| {
        let data = staging.join("data");
        std::fs::create_dir_all(&data)?;
        let size = archive::extract(kind, bytes, &data, limits).map_err(|e| match e {
            ArchiveError::Bad(m) => ApiError::bad_request(m),
            ArchiveError::TooLarge(m) => ApiError::new(Code::PayloadTooLarge, m),
            ArchiveError::Io(e) => ApiError::internal(e),
        })?;
        let root = archive::dataset_root(&data);
        let ds = Dataset::load(&root, &LoadOptions::default()).map_err(|e| {
            // Name files relative to the archive, not the server's folders.
            let prefix = format!("{}/", data.display());
            ApiError::new(
                Code::InvalidDataset,
                e.to_string().replace(&prefix, "").replace(&*data.to_string_lossy(), "."),
            )
        })?;
        if ds.train.is_empty() {
            return Err(ApiError::new(Code::InvalidDataset, "the dataset has no training views"));
        }
        let rel = root.strip_prefix(&staging).unwrap_or(Path::new("data")).to_string_lossy().into_owned();
        let info = scene_info(&id, &ds, size, rel);
        write_json(&staging.join("scene.json"), &info)?;
        std::fs::rename(&staging, storage.scene_dir(&id))?;
        Ok(info)
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&staging);
    }
    result
}

fn scene_info(id: &str, ds: &Dataset, size_bytes: u64, root: String) -> SceneInfo {
    let cam = &ds.frames[ds.train[0]].camera;
    let centre = ds.centre();
    let (mut up, mut dist) = (Vec3::splat(0.0), 0.0);
    for f in ds.split_frames(crate::engine::dataset::Split::Train) {
        up = up + f.camera.rotate(Vec3::new(0.0, 1.0, 0.0));
        dist += (f.camera.origin() - centre).norm();
    }
    let up = up.normalized().unwrap_or(Vec3::new(0.0, 0.0, 1.0));
    let mut warnings = ds.warnings.clone();
    if ds.test.is_empty() && ds.val.is_empty() {
        warnings.push("no held-out views: models of this scene cannot be measured".into());
    }
    SceneInfo {
        id: id.to_string(),
        format: ds.format,
        images: SplitCounts { train: ds.train.len(), val: ds.val.len(), test: ds.test.len() },
        resolution: [cam.width, cam.height],
        warnings,
        created_at: now_ms(),
        size_bytes,
        root,
        view: ViewDefaults {
            width: cam.width,
            height: cam.height,
            fov: (2.0 * (0.5 * cam.width as f32 / cam.fx).atan()).to_degrees(),
            centre: centre.to_array(),
            up: up.to_array(),
            radius: dist / ds.train.len() as f32,
            far: ds.far,
        },
    }
}

pub async fn list(State(s): State<AppState>) -> ApiResult<Json<Vec<SceneInfo>>> {
    let storage = s.storage.clone();
    Ok(Json(tokio::task::spawn_blocking(move || storage.list_scenes()).await??))
}

pub async fn get_one(State(s): State<AppState>, UrlPath(id): UrlPath<String>) -> ApiResult<Json<SceneInfo>> {
    s.storage.load_scene(&id)?.map(Json).ok_or_else(|| ApiError::not_found("scene", &id))
}

/// Deletes a scene unless a queued or running job uses it (409). Models
/// trained on it stay usable.
pub async fn delete(State(s): State<AppState>, UrlPath(id): UrlPath<String>) -> ApiResult<StatusCode> {
    if s.storage.load_scene(&id)?.is_none() {
        return Err(ApiError::not_found("scene", &id));
    }
    let storage = s.storage.clone();
    let trash = storage.tmp_dir().join(format!("deleted_{id}"));
    let (t2, id2) = (trash.clone(), id.clone());
    s.scheduler
        .delete_scene(&id, move || {
            // One rename makes the scene disappear; the files go after.
            std::fs::rename(storage.scene_dir(&id2), &t2)
        })
        .map_err(|e| match e {
            SchedError::SceneInUse { .. } => ApiError::conflict(e.to_string()),
            SchedError::Io(io) if io.kind() == std::io::ErrorKind::NotFound => ApiError::not_found("scene", &id),
            other => ApiError::internal(other),
        })?;
    tokio::task::spawn_blocking(move || std::fs::remove_dir_all(trash)).await??;
    Ok(StatusCode::NO_CONTENT)
}
