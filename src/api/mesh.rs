//! `GET /v1/models/{id}/mesh?format=glb|usdz|html`: any trained model (field or
//! splats) as a textured mesh (`engine::mesh`), made inside the model's crop
//! (else its scene box; a capture's automatic crop, found from its training
//! cameras, since its scene reaches the horizon). Making one takes tens of
//! seconds, so this node makes one at a time and keeps the last few: the
//! GLB that `<model-viewer>` shows and the USDZ of AR Quick Look asked for
//! after it come from the same mesh, and the second is quick. A client that
//! goes away stops the work.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::HeaderName;
use axum::http::header::{CONTENT_DISPOSITION, CONTENT_TYPE};
use axum::response::IntoResponse;
use serde::Deserialize;

use super::crop::invalid_field;
use super::models::{CancelOnDrop, loaded};
use super::{ApiError, ApiResult, AppState, site};
use crate::datadir::ScenePart;
use crate::engine::front::{
    CAPTURE_KIND, CropBox, MaskUse, MeshError, MeshOptions, Model, Placement, TexturedMesh, auto_crop_any, crop_model,
    make_mesh, mesh_glb, mesh_usdz, scene_box,
};
use crate::jobs::scoring::load_dataset;
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

/// Meshes made lately, most recent first, and the lock that lets this node
/// make one at a time.
#[derive(Default)]
pub struct MeshCache {
    made: tokio::sync::Mutex<Vec<Made>>,
}

struct Made {
    key: String,
    mesh: Arc<TexturedMesh>,
    place: Placement,
}

/// Meshes kept (each up to ~60 MB with a 2048-texel texture).
const KEPT: usize = 2;

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
) -> ApiResult<impl IntoResponse> {
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
    let (mesh, place) = mesh_of(&s, &info, &options, q.crop.unwrap_or(true)).await?;
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
    ))
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

/// The model's mesh with these options: kept from before, or made now
/// (one at a time on this node).
async fn mesh_of(
    s: &AppState,
    info: &ModelInfo,
    options: &MeshOptions,
    use_crop: bool,
) -> ApiResult<(Arc<TexturedMesh>, Placement)> {
    let record_crop = info.crop.filter(|_| use_crop);
    let key = format!(
        "{}/{}/{}/{}/{}",
        info.id,
        info.updated_at,
        serde_json::to_string(&record_crop).unwrap_or_default(),
        options.triangles,
        options.texture
    );
    let mut made = s.meshes.made.lock().await;
    if let Some(m) = made.iter().find(|m| m.key == key) {
        return Ok((m.mesh.clone(), m.place));
    }
    let model = loaded(s, info).await?.model;
    let crop = match record_crop {
        Some(b) => b,
        None => default_crop(s, info, &model).await?,
    };
    let cancel = CancelOnDrop(Arc::new(AtomicBool::new(false)));
    let flag = cancel.0.clone();
    let options = options.clone();
    let (mesh, place) = tokio::task::spawn_blocking(move || -> ApiResult<(TexturedMesh, Placement)> {
        let cropped = crop_model(&*model, &crop).map_err(|e| invalid_field("crop", e.to_string()))?;
        let source: &dyn Model = cropped.as_ref().map_or(&*model, |m| m as &dyn Model);
        let (mesh, _) = make_mesh(source, &crop, &options, &mut |_, _| {}, &flag).map_err(|e| match e {
            MeshError::Empty => ApiError::conflict(format!("{e}: set another crop (PUT /v1/models/{{id}}/crop)")),
            e => ApiError::internal(e),
        })?;
        let front = model.scene().rig.as_ref().map(|r| r.front);
        let place = Placement::new(&mesh, &crop, front, 0.5);
        Ok((mesh, place))
    })
    .await??;
    drop(cancel);
    let mesh = Arc::new(mesh);
    made.insert(0, Made { key, mesh: mesh.clone(), place });
    made.truncate(KEPT);
    Ok((mesh, place))
}

/// Without a crop: the scene's box, or for a capture (whose scene reaches
/// the horizon) the box around what its training cameras all see.
async fn default_crop(s: &AppState, info: &ModelInfo, model: &Arc<dyn Model>) -> ApiResult<CropBox> {
    if model.kind() != CAPTURE_KIND {
        return Ok(scene_box(&**model));
    }
    let scene = s.jobs.get_scene(&info.scene_id).await?.ok_or_else(|| {
        ApiError::conflict(format!(
            "model '{}''s scene '{}' is gone: its training cameras are needed to find the object; PUT a crop box",
            info.id, info.scene_id
        ))
    })?;
    let files = s.artifacts.scene_files(&scene, ScenePart::Data).await?;
    let model = model.clone();
    let id = info.id.clone();
    tokio::task::spawn_blocking(move || -> ApiResult<CropBox> {
        let ds = load_dataset(&files.path, &scene, MaskUse::Off)
            .map_err(|e| ApiError::internal(format!("loading the scene to find the object: {e}")))?;
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
