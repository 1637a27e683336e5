//! `GET /v1/models/{id}/mesh?format=glb|usdz|html`: any trained model (field or
//! splats) as a textured mesh (`engine::mesh`), made inside the model's crop
//! (else its scene box; a capture's automatic crop, found from its training
//! cameras, since its scene reaches the horizon). Making one takes tens of
//! seconds, so the first request starts it in the background and answers
//! `202 Accepted` with its progress; asking again answers the same until
//! the mesh is made, then the file. This node makes one mesh at a time (a
//! request for another meanwhile is a 503 with `Retry-After`) and keeps the
//! last two: the GLB that `<model-viewer>` shows and the USDZ of AR Quick
//! Look asked for after it come from the same mesh, and the second is
//! quick.

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::Json;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::header::{CONTENT_DISPOSITION, CONTENT_TYPE, RETRY_AFTER};
use axum::http::{HeaderName, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;

use super::crop::{invalid_field, training_set};
use super::models::loaded;
use super::{ApiError, ApiResult, AppState, Code, site};
use crate::engine::front::{
    CAPTURE_KIND, CropBox, MESH_STAGES, MeshError, MeshOptions, Model, Placement, TexturedMesh, auto_crop_any,
    crop_model, make_mesh, mesh_glb, mesh_photos, mesh_usdz, scene_box,
};
use crate::records::ModelInfo;

/// Query of `GET /v1/models/{id}/mesh`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshQuery {
    /// `glb` (default: glTF 2.0 binary, for `<model-viewer>` and Android),
    /// `usdz` (for AR Quick Look on iPhone and iPad) or `html` (a zip of a
    /// static web site showing the mesh, with both files).
    pub format: Option<String>,
    /// Most triangles (200,000).
    pub triangles: Option<usize>,
    /// The texture's side, texels (2048; 64 to [`MAX_TEXTURE`]).
    pub texture: Option<u32>,
    /// `false`: the scene's box (or a capture's automatic crop) even when
    /// the model has a crop (default true: inside the model's crop).
    pub crop: Option<bool>,
}

/// The largest texture a request may ask for (its floats take 200 MB while
/// it is made).
pub const MAX_TEXTURE: u32 = 4096;

/// The triangles the mesh holds.
pub const TRIANGLES_HEADER: &str = "x-triangles";

/// Meshes made lately, most recent first, and the one being made.
#[derive(Default)]
pub struct MeshCache {
    state: Mutex<CacheState>,
}

#[derive(Default)]
struct CacheState {
    made: Vec<Made>,
    making: Option<Making>,
}

struct Made {
    key: String,
    mesh: Arc<TexturedMesh>,
    place: Placement,
}

/// The mesh being made in the background, or why it could not be.
struct Making {
    key: String,
    started: Instant,
    /// The stage (`MESH_STAGES`) and the share done, as f32 bits.
    stage: Arc<AtomicUsize>,
    done: Arc<AtomicU32>,
    failed: Option<ApiError>,
}

/// Meshes kept (each up to ~60 MB with a 2048-texel texture).
const KEPT: usize = 2;

/// How long a client is told to wait before asking again, seconds.
const RETRY_SECS: u32 = 2;

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Glb,
    Usdz,
    /// A zip of a static web site showing the mesh (`site::mesh_files`).
    Html,
}

pub async fn get(
    State(s): State<AppState>,
    Path(id): Path<String>,
    q: Result<Query<MeshQuery>, QueryRejection>,
) -> ApiResult<Response> {
    let Query(q) = q?;
    let format = match q.format.as_deref().unwrap_or("glb") {
        "glb" => Format::Glb,
        "usdz" => Format::Usdz,
        "html" => Format::Html,
        f => {
            let message = format!("unknown mesh format '{f}' (expected glb, usdz or html)");
            return Err(ApiError::bad_field(message, "format", f, "glb, usdz, html"));
        }
    };
    let options = options_of(&q)?;
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    let (mesh, place) = match mesh_of(&s, &info, &options, q.crop.unwrap_or(true))? {
        Ready::Made(mesh, place) => (mesh, place),
        Ready::Making(progress) => {
            let retry = [(RETRY_AFTER, RETRY_SECS.to_string())];
            return Ok((StatusCode::ACCEPTED, retry, Json(progress)).into_response());
        }
    };
    let triangles = mesh.triangles.len();
    let folder = format!("{id}-mesh");
    let title = format!("{} ({} mesh)", info.id, info.scene_id);
    let bytes = tokio::task::spawn_blocking(move || -> std::io::Result<Vec<u8>> {
        match format {
            Format::Glb => mesh_glb(&mesh, &place),
            Format::Usdz => mesh_usdz(&mesh, &place),
            Format::Html => {
                let files = site::mesh_files(&title, mesh_glb(&mesh, &place)?, mesh_usdz(&mesh, &place)?);
                let mut out = Vec::new();
                site::write_zip(&folder, &files, std::io::Cursor::new(&mut out))?;
                Ok(out)
            }
        }
    })
    .await?
    .map_err(ApiError::internal)?;
    let (file, content_type) = match format {
        Format::Glb => (format!("{id}.glb"), "model/gltf-binary"),
        Format::Usdz => (format!("{id}.usdz"), "model/vnd.usdz+zip"),
        Format::Html => (format!("{id}-mesh.zip"), "application/zip"),
    };
    Ok((
        [
            (CONTENT_TYPE, content_type.to_string()),
            (CONTENT_DISPOSITION, format!("attachment; filename=\"{file}\"")),
            (HeaderName::from_static(TRIANGLES_HEADER), triangles.to_string()),
        ],
        bytes,
    )
        .into_response())
}

/// The query's options, checked (400 naming the one out of range).
fn options_of(q: &MeshQuery) -> ApiResult<MeshOptions> {
    let d = MeshOptions::default();
    let options =
        MeshOptions { triangles: q.triangles.unwrap_or(d.triangles), texture: q.texture.unwrap_or(d.texture), ..d };
    if options.texture > MAX_TEXTURE {
        let message = format!("texture {}: at most {MAX_TEXTURE} texels a side here", options.texture);
        return Err(ApiError::bad_field(message, "texture", options.texture, &format!("64..={MAX_TEXTURE}")));
    }
    options.check().map_err(|e| match e {
        MeshError::Option(name, why) => {
            ApiError::bad_field(format!("{name} {why}"), name, why.clone(), "see the message")
        }
        e => ApiError::internal(e),
    })?;
    Ok(options)
}

/// A mesh asked for: made, or being made (its progress).
enum Ready {
    Made(Arc<TexturedMesh>, Placement),
    Making(serde_json::Value),
}

/// The model's mesh with these options: kept from before, or being made
/// (started now if nothing else is being made; a 503 if something is), or
/// why it could not be made (said once, then forgotten).
fn mesh_of(s: &AppState, info: &ModelInfo, options: &MeshOptions, use_crop: bool) -> ApiResult<Ready> {
    let record_crop = info.crop.filter(|_| use_crop);
    let key = format!(
        "{}/{}/{}/{}/{}",
        info.id,
        info.updated_at,
        serde_json::to_string(&record_crop).unwrap_or_default(),
        options.triangles,
        options.texture
    );
    let mut state = s.meshes.state.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(m) = state.made.iter().find(|m| m.key == key) {
        return Ok(Ready::Made(m.mesh.clone(), m.place));
    }
    match &mut state.making {
        Some(m) if m.key == key => {
            if let Some(e) = m.failed.take() {
                state.making = None;
                return Err(e);
            }
            return Ok(Ready::Making(progress(m)));
        }
        Some(m) if m.failed.is_none() => {
            return Err(ApiError::new(
                Code::Unavailable,
                format!("this node is making another mesh ({}): ask again in a few seconds", m.stage()),
            )
            .with_details(json!({ "retry_after": RETRY_SECS })));
        }
        _ => {}
    }
    let making = Making {
        key: key.clone(),
        started: Instant::now(),
        stage: Arc::new(AtomicUsize::new(0)),
        done: Arc::new(AtomicU32::new(0)),
        failed: None,
    };
    let (stage, done) = (making.stage.clone(), making.done.clone());
    let answer = progress(&making);
    state.making = Some(making);
    drop(state);
    let (s, info, options) = (s.clone(), info.clone(), options.clone());
    tokio::spawn(async move {
        let made = make(&s, &info, record_crop, options, stage, done).await;
        let mut state = s.meshes.state.lock().unwrap_or_else(|e| e.into_inner());
        match made {
            Ok((mesh, place)) => {
                state.made.insert(0, Made { key, mesh: Arc::new(mesh), place });
                state.made.truncate(KEPT);
                state.making = None;
            }
            Err(e) => {
                tracing::warn!(model = %info.id, error = %e.message, "no mesh");
                if let Some(m) = state.making.as_mut().filter(|m| m.key == key) {
                    m.failed = Some(e);
                }
            }
        }
    });
    Ok(Ready::Making(answer))
}

impl Making {
    /// What is being done (one of `MESH_STAGES`).
    fn stage(&self) -> &'static str {
        MESH_STAGES[self.stage.load(Ordering::Relaxed).min(MESH_STAGES.len() - 1)]
    }
}

/// The 202's body: what is being done, how far, for how long.
fn progress(m: &Making) -> serde_json::Value {
    let done = f32::from_bits(m.done.load(Ordering::Relaxed));
    json!({
        "status": "making",
        "stage": m.stage(),
        "progress": (done.clamp(0.0, 1.0) * 1000.0).round() / 1000.0,
        "elapsed": (m.started.elapsed().as_secs_f64() * 10.0).round() / 10.0,
    })
}

/// Makes the mesh: the model loaded, its crop found, then the engine.
async fn make(
    s: &AppState,
    info: &ModelInfo,
    record_crop: Option<CropBox>,
    options: MeshOptions,
    stage: Arc<AtomicUsize>,
    done: Arc<AtomicU32>,
) -> ApiResult<(TexturedMesh, Placement)> {
    let model = loaded(s, info).await?.model;
    let crop = match record_crop {
        Some(b) => b,
        None => default_crop(s, info, &model).await?,
    };
    // The training photos sharpen the texture; a model whose scene is gone is coloured from itself alone.
    let train = match training_set(s, info, "fit the mesh's texture to its photos").await {
        Ok(ds) => Some(ds),
        Err(e) => {
            tracing::warn!(error = ?e, model = %info.id, "the mesh's texture comes from the model alone");
            None
        }
    };
    tokio::task::spawn_blocking(move || -> ApiResult<(TexturedMesh, Placement)> {
        let photos = train.map(|ds| mesh_photos(&*model, &ds)).unwrap_or_default();
        let cropped = crop_model(&*model, &crop).map_err(|e| invalid_field("crop", e.to_string()))?;
        let source: &dyn Model = cropped.as_ref().map_or(&*model, |m| m as &dyn Model);
        let mut report = |k: usize, d: f32| {
            stage.store(k, Ordering::Relaxed);
            done.store(d.to_bits(), Ordering::Relaxed);
        };
        let never = AtomicBool::new(false);
        let (mesh, _) = make_mesh(source, &crop, &options, &photos, &mut report, &never).map_err(|e| match e {
            MeshError::Empty => ApiError::conflict(format!("{e}: set another crop (PUT /v1/models/{{id}}/crop)")),
            e => ApiError::internal(e),
        })?;
        let front = model.scene().rig.as_ref().map(|r| r.front);
        let place = Placement::new(&mesh, &crop, front, 0.5);
        Ok((mesh, place))
    })
    .await?
}

/// Without a crop: the scene's box, or for a capture (whose scene reaches
/// the horizon) the box around what its training cameras all see.
async fn default_crop(s: &AppState, info: &ModelInfo, model: &Arc<dyn Model>) -> ApiResult<CropBox> {
    if model.kind() != CAPTURE_KIND {
        return Ok(scene_box(&**model));
    }
    let ds = training_set(s, info, "find the object (or PUT a crop box)").await?;
    let model = model.clone();
    let id = info.id.clone();
    tokio::task::spawn_blocking(move || -> ApiResult<CropBox> {
        auto_crop_any(&*model, &ds, &AtomicBool::new(false))
            .map_err(|e| ApiError::conflict(format!("finding the object: {e}")))?
            .ok_or_else(|| {
                ApiError::conflict(format!(
                    "model '{id}''s capture was not walked around (forward-facing, or no rig): PUT a crop box \
                     (PUT /v1/models/{id}/crop) to make a mesh of what is inside it"
                ))
            })
    })
    .await?
}
