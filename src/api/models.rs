//! `/v1/models`: list, get, delete, render a novel view as PNG, and export
//! a splats model (`.splat`, `.ply`, `.spz`, `.glb`, or a static web site),
//! each inside the model's crop (`api::crop`) unless asked with
//! `crop=false`.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use axum::Json;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::HeaderName;
use axum::http::StatusCode;
use axum::http::header::{CONTENT_DISPOSITION, CONTENT_TYPE};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};

use super::{ApiError, ApiResult, AppInner, AppState, CachedModel, site};
use crate::backend::Artifact;
use crate::engine::front::{
    Appearance, Camera, CheckpointError, CleanupSettings, Model, Removed, SplatsFormat, cleanup, crop_model,
    load_checkpoint, render_view_until, splats_of, write_splats,
};
use crate::media::png::{self, ViewImage};
use crate::records::{ModelInfo, VideoInfo, ViewDefaults};

/// A model as the API shows it: its record and the disk use of its videos.
#[derive(Debug, Serialize)]
pub struct ModelView {
    #[serde(flatten)]
    pub info: ModelInfo,
    /// Bytes of the videos rendered from this model (`size_bytes` is the
    /// checkpoint's).
    pub videos_bytes: u64,
}

fn view_of(info: ModelInfo, videos: &[VideoInfo]) -> ModelView {
    let videos_bytes = videos.iter().filter(|v| v.model_id == info.id).map(|v| v.size_bytes).sum();
    ModelView { info, videos_bytes }
}

pub async fn list(State(s): State<AppState>) -> ApiResult<Json<Vec<ModelView>>> {
    let videos = s.jobs.list_videos().await?;
    Ok(Json(s.jobs.list_models().await?.into_iter().map(|m| view_of(m, &videos)).collect()))
}

pub async fn get_one(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<Json<ModelView>> {
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    Ok(Json(view_of(info, &s.jobs.list_videos().await?)))
}

/// Deletes a model (record, then checkpoint) and forgets its loaded copy:
/// 204, 404, or 409 while a queued or running job writes or renders it.
/// Videos made from it stay.
pub async fn delete(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    s.jobs.delete_model(&id).await?;
    super::remove_artifact(&s, Artifact::Model(&id)).await;
    s.model_cache.lock().unwrap_or_else(|e| e.into_inner()).retain(|c| c.id != id);
    Ok(StatusCode::NO_CONTENT)
}

/// Query of `GET /v1/models/{id}/render`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderQuery {
    /// Camera-to-world matrix, 12 or 16 comma-separated numbers, row-major
    /// (OpenGL convention: the camera looks down its -z).
    pub c2w: Option<String>,
    /// Orbit position in degrees around the scene's up axis (0: the side the
    /// training cameras saw it from) ...
    pub azimuth: Option<f32>,
    /// ... degrees above the horizon (default: the training cameras' mean) ...
    pub elevation: Option<f32>,
    /// ... and distance from the scene centre (default: the training cameras').
    pub radius: Option<f32>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Horizontal field of view in degrees.
    pub fov: Option<f32>,
    /// `rgb` (default), `depth` (16-bit: distance / far * 65535, composited
    /// over the far plane, so nothing hit is white; see
    /// [`png::depth_u16`]) or `alpha`.
    pub output: Option<String>,
    /// `white` (default), `black` or `transparent` (RGBA).
    pub background: Option<String>,
    /// `mean` (default: the mean appearance of the images trained on; for
    /// splats baked from a capture model, their own look) or a training
    /// image's index (its appearance, or its colour correction); models
    /// without per-image appearance ignore it.
    pub appearance: Option<String>,
    /// `false`: every Gaussian of a splats model with a crop (default true:
    /// only those inside it).
    pub crop: Option<bool>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Output {
    Rgb,
    Depth,
    Alpha,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Background {
    Colour([f32; 3]),
    Transparent,
}

/// Parses a matrix of 12 or 16 numbers and checks that it is a finite
/// rigid transform.
pub fn parse_c2w(s: &str) -> Result<[[f32; 4]; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|t| t.trim().parse::<f32>().map_err(|_| format!("c2w: '{}' is not a number", t.trim())))
        .collect::<Result<_, _>>()?;
    if v.len() != 12 && v.len() != 16 {
        return Err(format!("c2w needs 12 or 16 numbers, got {}", v.len()));
    }
    if v.iter().any(|x| !x.is_finite()) {
        return Err("c2w has a non-finite number".into());
    }
    if v.len() == 16 && v[12..] != [0.0, 0.0, 0.0, 1.0] {
        return Err("c2w: the last row of a 4x4 matrix must be 0,0,0,1".into());
    }
    let m = [[v[0], v[1], v[2], v[3]], [v[4], v[5], v[6], v[7]], [v[8], v[9], v[10], v[11]]];
    for a in 0..3 {
        for b in 0..3 {
            let dot: f32 = (0..3).map(|r| m[r][a] * m[r][b]).sum();
            let want = if a == b { 1.0 } else { 0.0 };
            if (dot - want).abs() > 1e-3 {
                return Err("c2w: the rotation part is not orthonormal".into());
            }
        }
    }
    Ok(m)
}

/// What `appearance` takes in a request.
const APPEARANCE: &str = "mean, or a training image's index";

/// Reads a request's `appearance` (render query, video body): `mean` (the
/// default) or a training image's index. `nearest` is the command line's
/// (and held-out scoring's) only: a request names what it wants to see.
pub(super) fn parse_appearance(value: Option<&str>) -> ApiResult<Appearance> {
    match value.map(str::parse::<Appearance>) {
        None => Ok(Appearance::Mean),
        Some(Ok(Appearance::Nearest)) | Some(Err(_)) => {
            let v = value.unwrap_or_default();
            let message = format!("appearance '{v}': expected mean or a training image's index");
            Err(ApiError::bad_field(message, "appearance", v, APPEARANCE))
        }
        Some(Ok(a)) => Ok(a),
    }
}

/// What `c2w` takes.
const C2W: &str = "12 or 16 comma-separated numbers: a rigid transform, row-major";

/// A render's camera and what to draw of it.
#[derive(Debug)]
struct Request {
    camera: Camera,
    output: Output,
    background: Background,
    appearance: Appearance,
}

fn parse_query(q: &RenderQuery, view: &ViewDefaults, max_pixels: u64) -> ApiResult<Request> {
    let orbit = q.azimuth.is_some() || q.elevation.is_some() || q.radius.is_some();
    let pose = match &q.c2w {
        Some(_) if orbit => return Err(ApiError::bad_request("give either c2w or azimuth/elevation/radius, not both")),
        Some(m) => parse_c2w(m).map_err(|e| ApiError::bad_field(e, "c2w", m, C2W))?,
        None => {
            let (az, el, r) =
                (q.azimuth.unwrap_or(0.0), q.elevation.unwrap_or(view.elevation), q.radius.unwrap_or(view.radius));
            let orbit_error = |field: &str, value: f32, allowed: &str| {
                let message = "orbit needs finite azimuth, elevation in [-90, 90], radius > 0";
                ApiError::bad_field(message, field, value, allowed)
            };
            if !az.is_finite() {
                return Err(orbit_error("azimuth", az, "finite"));
            }
            if !(el.is_finite() && (-90.0..=90.0).contains(&el)) {
                return Err(orbit_error("elevation", el, "[-90, 90]"));
            }
            if !(r.is_finite() && r > 0.0) {
                return Err(orbit_error("radius", r, "> 0"));
            }
            view.orbit(el, r)
                .pose(az)
                .ok_or_else(|| ApiError::bad_request("this orbit position gives no well-defined camera"))?
        }
    };
    let (width, height) = view.frame_size(q.width, q.height);
    if width == 0 || height == 0 || width > 8192 || height > 8192 || width as u64 * height as u64 > max_pixels {
        let allowed = format!("at most {max_pixels} pixels, sides 1..=8192");
        let message = format!("render size {width}x{height} is out of range ({allowed})");
        return Err(ApiError::bad_field(message, "width,height", [width, height], &allowed));
    }
    let fov = q.fov.unwrap_or(view.fov);
    if !(fov.is_finite() && fov > 1.0 && fov < 179.0) {
        return Err(ApiError::bad_field("fov must be between 1 and 179 degrees", "fov", fov, "(1, 179)"));
    }
    let output = match q.output.as_deref().unwrap_or("rgb") {
        "rgb" => Output::Rgb,
        "depth" => Output::Depth,
        "alpha" => Output::Alpha,
        o => {
            let message = format!("unknown output '{o}' (expected rgb, depth or alpha)");
            return Err(ApiError::bad_field(message, "output", o, "rgb, depth, alpha"));
        }
    };
    let background = match q.background.as_deref().unwrap_or("white") {
        "white" => Background::Colour([1.0; 3]),
        "black" => Background::Colour([0.0; 3]),
        "transparent" => Background::Transparent,
        b => {
            let message = format!("unknown background '{b}' (expected white, black or transparent)");
            return Err(ApiError::bad_field(message, "background", b, "white, black, transparent"));
        }
    };
    let appearance = parse_appearance(q.appearance.as_deref())?;
    Ok(Request { camera: Camera::from_fov(width, height, fov.to_radians(), pose), output, background, appearance })
}

pub async fn render(
    State(s): State<AppState>,
    Path(id): Path<String>,
    q: Result<Query<RenderQuery>, QueryRejection>,
) -> ApiResult<impl IntoResponse> {
    let Query(q) = q?;
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    let Request { camera, output, background, appearance } = parse_query(&q, &info.view, s.config.max_render_pixels)?;
    let _slot = s.render_slots.acquire().await.map_err(ApiError::internal)?;
    let t0 = Instant::now();
    let loaded = loaded(&s, &info).await?;
    let model = if q.crop.unwrap_or(true) { loaded.viewed()? } else { loaded.model };
    // Set when this handler is dropped: the client went away (a viewer that
    // moved on), so the render stops instead of holding the workers.
    let cancel = CancelOnDrop(Arc::new(AtomicBool::new(false)));
    let flag = cancel.0.clone();
    let png = tokio::task::spawn_blocking(move || -> ApiResult<Option<Vec<u8>>> {
        let bg = match background {
            Background::Colour(c) => c,
            Background::Transparent => [0.0; 3],
        };
        let options = appearance.resolve(&*model, &camera)?;
        let Some(v) = render_view_until(&*model, &camera, bg, &options, &flag) else { return Ok(None) };
        png::encode_view(&v, image_of(output, background, info.view.far)).map(Some).map_err(ApiError::internal)
    })
    .await??;
    drop(cancel);
    let png = png.ok_or_else(|| ApiError::internal("render cancelled"))?;
    let mut r = s.renders.lock().unwrap_or_else(|e| e.into_inner());
    r.count += 1;
    r.seconds += t0.elapsed().as_secs_f64();
    Ok(([(CONTENT_TYPE, "image/png")], png))
}

/// Query of `GET /v1/models/{id}/export`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExportQuery {
    /// `splat` (default: antimatter15's 32 bytes a Gaussian), `ply` (the
    /// 3DGS paper's layout), `spz` (Niantic's, version 3), `glb` (glTF with
    /// `KHR_gaussian_splatting`) or `html` (a zip of a static web site
    /// showing the splats: `api::site`).
    pub format: Option<String>,
    /// `false`: every Gaussian, without the floater cleanup (default true).
    pub cleanup: Option<bool>,
    /// `false`: the Gaussians outside the model's crop too (default true:
    /// only those inside it).
    pub crop: Option<bool>,
}

/// What `format` takes.
const EXPORT_FORMATS: &str = "splat, ply, spz, glb or html";

/// The Gaussians an export holds, and those its floater cleanup removed.
pub const GAUSSIANS_HEADER: &str = "x-gaussians";
pub const REMOVED_HEADER: &str = "x-gaussians-removed";
/// The Gaussians outside the model's crop, left out of the export.
pub const CROPPED_HEADER: &str = "x-gaussians-cropped";

/// `GET /v1/models/{id}/export`: a splats model as a file other tools
/// open, or as a static web site (zip), named by `Content-Disposition`,
/// after the floater cleanup unless `cleanup=false` (its count in the
/// `X-Gaussians-Removed` header, the Gaussians written in `X-Gaussians`).
/// A model of another kind is a conflict (409), saying to bake it.
pub async fn export(
    State(s): State<AppState>,
    Path(id): Path<String>,
    q: Result<Query<ExportQuery>, QueryRejection>,
) -> ApiResult<impl IntoResponse> {
    let Query(q) = q?;
    let name = q.format.as_deref().unwrap_or("splat");
    let format = match name {
        "html" => None,
        f => Some(SplatsFormat::parse(f).ok_or_else(|| {
            let message = format!("unknown export format '{f}' (expected {EXPORT_FORMATS})");
            ApiError::bad_field(message, "format", f, EXPORT_FORMATS)
        })?),
    };
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    let loaded = loaded(&s, &info).await?;
    let all = splats_of(&*loaded.model).map_or(0, |m| m.layout().n);
    let model = if q.crop.unwrap_or(true) { loaded.viewed()? } else { loaded.model };
    if splats_of(&*model).is_none() {
        return Err(ApiError::conflict(format!(
            "model '{id}' is a '{}' model: only splats export as {name}; bake it first (POST /v1/jobs {{\"kind\": \"bake\", \"model_id\": \"{id}\"}})",
            model.kind()
        )));
    }
    let view = info.view.clone();
    let title = format!("{} ({} splats)", info.id, info.scene_id);
    let folder = format!("{id}-site");
    let folder2 = folder.clone();
    let settings = if q.cleanup.unwrap_or(true) { CleanupSettings::default() } else { CleanupSettings::OFF };
    let cropped = all - splats_of(&*model).map_or(0, |m| m.layout().n);
    let (bytes, removed, kept) = tokio::task::spawn_blocking(move || -> std::io::Result<(Vec<u8>, Removed, usize)> {
        let (splats, removed) =
            cleanup(splats_of(&*model).expect("checked above"), &settings).map_err(std::io::Error::other)?;
        let splats = &splats;
        let mut out = Vec::new();
        match format {
            Some(f) => write_splats(splats, f, &mut out)?,
            None => {
                let mut spz = Vec::new();
                write_splats(splats, SplatsFormat::Spz, &mut spz)?;
                let files = site::files(&title, &view, spz)?;
                site::write_zip(&folder2, &files, std::io::Cursor::new(&mut out))?;
            }
        }
        Ok((out, removed, splats.layout().n))
    })
    .await?
    .map_err(ApiError::internal)?;
    let (file, content_type) = match format {
        Some(f) => (format!("{id}.{}", f.extension()), f.content_type()),
        None => (format!("{folder}.zip"), "application/zip"),
    };
    let disposition = format!("attachment; filename=\"{file}\"");
    Ok((
        [
            (CONTENT_TYPE, content_type.to_string()),
            (CONTENT_DISPOSITION, disposition),
            (HeaderName::from_static(GAUSSIANS_HEADER), kept.to_string()),
            (HeaderName::from_static(REMOVED_HEADER), removed.total().to_string()),
            (HeaderName::from_static(CROPPED_HEADER), cropped.to_string()),
        ],
        bytes,
    ))
}

/// Sets its flag when dropped.
struct CancelOnDrop(Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// Loads a model from its checkpoint (on the blocking threads), or reuses
/// it when its record has not changed.
pub(super) async fn model_of(s: &AppInner, info: &ModelInfo) -> ApiResult<Arc<dyn Model>> {
    Ok(loaded(s, info).await?.model)
}

/// A model and its transient maps, loaded from its checkpoint (on the
/// blocking threads) once and kept while its record has not changed.
pub(super) async fn loaded(s: &AppInner, info: &ModelInfo) -> ApiResult<CachedModel> {
    {
        let cache = s.model_cache.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(c) = cache.iter().find(|c| c.id == info.id && c.updated_at == info.updated_at) {
            return Ok(c.clone());
        }
    }
    let ckpt = s.artifacts.checkpoint(info).await?;
    let restored = tokio::task::spawn_blocking(move || load_checkpoint(&ckpt.path)).await?;
    let restored = restored.map_err(|e| match e {
        // Deleted since its record was read.
        CheckpointError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            ApiError::not_found("model", &info.id)
        }
        e => e.into(),
    })?;
    let model: Arc<dyn Model> = Arc::from(restored.model);
    let cropped = match info.crop {
        None => None,
        Some(b) => {
            let m = model.clone();
            let made = tokio::task::spawn_blocking(move || crop_model(&*m, &b)).await?;
            Some(made.map(|c| c.map(|c| Arc::new(c) as Arc<dyn Model>)).map_err(|e| e.to_string()))
        }
    };
    let loaded = CachedModel {
        id: info.id.clone(),
        updated_at: info.updated_at,
        model,
        transients: restored.transients.map(Arc::new),
        cropped,
    };
    let mut cache = s.model_cache.lock().unwrap_or_else(|e| e.into_inner());
    cache.retain(|c| c.id != info.id);
    cache.insert(0, loaded.clone());
    cache.truncate(4);
    Ok(loaded)
}

/// The image the query asked for.
fn image_of(output: Output, background: Background, far: f32) -> ViewImage {
    match (output, background) {
        (Output::Rgb, Background::Colour(_)) => ViewImage::Rgb,
        // Rendered on black, the colour is premultiplied: media divides it out.
        (Output::Rgb, Background::Transparent) => ViewImage::Rgba,
        (Output::Alpha, _) => ViewImage::Alpha,
        (Output::Depth, _) => ViewImage::Depth { far },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> ViewDefaults {
        ViewDefaults { width: 8, height: 8, fov: 50.0, radius: 4.0, far: 6.0, ..crate::records::sample_view() }
    }

    /// The `details` of the error a render query gets.
    fn details_of(q: RenderQuery) -> serde_json::Value {
        let e = parse_query(&q, &view(), 1 << 20).expect_err("refused");
        assert_eq!(e.code, crate::api::Code::BadRequest);
        e.details
    }

    #[test]
    fn bad_render_parameters_are_named_with_their_value() {
        use serde_json::json;
        let fov = details_of(RenderQuery { fov: Some(0.0), ..Default::default() });
        assert_eq!(fov, json!({ "field": "fov", "value": 0.0, "allowed": "(1, 179)" }));
        let out = details_of(RenderQuery { output: Some("nope".into()), ..Default::default() });
        assert_eq!(out, json!({ "field": "output", "value": "nope", "allowed": "rgb, depth, alpha" }));
        let bg = details_of(RenderQuery { background: Some("red".into()), ..Default::default() });
        assert_eq!((bg["field"].as_str(), bg["value"].as_str()), (Some("background"), Some("red")));
        let el = details_of(RenderQuery { elevation: Some(91.0), ..Default::default() });
        assert_eq!(el, json!({ "field": "elevation", "value": 91.0, "allowed": "[-90, 90]" }));
        let r = details_of(RenderQuery { radius: Some(-1.0), ..Default::default() });
        assert_eq!((r["field"].as_str(), r["value"].as_f64()), (Some("radius"), Some(-1.0)));
        let size = details_of(RenderQuery { width: Some(2000), height: Some(2000), ..Default::default() });
        assert_eq!((size["field"].as_str(), &size["value"]), (Some("width,height"), &json!([2000, 2000])));
        assert!(size["allowed"].as_str().unwrap().contains("1048576 pixels"), "{size}");
        let c2w = details_of(RenderQuery { c2w: Some("1,2,3".into()), ..Default::default() });
        assert_eq!((c2w["field"].as_str(), c2w["value"].as_str()), (Some("c2w"), Some("1,2,3")));
        assert!(parse_query(&RenderQuery::default(), &view(), 1 << 20).is_ok());
        for bad in ["nearest", "Mean", "-3", "1e3", "99999999999"] {
            let a = details_of(RenderQuery { appearance: Some(bad.into()), ..Default::default() });
            assert_eq!(a, json!({ "field": "appearance", "value": bad, "allowed": APPEARANCE }));
        }
    }

    #[test]
    fn appearance_is_mean_or_an_index() {
        let q = |a: Option<&str>| RenderQuery { appearance: a.map(str::to_string), ..Default::default() };
        let appearance = |a| parse_query(&q(a), &view(), 1 << 20).unwrap().appearance;
        assert_eq!(appearance(None), Appearance::Mean);
        assert_eq!(appearance(Some("mean")), Appearance::Mean);
        assert_eq!(appearance(Some("12")), Appearance::Image(12));
    }

    #[test]
    fn c2w_checks() {
        assert!(parse_c2w("1,0,0,0, 0,1,0,0, 0,0,1,4").is_ok());
        assert!(parse_c2w("1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1").is_ok());
        assert!(parse_c2w("1,0,0,0, 0,1,0,0, 0,0,1").is_err());
        assert!(parse_c2w("2,0,0,0, 0,1,0,0, 0,0,1,4").is_err());
        assert!(parse_c2w("NaN,0,0,0, 0,1,0,0, 0,0,1,4").is_err());
    }
}
